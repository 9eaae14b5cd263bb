"""The [tunnel]/[model] loader: the paper's octagon, and one-line errors naming file and key."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest

from cdpr.analysis.errors import ConfigError
from cdpr.pipelines.tunnel_section import tunnel_section_from_mapping

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "tunnel_section_octagon.toml"


def _data() -> dict:
    return tomllib.loads(SAMPLE.read_text())


def test_paper_octagon_loads() -> None:
    ts = tunnel_section_from_mapping(_data(), str(SAMPLE))
    # regular octagon of side a: area 2 (1 + sqrt 2) a^2 = 4.828427 * 0.141376 = 0.682624 m^2
    assert ts.walls.area_m2 == pytest.approx(0.682624, rel=1e-6)
    assert ts.geometry.x_end_m - ts.geometry.x_start_m == pytest.approx(1.075)
    # width across flats a (1 + sqrt 2) = 0.907744 m
    ys = ts.geometry.polygon_yz_m[:, 0]
    assert ys.max() - ys.min() == pytest.approx(0.907744, rel=1e-6)
    ar = 0.2441**2 / 0.0125
    assert ts.walls.lift_slope_per_rad == pytest.approx(2 * math.pi * ar / (ar + 2))
    assert len(ts.notes) == 1 and "lift slope not given" in ts.notes[0]


@pytest.mark.parametrize(
    ("table", "key", "value", "where"),
    [
        ("tunnel", "kind", "slotted", "tunnel.kind"),
        ("tunnel", "colour", "red", "tunnel.colour"),
        ("tunnel", "octagon_side_m", -1.0, "tunnel.octagon_side_m"),
        ("tunnel", "delta", -0.125, "tunnel.delta"),
        ("model", "volume_m3", "big", "model.volume_m3"),
        ("tunnel", "polygon_yz_m", [[0, 0], [1, 1], [1, 0]], "tunnel.polygon_yz_m"),
    ],
)
def test_bad_values_name_the_key(table: str, key: str, value: object, where: str) -> None:
    d = _data()
    d[table][key] = value
    if key == "polygon_yz_m":
        d["tunnel"]["shape"] = "polygon"
    with pytest.raises(ConfigError) as info:
        tunnel_section_from_mapping(d, "matrix.toml")
    assert info.value.source == "matrix.toml" and info.value.key == where


def test_missing_required_factor() -> None:
    d = _data()
    del d["tunnel"]["tau1"]
    with pytest.raises(ConfigError, match="tunnel.tau1: missing"):
        tunnel_section_from_mapping(d, "matrix.toml")
