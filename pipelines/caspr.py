"""Import a single-body cable robot from CASPR's XML model files into a :class:`Rig`.

CASPR (Lau et al., BSD licence) describes a robot with two files:

- ``*_bodies.xml``: ``<bodies_system><links><link_rigid num="1">`` with a ``<joint type=...
  q_initial=...>``, ``<physical>`` (``mass``, ``com_location``, ``inertia ref="com"|"joint"`` with
  ``Ixx Iyy Izz Ixy Ixz Iyz``: the entries of the inertia tensor, off-diagonals as they stand in the
  matrix) and ``<parent><num>0</num><location>`` (the joint origin in the base frame);
- ``*_cables.xml``: ``<cables default_cable_set="ID"><cable_set id="ID"><cable_ideal name=...
  attachment_reference="joint"|"com">`` with ``<properties><force_min>, <force_max>`` and two
  ``<attachment><link>k</link><location>x y z</location>`` (k = 0: base frame, k = 1: platform).

Mapping onto the rig model: {O} is CASPR's base frame (link 0) and {P} the platform's joint frame, so
anchors are the link-0 locations and platform points the link-1 locations (plus ``com_location``
when ``attachment_reference="com"``).  The reference pose is ``parent location + q_initial``; the
joint type ``SPATIAL_EULER_XYZ`` orders the angles as X-Y-Z Euler angles, ``R = Rx(a) Ry(b) Rz(c)``,
converted to this project's Z-Y-X angles through the rotation matrix.  The inertia is moved to P
(parallel-axis theorem) when given about the centre of mass.  Tension limits come from
``force_min``/``force_max``; a cable without them gets the defaults passed in (documented in the rig's
``[assumptions]``).  Only single-body models with ideal (straight, point-to-point) cables are
supported; anything else raises :class:`~cdpr.analysis.errors.ConfigError` naming file and element.
"""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rig import Rig
from cdpr.analysis.rotations import euler_from_rotation
from cdpr.daq.schema import rig_from_mapping

DEFAULT_T_MIN_N = 0.0
"""Lower tension limit (N) for a cable whose model gives none."""

DEFAULT_T_MAX_N = 1000.0
"""Upper tension limit (N) for a cable whose model gives none."""

SUPPORTED_JOINTS = ("SPATIAL_EULER_XYZ",)


@dataclass(frozen=True)
class CasprCable:
    """One ideal cable as read from the XML (numbers exactly as written, SI)."""

    name: str
    anchor_m: tuple[float, float, float]
    attach_m: tuple[float, float, float]
    attachment_reference: str
    force_min_N: float | None
    force_max_N: float | None


def _parse(path: str | os.PathLike[str]) -> ET.Element:
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise ConfigError(str(p), "", "file not found") from None
    except OSError as exc:
        raise ConfigError(str(p), "", f"cannot read: {exc.strerror}") from None
    if b"<!ENTITY" in data:
        # CASPR files never declare entities; refusing them rules out entity-expansion attacks
        raise ConfigError(str(p), "DOCTYPE", "entity declarations are not supported")
    try:
        return ET.fromstring(data)
    except ET.ParseError as exc:
        line, col = exc.position
        raise ConfigError(str(p), f"line {line}, column {col}", f"malformed XML: {exc}") from None


def _text(src: str, parent: ET.Element, tag: str, where: str) -> str:
    el = parent.find(tag)
    if el is None or el.text is None or not el.text.strip():
        raise ConfigError(src, f"{where}/{tag}", "missing")
    return el.text.strip()


def _floats(src: str, text: str, where: str, n: int) -> list[float]:
    try:
        vals = [float(v) for v in text.split()]
    except ValueError:
        raise ConfigError(src, where, f"expected {n} numbers, got {text!r}") from None
    if len(vals) != n or not all(np.isfinite(vals)):
        raise ConfigError(src, where, f"expected {n} finite numbers, got {text!r}")
    return vals


def _number(src: str, parent: ET.Element, tag: str, where: str) -> float:
    return _floats(src, _text(src, parent, tag, where), f"{where}/{tag}", 1)[0]


def _rot_xyz(a: float, b: float, c: float) -> np.ndarray:
    """CASPR's SPATIAL_EULER_XYZ rotation ``Rx(a) Ry(b) Rz(c)``."""
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    Rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    Ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    Rz = np.array([[cc, -sc, 0], [sc, cc, 0], [0, 0, 1]])
    return Rx @ Ry @ Rz


@dataclass(frozen=True)
class CasprBody:
    """The platform of a single-body CASPR model."""

    name: str
    mass_kg: float
    com_m: np.ndarray
    inertia_P_kgm2: np.ndarray
    position_m: np.ndarray
    euler_zyx_rad: np.ndarray
    joint_type: str


def read_caspr_bodies(path: str | os.PathLike[str]) -> CasprBody:
    """Read the platform of a single-body CASPR ``*_bodies.xml``.

    Inertia returned about P (the joint frame origin) in {P} axes; pose as position (m) and this
    project's Z-Y-X Euler angles (rad).
    """
    src = str(path)
    root = _parse(path)
    if root.tag != "bodies_system":
        raise ConfigError(src, root.tag, "expected a <bodies_system> root element")
    links = root.find("links")
    if links is None:
        raise ConfigError(src, "bodies_system/links", "missing")
    bodies = list(links)
    rigid = [b for b in bodies if b.tag == "link_rigid"]
    other = [b for b in bodies if b.tag != "link_rigid"]
    if other:
        raise ConfigError(src, f"links/{other[0].tag}", "unsupported link type (only link_rigid)")
    if len(rigid) != 1:
        raise ConfigError(
            src,
            f"links/link_rigid[{min(len(rigid), 2)}]",
            f"multi-link models are not supported: expected 1 link_rigid, got {len(rigid)}",
        )
    link = rigid[0]
    where = f"link_rigid[num={link.get('num')}]"
    joint = link.find("joint")
    if joint is None:
        raise ConfigError(src, f"{where}/joint", "missing")
    jtype = joint.get("type", "")
    if jtype not in SUPPORTED_JOINTS:
        raise ConfigError(
            src,
            f"{where}/joint",
            f"unsupported joint type {jtype!r} (supported: {SUPPORTED_JOINTS})",
        )
    q0 = _floats(src, joint.get("q_initial", "0 0 0 0 0 0"), f"{where}/joint@q_initial", 6)
    phys = link.find("physical")
    if phys is None:
        raise ConfigError(src, f"{where}/physical", "missing")
    pw = f"{where}/physical"
    mass = _number(src, phys, "mass", pw)
    if mass <= 0:
        raise ConfigError(src, f"{pw}/mass", f"must be > 0 kg, got {mass}")
    com = np.array(_floats(src, _text(src, phys, "com_location", pw), f"{pw}/com_location", 3))
    inertia_el = phys.find("inertia")
    if inertia_el is None:
        raise ConfigError(src, f"{pw}/inertia", "missing")
    iw = f"{pw}/inertia"
    v = {k: _number(src, inertia_el, k, iw) for k in ("Ixx", "Iyy", "Izz", "Ixy", "Ixz", "Iyz")}
    I_ref = np.array(
        [
            [v["Ixx"], v["Ixy"], v["Ixz"]],
            [v["Ixy"], v["Iyy"], v["Iyz"]],
            [v["Ixz"], v["Iyz"], v["Izz"]],
        ]
    )
    ref = inertia_el.get("ref", "")
    if ref == "com":
        I_P = I_ref + mass * (float(com @ com) * np.eye(3) - np.outer(com, com))
    elif ref == "joint":
        I_P = I_ref
    else:
        raise ConfigError(src, f"{iw}@ref", f"expected 'com' or 'joint', got {ref!r}")
    parent = link.find("parent")
    if parent is None:
        raise ConfigError(src, f"{where}/parent", "missing")
    pnum = _text(src, parent, "num", f"{where}/parent")
    if pnum != "0":
        raise ConfigError(src, f"{where}/parent/num", f"expected the base (0), got {pnum}")
    ploc = _floats(src, _text(src, parent, "location", f"{where}/parent"), f"{where}/parent", 3)
    R = _rot_xyz(*q0[3:])
    return CasprBody(
        name=link.get("name", "") or Path(src).stem,
        mass_kg=mass,
        com_m=com,
        inertia_P_kgm2=I_P,
        position_m=np.array(ploc) + np.array(q0[:3]),
        euler_zyx_rad=euler_from_rotation(R) + 0.0,  # no negative zeros
        joint_type=jtype,
    )


def read_caspr_cables(
    path: str | os.PathLike[str], cable_set: str | None = None
) -> tuple[str, list[CasprCable]]:
    """Read one cable set (default: ``default_cable_set``, else the first) of a ``*_cables.xml``.

    Returns the set id and its cables.
    """
    src = str(path)
    root = _parse(path)
    if root.tag != "cables":
        raise ConfigError(src, root.tag, "expected a <cables> root element")
    sets = root.findall("cable_set")
    if not sets:
        raise ConfigError(src, "cables/cable_set", "missing: no cable set in the file")
    ids = [s.get("id", "") for s in sets]
    want = cable_set or root.get("default_cable_set") or ids[0]
    if want not in ids:
        raise ConfigError(src, f"cable_set[id={want}]", f"not found (have: {ids})")
    cset = sets[ids.index(want)]
    cables: list[CasprCable] = []
    for k, el in enumerate(cset):
        where = f"cable_set[id={want}]/{el.tag}[{k + 1}]"
        if el.tag != "cable_ideal":
            raise ConfigError(src, where, "unsupported cable type (only cable_ideal)")
        name = el.get("name", f"cable {k + 1}")
        where = f"cable_set[id={want}]/cable_ideal[name={name}]"
        ref = el.get("attachment_reference", "joint")
        if ref not in ("joint", "com"):
            raise ConfigError(src, f"{where}@attachment_reference", f"unsupported: {ref!r}")
        props = el.find("properties")
        fmin = fmax = None
        if props is not None:
            if props.find("force_min") is not None:
                fmin = _number(src, props, "force_min", f"{where}/properties")
            if props.find("force_max") is not None:
                fmax = _number(src, props, "force_max", f"{where}/properties")
        att = el.find("attachments")
        if att is None:
            raise ConfigError(src, f"{where}/attachments", "missing")
        unsupported = [a.tag for a in att if a.tag != "attachment"]
        if unsupported:
            raise ConfigError(
                src, f"{where}/attachments/{unsupported[0]}", "unsupported (only point attachments)"
            )
        points: dict[str, list[float]] = {}
        for a in att:
            link = _text(src, a, "link", f"{where}/attachment")
            points[link] = _floats(src, _text(src, a, "location", f"{where}/attachment"), where, 3)
        if sorted(points) != ["0", "1"] or len(att) != 2:
            raise ConfigError(
                src,
                f"{where}/attachments",
                f"expected one attachment on link 0 and one on link 1, got links {list(points)}",
            )
        a0, a1 = points["0"], points["1"]
        cables.append(
            CasprCable(
                name=name,
                anchor_m=(a0[0], a0[1], a0[2]),
                attach_m=(a1[0], a1[1], a1[2]),
                attachment_reference=ref,
                force_min_N=fmin,
                force_max_N=fmax,
            )
        )
    if not cables:
        raise ConfigError(src, f"cable_set[id={want}]", "no cables in this set")
    return want, cables


def _cable_name(raw: str, index: int, used: set[str]) -> str:
    name = re.sub(r"[^A-Za-z0-9]+", "_", raw).strip("_") or f"cable_{index + 1}"
    if name[0].isdigit():
        name = f"cable_{name}"
    base, k = name, 2
    while name in used:
        name, k = f"{base}_{k}", k + 1
    used.add(name)
    return name


def caspr_cables_path(bodies_path: str | os.PathLike[str]) -> Path:
    """The cables file CASPR keeps beside ``MODEL_bodies.xml``: ``MODEL_cables.xml``."""
    p = Path(bodies_path)
    stem = p.name[: -len("_bodies.xml")] if p.name.endswith("_bodies.xml") else p.stem
    return p.with_name(f"{stem}_cables.xml")


def import_caspr(
    bodies_path: str | os.PathLike[str],
    cables_path: str | os.PathLike[str] | None = None,
    cable_set: str | None = None,
    default_t_min_N: float = DEFAULT_T_MIN_N,
    default_t_max_N: float = DEFAULT_T_MAX_N,
) -> Rig:
    """A validated :class:`Rig` from a single-body CASPR model (see the module doc for the mapping)."""
    body = read_caspr_bodies(bodies_path)
    cpath = Path(cables_path) if cables_path is not None else caspr_cables_path(bodies_path)
    set_id, cables = read_caspr_cables(cpath, cable_set)
    used: set[str] = set()
    names, anchors, attach, tmin, tmax = [], [], [], [], []
    n_default = 0
    for i, c in enumerate(cables):
        names.append(_cable_name(c.name, i, used))
        anchors.append(c.anchor_m)
        pp = np.array(c.attach_m)
        if c.attachment_reference == "com":
            pp = pp + body.com_m
        attach.append(pp)
        if c.force_min_N is None or c.force_max_N is None:
            n_default += 1
        tmin.append(default_t_min_N if c.force_min_N is None else c.force_min_N)
        tmax.append(default_t_max_N if c.force_max_N is None else c.force_max_N)
    source_note = f"CASPR model {Path(bodies_path).name} + {cpath.name}, cable set {set_id!r}"
    assumptions = {
        "source": source_note + " (CASPR, BSD 3-Clause licence)",
        "frames": (
            "{O} = CASPR base frame (link 0), {P} = platform joint frame; reference pose = parent "
            "location + q_initial (SPATIAL_EULER_XYZ angles converted to Z-Y-X)"
        ),
        "inertia": "CASPR inertia moved to P by the parallel-axis theorem (ref='com') or kept ('joint')",
    }
    if n_default:
        assumptions["tension_limits"] = (
            f"{n_default} cable(s) without force_min/force_max: default "
            f"[{default_t_min_N:g}, {default_t_max_N:g}] N"
        )
    else:
        assumptions["tension_limits"] = "force_min/force_max of every cable from the cable model"
    # through the rig file's schema: the same keys, types and plausible ranges as a rig file
    mapping = {
        "rig": {
            "name": re.sub(r"\s+", "-", body.name.strip()) or "caspr",
            "description": f"Imported from {source_note}",
            "reference_position_O_m": np.asarray(body.position_m, dtype=float).tolist(),
            "reference_euler_rad": np.asarray(body.euler_zyx_rad, dtype=float).tolist(),
        },
        "platform": {
            "mass_kg": float(body.mass_kg),
            "com_P_m": np.asarray(body.com_m, dtype=float).tolist(),
            "inertia_P_kgm2": np.asarray(body.inertia_P_kgm2, dtype=float).tolist(),
        },
        "cables": [
            {
                "name": names[i],
                "anchor_O_m": np.asarray(anchors[i], dtype=float).tolist(),
                "attach_P_m": np.asarray(attach[i], dtype=float).tolist(),
                "t_min_N": float(tmin[i]),
                "t_max_N": float(tmax[i]),
            }
            for i in range(len(names))
        ],
        "assumptions": assumptions,
    }
    return rig_from_mapping(mapping, source=str(cpath))
