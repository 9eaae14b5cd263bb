"""The rig model: cable anchors, platform attachment points, mass properties and cable limits.

A :class:`Rig` is frozen and validated on construction (its invariants).  The rig file's schema
(keys, types, plausible ranges) and ``rig_from_mapping`` live in :mod:`cdpr.daq.schema`, which
names the file and key of any problem; :func:`rig_to_mapping` is its inverse.  Reading and writing
files is not this module's job.

Rig file layout (all SI)::

    [rig]
    name = "flat-optimum"
    gravity_O_mps2 = [0.0, 0.0, -9.80665]        # optional
    reference_position_O_m = [0.5, 0.0, 0.335]   # optional, the nominal pose of P
    reference_euler_rad = [0.0, 0.0, 0.0]        # optional

    [platform]
    mass_kg = 0.64
    com_P_m = [0.0, 0.0, 0.0]
    inertia_P_kgm2 = [[...], [...], [...]]       # about P, {P} axes
    windage_drag_area_m2 = 0.0                    # optional: CD*A of the bare platform in the flow

    [[cables]]                                    # one table per cable, m >= 1
    name = "front_left_top"
    anchor_O_m = [0.0, 0.255, 0.67]               # b_i in {O}
    attach_P_m = [-0.015, 0.005, 0.0]             # pp_i in {P}
    t_min_N = 35.0
    t_max_N = 300.0
    diameter_m = 0.001                            # optional, default DEFAULT_CABLE_DIAMETER_M
    drag_coefficient = 1.1                        # optional, default: CD(Re) of a cylinder
    EA_N = 70000.0                                # optional, default DEFAULT_CABLE_EA_N
    max_speed_mps = 0.5                           # optional: the winch's largest cable speed
    max_accel_mps2 = 20.0                         # optional: and acceleration (none: unchecked)
    anchor_sd_m = 0.5e-3                          # optional: σ of each coordinate of b_i (m), or
    attach_sd_m = [1e-4, 1e-4, 2e-4]              # [x, y, z]; σ of pp_i (rig geometry's error)

    [uncertainty]                                 # optional: the same σ for every cable that
    anchor_sd_m = 0.5e-3                          # gives none (default: ISO 2768-1 class m,
    attach_sd_m = 0.1e-3                          # cdpr.analysis.systematic.default_geometry_sd)

    [assumptions]                                 # optional free text, kept with the rig
    layout = "..."
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .conventions import GRAVITY_O_MPS2
from .errors import ConfigError

FloatArray = NDArray[np.float64]

DEFAULT_CABLE_DIAMETER_M: float = 1.0e-3
"""Assumed cable diameter when the rig file gives none: 1 mm (the issue's estimate; the paper
does not give it)."""

DEFAULT_CABLE_EA_N: float = 7.0e4
"""Assumed axial stiffness E*A when the rig file gives none: a 1 mm 7x7 steel wire rope
(effective modulus about 90 GPa on the 0.785 mm^2 nominal section).  The paper does not give it;
the natural frequencies scale with its square root."""


def _frozen(a: Any, shape: tuple[int, ...]) -> FloatArray:
    arr = np.array(a, dtype=np.float64).reshape(shape)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Rig:
    """A cable robot: m cables between anchors ``b_i`` in {O} and platform points ``pp_i`` in {P}.

    Attributes
    ----------
    name: rig name.
    cable_names: m cable names, unique.
    anchors_O_m: (m, 3) anchor points b_i in {O}, m.
    attach_P_m: (m, 3) platform attachment points pp_i in {P}, m.
    mass_kg: platform (plus model) mass, kg, > 0.
    com_P_m: (3,) centre of mass in {P}, m.
    inertia_P_kgm2: (3, 3) symmetric positive semi-definite inertia tensor about P in {P}, kg m^2.
    t_min_N, t_max_N: (m,) per-cable tension limits, N, 0 <= t_min < t_max.
    gravity_O_mps2: (3,) gravity in {O}, m/s^2.
    reference_position_O_m: (3,) nominal position of P in {O}, m.
    reference_euler_rad: (3,) nominal Z-Y-X Euler angles, rad.
    assumptions: free-text notes on where the numbers come from.
    cable_diameter_m: (m,) cable diameters, m (default :data:`DEFAULT_CABLE_DIAMETER_M`).
    cable_drag_coefficient: (m,) constant cross-flow drag coefficients; NaN (the default) means
      the cylinder's CD(Re) of :func:`cdpr.analysis.windage.cylinder_drag_coefficient`.
    cable_EA_N: (m,) axial stiffness E*A, N (default :data:`DEFAULT_CABLE_EA_N`).
    platform_drag_area_m2: CD*A of the bare platform in the flow, m^2 (default 0: inside the model).
    cable_max_speed_mps, cable_max_accel_mps2: (m,) the winches' largest cable speed (m/s) and
      acceleration (m/s^2), ``inf`` where the rig file gives none (the motion planner then says
      it could not check them).
    anchor_sd_m, attach_sd_m: (m, 3) σ of each coordinate of b_i and pp_i (m), NaN where the rig
      file gives none (:func:`cdpr.analysis.systematic.rig_geometry_sd` then takes the default).
    """

    name: str
    cable_names: tuple[str, ...]
    anchors_O_m: FloatArray
    attach_P_m: FloatArray
    mass_kg: float
    com_P_m: FloatArray
    inertia_P_kgm2: FloatArray
    t_min_N: FloatArray
    t_max_N: FloatArray
    gravity_O_mps2: FloatArray = field(default_factory=lambda: GRAVITY_O_MPS2.copy())
    reference_position_O_m: FloatArray = field(default_factory=lambda: np.zeros(3))
    reference_euler_rad: FloatArray = field(default_factory=lambda: np.zeros(3))
    assumptions: Mapping[str, str] = field(default_factory=dict)
    description: str = ""
    source: str = "<memory>"
    cable_diameter_m: Any = None
    cable_drag_coefficient: Any = None
    cable_EA_N: Any = None
    platform_drag_area_m2: float = 0.0
    cable_max_speed_mps: Any = None
    cable_max_accel_mps2: Any = None
    anchor_sd_m: Any = None
    attach_sd_m: Any = None

    def __post_init__(self) -> None:
        src = self.source
        names = tuple(str(n) for n in self.cable_names)
        m = len(names)
        if m < 1:
            raise ConfigError(src, "cables", "expected at least one cable, got none")
        if len(set(names)) != m:
            dup = sorted({n for n in names if names.count(n) > 1})
            raise ConfigError(src, "cables.name", f"cable names must be unique, repeated: {dup}")
        object.__setattr__(self, "cable_names", names)

        def arr(key: str, value: Any, shape: tuple[int, ...]) -> FloatArray:
            try:
                a = np.array(value, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise ConfigError(src, key, f"expected numbers of shape {shape}") from exc
            if a.shape != shape:
                raise ConfigError(src, key, f"expected shape {shape}, got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ConfigError(src, key, "expected finite numbers, got NaN or inf")
            return _frozen(a, shape)

        object.__setattr__(self, "anchors_O_m", arr("cables.anchor_O_m", self.anchors_O_m, (m, 3)))
        object.__setattr__(self, "attach_P_m", arr("cables.attach_P_m", self.attach_P_m, (m, 3)))
        t_min = np.broadcast_to(np.asarray(self.t_min_N, dtype=np.float64), (m,))
        t_max = np.broadcast_to(np.asarray(self.t_max_N, dtype=np.float64), (m,))
        object.__setattr__(self, "t_min_N", arr("cables.t_min_N", t_min, (m,)))
        object.__setattr__(self, "t_max_N", arr("cables.t_max_N", t_max, (m,)))
        bad = np.flatnonzero(self.t_min_N < 0)
        if bad.size:
            raise ConfigError(src, f"cables[{bad[0]}].t_min_N", "must be >= 0 N")
        bad = np.flatnonzero(self.t_min_N >= self.t_max_N)
        if bad.size:
            i = int(bad[0])
            raise ConfigError(
                src,
                f"cables[{i}].t_min_N",
                f"t_min_N ({self.t_min_N[i]}) must be < t_max_N ({self.t_max_N[i]})",
            )
        try:
            mass = float(self.mass_kg)
        except (TypeError, ValueError) as exc:
            raise ConfigError(src, "platform.mass_kg", "expected a number") from exc
        if not math.isfinite(mass) or mass <= 0:
            raise ConfigError(src, "platform.mass_kg", f"must be > 0 kg, got {self.mass_kg}")
        object.__setattr__(self, "mass_kg", mass)
        object.__setattr__(self, "com_P_m", arr("platform.com_P_m", self.com_P_m, (3,)))
        inertia = arr("platform.inertia_P_kgm2", self.inertia_P_kgm2, (3, 3))
        if not np.allclose(inertia, inertia.T, atol=1e-12):
            raise ConfigError(src, "platform.inertia_P_kgm2", "must be symmetric")
        if np.linalg.eigvalsh(inertia).min() < -1e-12:
            raise ConfigError(src, "platform.inertia_P_kgm2", "must be positive semi-definite")
        object.__setattr__(self, "inertia_P_kgm2", inertia)
        object.__setattr__(
            self, "gravity_O_mps2", arr("rig.gravity_O_mps2", self.gravity_O_mps2, (3,))
        )
        object.__setattr__(
            self,
            "reference_position_O_m",
            arr("rig.reference_position_O_m", self.reference_position_O_m, (3,)),
        )
        object.__setattr__(
            self,
            "reference_euler_rad",
            arr("rig.reference_euler_rad", self.reference_euler_rad, (3,)),
        )
        object.__setattr__(self, "assumptions", dict(self.assumptions))

        def per_cable(key: str, value: Any, default: float, allow_nan: bool = False) -> FloatArray:
            v = np.broadcast_to(np.asarray(default if value is None else value, dtype=float), (m,))
            a = np.array(v, dtype=np.float64)
            ok = np.isfinite(a) & (a > 0)
            if allow_nan:
                ok |= np.isnan(a)
            bad_i = np.flatnonzero(~ok)
            if bad_i.size:
                raise ConfigError(
                    src, f"cables[{bad_i[0]}].{key}", f"must be > 0, got {a[bad_i[0]]}"
                )
            return _frozen(a, (m,))

        try:
            object.__setattr__(
                self,
                "cable_diameter_m",
                per_cable("diameter_m", self.cable_diameter_m, DEFAULT_CABLE_DIAMETER_M),
            )
            object.__setattr__(
                self,
                "cable_drag_coefficient",
                per_cable("drag_coefficient", self.cable_drag_coefficient, math.nan, True),
            )
            object.__setattr__(
                self, "cable_EA_N", per_cable("EA_N", self.cable_EA_N, DEFAULT_CABLE_EA_N)
            )
            for key, attr in (
                ("max_speed_mps", "cable_max_speed_mps"),
                ("max_accel_mps2", "cable_max_accel_mps2"),
            ):
                v = np.broadcast_to(
                    np.asarray(math.inf if getattr(self, attr) is None else getattr(self, attr),
                               dtype=float), (m,))  # fmt: skip
                bad_i = np.flatnonzero(~(v > 0) | np.isnan(v))
                if bad_i.size:
                    raise ConfigError(
                        src, f"cables[{bad_i[0]}].{key}", f"must be > 0, got {v[bad_i[0]]}"
                    )
                object.__setattr__(self, attr, _frozen(v, (m,)))
        except (TypeError, ValueError) as exc:
            raise ConfigError(
                src, "cables", f"bad diameter_m, drag_coefficient or EA_N: {exc}"
            ) from None
        for key in ("anchor_sd_m", "attach_sd_m"):
            object.__setattr__(self, key, _geometry_sd(src, key, getattr(self, key), m))
        try:
            cda = float(self.platform_drag_area_m2)
        except (TypeError, ValueError):
            raise ConfigError(src, "platform.windage_drag_area_m2", "expected a number") from None
        if not math.isfinite(cda) or cda < 0:
            raise ConfigError(src, "platform.windage_drag_area_m2", f"must be >= 0 m^2, got {cda}")
        object.__setattr__(self, "platform_drag_area_m2", cda)
        # A cable of zero length at the reference pose cannot define a direction.
        from .kinematics import cable_vectors
        from .rotations import rotation_from_euler

        l_O = cable_vectors(
            self.anchors_O_m,
            self.attach_P_m,
            self.reference_position_O_m,
            rotation_from_euler(self.reference_euler_rad),
        )
        lengths = np.linalg.norm(l_O, axis=-1)
        bad = np.flatnonzero(lengths < 1e-9)
        if bad.size:
            raise ConfigError(
                src,
                f"cables[{bad[0]}] ({names[bad[0]]})",
                "zero-length cable at the reference pose: anchor coincides with the attachment point",
            )

    @property
    def n_cables(self) -> int:
        """Number of cables m."""
        return len(self.cable_names)

    def describe(self) -> dict[str, Any]:
        """A short, JSON-friendly summary (names, units, shapes)."""
        return {
            "name": self.name,
            "n_cables": self.n_cables,
            "cable_names": list(self.cable_names),
            "mass_kg": self.mass_kg,
            "t_min_N": self.t_min_N.tolist(),
            "t_max_N": self.t_max_N.tolist(),
        }


def _geometry_sd(src: str, key: str, value: Any, m: int) -> FloatArray:
    """σ per cable and coordinate (m, 3): None (not given: NaN), a scalar, (m,) or (m, 3); each
    value NaN (not given) or finite and >= 0."""
    try:
        a = np.array(np.nan if value is None else value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(src, f"cables.{key}", "expected numbers") from None
    if a.shape == (m,):
        a = a[:, None]
    if a.ndim > 2 or (a.ndim and a.shape not in ((m, 1), (m, 3))):
        raise ConfigError(src, f"cables.{key}", f"expected a number or 3 per cable, got {a.shape}")
    a = np.array(np.broadcast_to(a, (m, 3)))
    bad = np.flatnonzero(((a < 0) | np.isinf(a)).any(axis=1))
    if bad.size:
        raise ConfigError(
            src, f"cables[{bad[0]}].{key}", f"must be finite and >= 0 m, got {a[bad[0]]}"
        )
    return _frozen(a, (m, 3))


def rig_to_mapping(rig: Rig) -> dict[str, Any]:
    """The inverse of :func:`cdpr.daq.schema.rig_from_mapping`: a nested dict ready to be written
    as TOML."""
    out: dict[str, Any] = {
        "rig": {
            "name": rig.name,
            "gravity_O_mps2": rig.gravity_O_mps2.tolist(),
            "reference_position_O_m": rig.reference_position_O_m.tolist(),
            "reference_euler_rad": rig.reference_euler_rad.tolist(),
        },
        "platform": {
            "mass_kg": rig.mass_kg,
            "com_P_m": rig.com_P_m.tolist(),
            "inertia_P_kgm2": rig.inertia_P_kgm2.tolist(),
        },
        "cables": [
            {
                "name": rig.cable_names[i],
                "anchor_O_m": rig.anchors_O_m[i].tolist(),
                "attach_P_m": rig.attach_P_m[i].tolist(),
                "t_min_N": float(rig.t_min_N[i]),
                "t_max_N": float(rig.t_max_N[i]),
            }
            for i in range(rig.n_cables)
        ],
    }
    # the optional windage and stiffness keys are written only where they differ from the default
    for i, cab in enumerate(out["cables"]):
        if rig.cable_diameter_m[i] != DEFAULT_CABLE_DIAMETER_M:
            cab["diameter_m"] = float(rig.cable_diameter_m[i])
        if not math.isnan(rig.cable_drag_coefficient[i]):
            cab["drag_coefficient"] = float(rig.cable_drag_coefficient[i])
        if rig.cable_EA_N[i] != DEFAULT_CABLE_EA_N:
            cab["EA_N"] = float(rig.cable_EA_N[i])
        if math.isfinite(rig.cable_max_speed_mps[i]):
            cab["max_speed_mps"] = float(rig.cable_max_speed_mps[i])
        if math.isfinite(rig.cable_max_accel_mps2[i]):
            cab["max_accel_mps2"] = float(rig.cable_max_accel_mps2[i])
        for key in ("anchor_sd_m", "attach_sd_m"):
            sd = getattr(rig, key)[i]
            if not np.isnan(sd).any():
                cab[key] = float(sd[0]) if np.all(sd == sd[0]) else sd.tolist()
    if rig.platform_drag_area_m2 != 0.0:
        out["platform"]["windage_drag_area_m2"] = rig.platform_drag_area_m2
    if rig.description:
        out["rig"]["description"] = rig.description
    if rig.assumptions:
        out["assumptions"] = dict(rig.assumptions)
    return out
