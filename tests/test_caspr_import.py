"""CASPR importer: the five shipped models, numbers checked against the XML text, CLI and errors."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.rotations import rotation_from_euler
from cdpr.pipelines.caspr import import_caspr
from cdpr.pipelines.cli import main
from cdpr.pipelines.config import load_rig

CASPR = Path(__file__).resolve().parents[1] / "data_samples" / "caspr"
MODELS = ["IPAnema_1", "IPAnema_2", "CoGiRo", "CAROCA", "SEGESTA"]


def _cables_in_default_set(model: str) -> int:
    """Count <cable_ideal> tags in the default cable set by plain text search (independent of ET)."""
    text = (CASPR / f"{model}_cables.xml").read_text()
    default = re.search(r'default_cable_set="([^"]+)"', text).group(1)
    start = text.index(f'<cable_set id="{default}">')
    end = text.index("</cable_set>", start)
    return text[start:end].count("<cable_ideal")


@pytest.mark.parametrize("model", MODELS)
def test_every_model_imports_with_full_rank(model: str) -> None:
    rig = import_caspr(CASPR / f"{model}_bodies.xml")
    assert rig.n_cables == _cables_in_default_set(model)
    A = structure_matrix(
        rig.anchors_O_m,
        rig.attach_P_m,
        rig.reference_position_O_m,
        rotation_from_euler(rig.reference_euler_rad),
    )
    assert A.shape == (6, rig.n_cables)
    sv = np.linalg.svd(A, compute_uv=False)
    assert sv[-1] > 1e-3 * sv[0], f"{model}: singular values {sv}"


def test_numbers_against_the_xml_by_hand() -> None:
    # IPAnema_1, cable 1: base (-2.0 1.5 2.0), platform (-0.06 0.06 0.0), force 0..720; mass 25;
    # q_initial "0 0 1.0 0 0 0"
    r = import_caspr(CASPR / "IPAnema_1_bodies.xml")
    np.testing.assert_array_equal(r.anchors_O_m[0], [-2.0, 1.5, 2.0])
    np.testing.assert_array_equal(r.attach_P_m[0], [-0.06, 0.06, 0.0])
    np.testing.assert_array_equal(r.anchors_O_m[7], [-2.0, -1.5, 0.0])  # cable 8
    assert (r.t_min_N[0], r.t_max_N[0]) == (0.0, 720.0)
    assert r.mass_kg == 25.0
    np.testing.assert_array_equal(r.reference_position_O_m, [0, 0, 1.0])
    np.testing.assert_array_equal(r.inertia_P_kgm2, np.diag([14.0, 14.0, 14.0]))
    assert r.cable_names[0] == "cable_1"
    # IPAnema_2 cable 1: (-4.0 3.0 5.0), (-0.65 0.125 0.25), 0..200 N; mass 10; z0 = 3.0
    r = import_caspr(CASPR / "IPAnema_2_bodies.xml")
    np.testing.assert_array_equal(r.anchors_O_m[0], [-4.0, 3.0, 5.0])
    np.testing.assert_array_equal(r.attach_P_m[0], [-0.65, 0.125, 0.25])
    assert r.t_max_N[0] == 200.0 and r.mass_kg == 10.0
    np.testing.assert_array_equal(r.reference_position_O_m, [0, 0, 3.0])
    # SEGESTA cable 1: (0.7400 -0.6790 0.0000), (0.0400 0.0000 0.0350), 0..5000 N, mass 0.125
    r = import_caspr(CASPR / "SEGESTA_bodies.xml")
    np.testing.assert_array_equal(r.anchors_O_m[0], [0.74, -0.679, 0.0])
    np.testing.assert_array_equal(r.attach_P_m[0], [0.04, 0.0, 0.035])
    assert r.t_max_N[0] == 5000.0 and r.mass_kg == 0.125
    # CAROCA cable "1" (default set "original"): (1.659 -2.850 3.221), (0.16 0.14 0.105)
    r = import_caspr(CASPR / "CAROCA_bodies.xml")
    assert r.cable_names[0] == "cable_1"
    np.testing.assert_array_equal(r.anchors_O_m[0], [1.659, -2.850, 3.221])
    np.testing.assert_array_equal(r.attach_P_m[0], [0.16, 0.14, 0.105])
    assert r.mass_kg == 150.0
    np.testing.assert_array_equal(r.inertia_P_kgm2, np.diag([6.5, 20.0, 22.5]))
    # CAROCA by cable-set id: "gazebo_sim" cable 1: (-3.5 -2.0 3.5), (0.6 -0.3 -0.2)
    r = import_caspr(CASPR / "CAROCA_bodies.xml", cable_set="gazebo_sim")
    np.testing.assert_array_equal(r.anchors_O_m[0], [-3.5, -2.0, 3.5])
    np.testing.assert_array_equal(r.attach_P_m[0], [0.6, -0.3, -0.2])
    # IPAnema_1 IROS_CASPR_2016 set, cable 1: (-2.0 3.0 5.0), (0.65 0.125 0.25)
    r = import_caspr(CASPR / "IPAnema_1_bodies.xml", cable_set="IROS_CASPR_2016")
    np.testing.assert_array_equal(r.anchors_O_m[0], [-2.0, 3.0, 5.0])
    np.testing.assert_array_equal(r.attach_P_m[0], [0.65, 0.125, 0.25])


def test_cogiro_inertia_moved_to_the_joint_by_hand() -> None:
    # CoGiRo: m = 91.058, com (-0.034 -0.013 0.264), I about com: Ixx 36.598, Iyy 35.982, Izz 25.439,
    # Ixy -0.453, Ixz 3.012, Iyz -1.539 (tensor entries).  Parallel axis: I_P = I_G + m (|c|^2 1 - c c^T)
    m, (cx, cy, cz) = 91.058, (-0.034, -0.013, 0.264)
    r = import_caspr(CASPR / "CoGiRo_bodies.xml")
    assert r.inertia_P_kgm2[0, 0] == pytest.approx(36.598 + m * (cy**2 + cz**2), abs=1e-9)
    assert r.inertia_P_kgm2[1, 1] == pytest.approx(35.982 + m * (cx**2 + cz**2), abs=1e-9)
    assert r.inertia_P_kgm2[2, 2] == pytest.approx(25.439 + m * (cx**2 + cy**2), abs=1e-9)
    assert r.inertia_P_kgm2[0, 1] == pytest.approx(-0.453 - m * cx * cy, abs=1e-9)
    assert r.inertia_P_kgm2[0, 2] == pytest.approx(3.012 - m * cx * cz, abs=1e-9)
    assert r.inertia_P_kgm2[1, 2] == pytest.approx(-1.539 - m * cy * cz, abs=1e-9)
    np.testing.assert_array_equal(r.com_P_m, [cx, cy, cz])
    assert r.t_min_N[0] == 100.0 and r.t_max_N[0] == 5000.0


BODY = """<?xml version="1.0" encoding="utf-8"?>
<bodies_system><links>
  <link_rigid num="1" name="synthetic">
    <joint type="SPATIAL_EULER_XYZ" q_initial="{q}"/>
    <physical><mass>2.0</mass><com_location>0.1 0 0</com_location><end_location>0 0 0</end_location>
      <inertia ref="com"><Ixx>1</Ixx><Iyy>1</Iyy><Izz>1</Izz><Ixy>0</Ixy><Ixz>0</Ixz><Iyz>0</Iyz></inertia>
    </physical>
    <parent><num>0</num><location>1.0 2.0 0.5</location></parent>
  </link_rigid>{extra}
</links></bodies_system>
"""

CABLE = """<cable_ideal name="{name}" attachment_reference="{ref}">{props}
  <attachments>
    <attachment><link>0</link><location>{b}</location></attachment>
    <attachment><link>1</link><location>{p}</location></attachment>
  </attachments></cable_ideal>"""


def _cables_xml(ref: str = "joint", props: bool = True) -> str:
    pts = [
        (-2, -2, 3),
        (2, -2, 3),
        (2, 2, 3),
        (-2, 2, 3),
        (-2, -2, 0),
        (2, -2, 0),
        (2, 2, 0),
        (-2, 2, 0),
    ]
    plat = [(-0.1, -0.1, 0.1), (0.1, -0.1, 0.1), (0.1, 0.1, 0.1), (-0.1, 0.1, 0.1)] * 2
    prop = "<properties><force_min>5</force_min><force_max>50</force_max></properties>"
    body = "".join(
        CABLE.format(
            name=f"c {i}",
            ref=ref,
            props=prop if props else "",
            b=" ".join(map(str, b)),
            p=" ".join(map(str, p)),
        )
        for i, (b, p) in enumerate(zip(pts, plat, strict=True))
    )
    return f'<cables default_cable_set="s"><cable_set id="s">{body}</cable_set></cables>'


def test_initial_angles_position_com_reference_and_default_limits(tmp_path: Path) -> None:
    (tmp_path / "X_bodies.xml").write_text(BODY.format(q="0.1 0.2 0.3 0.1 0.2 0.3", extra=""))
    (tmp_path / "X_cables.xml").write_text(_cables_xml(ref="com", props=False))
    r = import_caspr(tmp_path / "X_bodies.xml", default_t_min_N=7.0, default_t_max_N=70.0)
    # CASPR XYZ Euler: R = Rx(a) Ry(b) Rz(c) = scipy intrinsic "XYZ"
    R_expect = Rotation.from_euler("XYZ", [0.1, 0.2, 0.3]).as_matrix()
    np.testing.assert_allclose(rotation_from_euler(r.reference_euler_rad), R_expect, atol=1e-12)
    np.testing.assert_allclose(r.reference_position_O_m, [1.1, 2.2, 0.8], atol=1e-15)
    # attachment_reference="com": platform point = com + location
    np.testing.assert_allclose(r.attach_P_m[0], [0.0, -0.1, 0.1], atol=1e-15)
    assert np.all(r.t_min_N == 7.0) and np.all(r.t_max_N == 70.0)
    assert "default" in r.assumptions["tension_limits"]


def test_errors_name_file_and_element(tmp_path: Path) -> None:
    link2 = BODY.split("<links>")[1].split("</links>")[0].replace('num="1"', 'num="2"')
    (tmp_path / "M_bodies.xml").write_text(BODY.format(q="0 0 1 0 0 0", extra=link2))
    (tmp_path / "M_cables.xml").write_text(_cables_xml())
    with pytest.raises(ConfigError, match=r"M_bodies\.xml: links/link_rigid\[2\]: multi-link"):
        import_caspr(tmp_path / "M_bodies.xml")
    (tmp_path / "T_bodies.xml").write_text(BODY.format(q="0 0 1 0 0 0", extra="")[:300])
    with pytest.raises(ConfigError, match=r"T_bodies\.xml: line \d+, column \d+: malformed XML"):
        import_caspr(tmp_path / "T_bodies.xml", tmp_path / "M_cables.xml")
    with pytest.raises(ConfigError, match=r"CAROCA_cables\.xml: .*base_rotating_pulley"):
        import_caspr(CASPR / "CAROCA_bodies.xml", cable_set="with_rotating_pulleys")
    with pytest.raises(ConfigError, match=r"cable_set\[id=nope\]: not found"):
        import_caspr(CASPR / "CAROCA_bodies.xml", cable_set="nope")
    bomb = (
        '<?xml version="1.0"?><!DOCTYPE b [<!ENTITY a "aaaa">]><bodies_system>&a;</bodies_system>'
    )
    (tmp_path / "E_bodies.xml").write_text(bomb)
    with pytest.raises(ConfigError, match=r"E_bodies\.xml: DOCTYPE: entity declarations"):
        import_caspr(tmp_path / "E_bodies.xml", tmp_path / "M_cables.xml")
    with pytest.raises(ConfigError, match=r"nothere_bodies\.xml: file not found"):
        import_caspr(tmp_path / "nothere_bodies.xml")
    bad = BODY.format(q="0 0 1 0 0 0", extra="").replace("<mass>2.0</mass>", "<mass>heavy</mass>")
    (tmp_path / "B_bodies.xml").write_text(bad)
    with pytest.raises(ConfigError, match=r"B_bodies\.xml: link_rigid\[num=1\]/physical/mass"):
        import_caspr(tmp_path / "B_bodies.xml", tmp_path / "M_cables.xml")


def test_cli_import_then_solve(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ipanema2.toml"
    assert (
        main(["rig", "import-caspr", str(CASPR / "IPAnema_2_bodies.xml"), "--out", str(out)]) == 0
    )
    rig = load_rig(out)
    assert rig.n_cables == 8 and rig.mass_kg == 10.0
    np.testing.assert_array_equal(rig.anchors_O_m[0], [-4.0, 3.0, 5.0])
    assert "sha256=" in out.read_text()
    tens = tmp_path / "t.csv"
    args = ["solve", "--rig", str(out), "--method", "closed-form", "--out", str(tens)]
    assert main(args) == 0
    df = pd.read_csv(tens, comment="#")
    assert len(df) == 1 and df["residual_N"].iloc[0] < 1e-6
    # equilibrium against gravity, checked with an independent structure matrix: sum T_i u_i = m g
    T = df[[f"T_cable_{i}_N" for i in range(1, 9)]].to_numpy()[0]
    p = np.array([0.0, 0.0, 3.0])
    d = rig.anchors_O_m - (p + rig.attach_P_m)
    F = (T[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True)).sum(axis=0)
    np.testing.assert_allclose(F, [0, 0, 10.0 * 9.80665], atol=1e-6)
    # bad cable set via the CLI: exit 2, one line, no file
    bad = tmp_path / "bad.toml"
    capsys.readouterr()
    code = main(
        ["rig", "import-caspr", str(CASPR / "CAROCA_bodies.xml")]
        + ["--cable-set", "with_rotating_pulleys", "--out", str(bad)]
    )
    assert code == 2 and not bad.exists()
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
