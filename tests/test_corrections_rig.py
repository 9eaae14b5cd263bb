"""Rig-file keys for cable diameter, drag coefficient and EA; `cdpr rig show` prints the modes."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rig import (
    DEFAULT_CABLE_DIAMETER_M,
    DEFAULT_CABLE_EA_N,
    rig_to_mapping,
)
from cdpr.analysis.rigs import flat_rig
from cdpr.daq.schema import rig_from_mapping
from cdpr.pipelines.cli import main


def _mapping() -> dict:
    return rig_to_mapping(flat_rig(51, 28, 0.67, 0.5))


def test_defaults_and_round_trip() -> None:
    rig = rig_from_mapping(_mapping())
    assert np.all(rig.cable_diameter_m == DEFAULT_CABLE_DIAMETER_M)
    assert np.all(rig.cable_EA_N == DEFAULT_CABLE_EA_N)
    assert np.all(np.isnan(rig.cable_drag_coefficient)) and rig.platform_drag_area_m2 == 0.0
    assert "diameter_m" not in _mapping()["cables"][0]  # defaults are not written
    d = _mapping()
    d["cables"][2].update(diameter_m=0.0015, drag_coefficient=1.2, EA_N=9.0e4)
    d["platform"]["windage_drag_area_m2"] = 1e-4
    rig = rig_from_mapping(d)
    assert rig.cable_diameter_m[2] == 0.0015 and rig.cable_EA_N[2] == 9.0e4
    assert rig.cable_drag_coefficient[2] == 1.2 and math.isnan(rig.cable_drag_coefficient[0])
    again = rig_from_mapping(rig_to_mapping(rig))
    assert rig_to_mapping(again) == rig_to_mapping(rig)
    assert again.platform_drag_area_m2 == 1e-4


@pytest.mark.parametrize(
    ("key", "value", "where"),
    [
        ("diameter_m", -0.001, "cables[3].diameter_m"),
        ("EA_N", "stiff", "cables[3].EA_N"),
        ("drag_coefficient", 0.0, "cables[3].drag_coefficient"),
    ],
)
def test_bad_keys_name_file_and_key(key: str, value: object, where: str) -> None:
    d = _mapping()
    d["cables"][3][key] = value
    with pytest.raises(ConfigError) as info:
        rig_from_mapping(d, source="rig.toml")
    assert info.value.source == "rig.toml" and info.value.key == where


def test_rig_show_prints_six_modes(tmp_path: Path, capsys) -> None:
    path = tmp_path / "rig.toml"
    path.write_text(tomli_w.dumps(_mapping()))
    assert main(["rig", "show", str(path)]) == 0
    out = capsys.readouterr().out
    freqs = [float(x) for x in re.findall(r"mode \d: +([0-9.]+) Hz", out)]
    assert len(freqs) == 6 and freqs == sorted(freqs) and freqs[0] > 0
    assert "EA = 70000 N" in out


def test_rig_show_bad_key_exits_2(tmp_path: Path, capsys) -> None:
    d = _mapping()
    d["cables"][0]["EA_N"] = -5.0
    path = tmp_path / "rig.toml"
    path.write_text(tomli_w.dumps(d))
    assert main(["rig", "show", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "cables[0].EA_N" in err[0]
