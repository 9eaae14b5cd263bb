"""The schema library (pydantic) and its one error formatter: file, key, problem.

Expected messages are written by hand from the rig-file layout (docs) and the schema's ranges.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from cdpr.analysis.errors import ConfigError
from cdpr.daq.aero_model import AeroModel, aero_from_mapping
from cdpr.daq.schema import load_rig, rig_from_mapping

ROOT = Path(__file__).resolve().parents[1]
A0 = "anchor_O_m = [0.0, 0.255, 0.67]"
RIG_TEXT = (ROOT / "data_samples" / "flat_optimum.toml").read_text()


def _error(text: str, tmp_path: Path) -> str:
    p = tmp_path / "r.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_rig(p)
    msg = str(info.value)
    assert msg.startswith(f"{p}: ") and "\n" not in msg
    return msg.removeprefix(f"{p}: ")


@pytest.mark.parametrize(
    "old,new,expected",
    [
        ("mass_kg = 0.64", "mass_kg = nan", "platform.mass_kg: expected a finite number, got nan"),
        ("mass_kg = 0.64", 'mass_kg = "0.64"', "platform.mass_kg: expected a valid number, got '0.64'"),
        ("mass_kg = 0.64", "mass_kg = true", "platform.mass_kg: expected a valid number, got True"),
        ("mass_kg = 0.64", "mass_kg = -1", "platform.mass_kg: must be > 0.0, got -1"),
        ("mass_kg = 0.64", "mass_kg = 1e300", "platform.mass_kg: must be <= 1000000.0"),
        ("mass_kg = 0.64", "mass = 0.64", "platform.mass_kg: missing"),
        ("t_min_N = 35.0", "t_min_N = -1.0", "cables[0].t_min_N: must be >= 0.0, got -1.0"),
        (A0, "anchor_O_m = [0.0, 0.255]", "cables[0].anchor_O_m: expected at least 3 numbers, got 2"),
        (A0, "anchor_O_m = [0.0, 0.255, inf]", "cables[0].anchor_O_m[2]: expected a finite number"),
        (A0, A0 + "\ncolour = 1", "cables[0].colour: unknown key"),
    ],
)  # fmt: skip
def test_rig_errors_name_the_key_and_the_problem(tmp_path, old, new, expected):
    assert old in RIG_TEXT
    assert _error(RIG_TEXT.replace(old, new, 1), tmp_path).startswith(expected)


def test_rig_invariants_still_checked_after_the_schema():
    d = tomllib.loads(RIG_TEXT)
    d["cables"][1]["name"] = d["cables"][0]["name"]
    with pytest.raises(ConfigError, match="cables.name: cable names must be unique"):
        rig_from_mapping(d, "x.toml")


def test_rig_round_trip_keeps_every_value():
    rig = load_rig(ROOT / "data_samples" / "flat_optimum.toml")
    d = tomllib.loads(RIG_TEXT)
    assert rig.mass_kg == d["platform"]["mass_kg"]
    assert rig.anchors_O_m.tolist() == [c["anchor_O_m"] for c in d["cables"]]
    assert rig.cable_names == tuple(c["name"] for c in d["cables"])


def test_aero_section():
    assert aero_from_mapping({}, "s.toml") == AeroModel()
    m = aero_from_mapping({"b_ref_m": 0.5, "mrp_P_m": [0.0, 0.0, 0.01]}, "s.toml")
    assert m.s_ref_m2 == 0.5 * AeroModel.c_ref_m and m.mrp_P_m == (0.0, 0.0, 0.01)
    cases = [
        ({"c_ref_m": 1e300}, "s.toml: aero.c_ref_m: must be <= 100.0"),
        ({"CL_alpha": "3.5"}, "s.toml: aero.CL_alpha: expected a valid number, got '3.5'"),
        ({"static_pressure_Pa": 0}, "s.toml: aero.static_pressure_Pa: must be > 0.0, got 0"),
        ({"mrp_P_m": [0, 0]}, "s.toml: aero.mrp_P_m: expected at least 3 numbers, got 2"),
        ({"spin": 1.0}, "s.toml: aero.spin: unknown key"),
    ]
    for data, expected in cases:
        with pytest.raises(ConfigError) as info:
            aero_from_mapping(data, "s.toml")
        assert str(info.value).startswith(expected), str(info.value)
