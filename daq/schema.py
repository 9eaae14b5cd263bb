"""File schemas (pydantic v2) and the one error formatter: file, key, problem.

Every configuration file is a mapping (TOML, JSON) checked against a schema before any value is
used.  A schema is a :class:`Schema` subclass: unknown keys are refused, strings are never coerced
to numbers, NaN and infinity are refused, and each number has a plausible range (a value like
1e300 m is a typo, not a rig).  :func:`parse` validates a mapping and turns the first problem into
a :class:`~cdpr.analysis.errors.ConfigError` naming the file, the key (``cables[2].t_max_N``) and
the problem (:func:`config_error` is the formatter).

The building blocks (:data:`Position_m`, :data:`Vec3_m`, :data:`Tension_N`, ...) carry the units of
the project's naming convention; the rig file's schema is here too (:class:`RigFile`,
:func:`rig_from_mapping`), since :mod:`cdpr.analysis.rig` stays pure (numpy only).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from typing import Annotated, Any, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from pydantic_core import PydanticCustomError

from cdpr.analysis.conventions import GRAVITY_O_MPS2
from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rig import DEFAULT_CABLE_DIAMETER_M, DEFAULT_CABLE_EA_N, Rig

from .files import load_toml

MAX_LENGTH_M = 1e3
"""Largest coordinate (m) a rig or pose may hold: a cable robot is not a kilometre wide."""
MAX_ANGLE_RAD = 1e2
MAX_MASS_KG = 1e6
MAX_FORCE_N = 1e7
"""Largest force or tension (N) and moment (N m) a file may hold."""
MAX_INERTIA_KGM2 = 1e9
MAX_ACCEL_MPS2 = 1e3


class Schema(BaseModel):
    """Base of every file schema: unknown keys refused, no coercion from strings, no NaN/inf."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, frozen=True)


def _bounded(lo: float, hi: float, *, gt: bool = False) -> Any:
    return Field(gt=lo, le=hi) if gt else Field(ge=lo, le=hi)


Position_m = Annotated[float, _bounded(-MAX_LENGTH_M, MAX_LENGTH_M)]
Angle_rad = Annotated[float, _bounded(-MAX_ANGLE_RAD, MAX_ANGLE_RAD)]
Mass_kg = Annotated[float, _bounded(0.0, MAX_MASS_KG, gt=True)]
Tension_N = Annotated[float, _bounded(0.0, MAX_FORCE_N)]
Force_N = Annotated[float, _bounded(-MAX_FORCE_N, MAX_FORCE_N)]
Inertia_kgm2 = Annotated[float, _bounded(-MAX_INERTIA_KGM2, MAX_INERTIA_KGM2)]
Accel_mps2 = Annotated[float, _bounded(-MAX_ACCEL_MPS2, MAX_ACCEL_MPS2)]
Vec3_m = Annotated[list[Position_m], Field(min_length=3, max_length=3)]
Euler_rad = Annotated[list[Angle_rad], Field(min_length=3, max_length=3)]
Accel3_mps2 = Annotated[list[Accel_mps2], Field(min_length=3, max_length=3)]
Inertia3_kgm2 = Annotated[
    list[Annotated[list[Inertia_kgm2], Field(min_length=3, max_length=3)]],
    Field(min_length=3, max_length=3),
]
Text = Annotated[str, Field(max_length=10_000)]

M = TypeVar("M", bound=BaseModel)


def key_of(loc: tuple[int | str, ...], prefix: str = "") -> str:
    """A pydantic error location as the key a user reads: ``cables[2].anchor_O_m[1]``."""
    out = prefix
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


_BASIC_TAGS = frozenset({"str", "int", "float", "bool", "list", "dict", "none"})


def _is_union_tag(part: int | str) -> bool:
    """A part of an error location that names a union member (``constrained-float``,
    ``list[constrained-float]``, ``str``), not a key of the file."""
    return isinstance(part, str) and ("[" in part or "-" in part or part in _BASIC_TAGS)


RULE = "rule"
"""Error type of a rule relating keys (:func:`rule_error`)."""


def rule_error(problem: str, *keys: int | str) -> PydanticCustomError:
    """The error a model validator raises for a rule relating keys: the message names the key
    ``keys`` (below the model's own location) and says ``problem``."""
    return PydanticCustomError(RULE, problem, {"keys": keys})


def plain(value: Any) -> Any:
    """``value`` as a TOML reader would give it: tuples and arrays as lists, numpy scalars as
    Python numbers (settings built by code, checked by the same schema as a file's)."""
    if isinstance(value, Mapping):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray | np.generic):
        return plain(value.tolist())
    return value


def config_error(
    exc: ValidationError,
    source: str,
    prefix: str = "",
    errors: list[Any] | None = None,
) -> ConfigError:
    """The one error formatter: the first problem of ``exc`` as a :class:`ConfigError`
    naming ``source``, the key and the problem (with the value found, shortened).

    A value that fits no member of a union (``gain_N_per_count``: a number or a list) is named
    by its key alone: if one member matched the type but not the range, that problem is told;
    otherwise every member's expected type (``expected a valid string or a valid integer``).
    """
    if errors is None:
        errors = list(exc.errors(include_url=False))
    err = errors[0]
    loc = tuple(err["loc"])
    if any(_is_union_tag(p) for p in loc):
        # the errors of the same union: those whose location (union tags dropped) starts alike
        stem = loc[: next(i for i, p in enumerate(loc) if _is_union_tag(p))]
        same = [e for e in errors if tuple(e["loc"])[: len(stem)] == stem]
        # a member that matched the type (a list whose item is wrong, a number out of range)
        ranged = [
            e
            for e in same
            if not e["type"].endswith("_type")
            or len([p for p in e["loc"] if not _is_union_tag(p)]) > len(stem)
        ]
        if ranged:
            err = ranged[0]
        else:
            wants = dict.fromkeys(e["msg"].removeprefix("Input should be ") for e in same)
            return ConfigError(
                source,
                key_of(stem, prefix),
                f"expected {' or '.join(wants)}, got {_shown(err.get('input'))}",
            )
        loc = tuple(p for p in err["loc"] if not _is_union_tag(p))
    kind, ctx, value = err["type"], err.get("ctx", {}), err.get("input")
    if kind == RULE:  # a rule that relates keys names the key it blames
        return ConfigError(source, key_of((*loc, *ctx.get("keys", ())), prefix), err["msg"])
    key = key_of(loc, prefix)
    if kind == "extra_forbidden":
        problem = "unknown key"
    elif kind == "missing":
        problem = "missing"
    elif kind in ("too_short", "too_long"):  # the problem says how many came
        problem = _problem(kind, ctx, value, err["msg"])
    else:
        problem = f"{_problem(kind, ctx, value, err['msg'])}, got {_shown(value)}"
    return ConfigError(source, key, " ".join(problem.split()))


def _problem(kind: str, ctx: dict[str, Any], value: Any, msg: str) -> str:
    if kind == "greater_than":
        return f"must be > {ctx['gt']}"
    if kind == "greater_than_equal":
        return f"must be >= {ctx['ge']}"
    if kind in ("less_than_equal", "less_than"):
        return f"must be <= {ctx.get('le', ctx.get('lt'))} (a larger value is not plausible here)"
    if kind in ("too_short", "too_long"):
        noun = "number" if all(isinstance(v, int | float) for v in value or []) else "item"
        n = ctx.get("min_length", ctx.get("max_length"))
        noun += "" if n == 1 else "s"
        which = "at least" if kind == "too_short" else "at most"
        return f"expected {which} {n} {noun}, got {ctx.get('actual_length')}"
    if kind in ("string_too_short", "string_too_long"):
        n = ctx.get("min_length", ctx.get("max_length"))
        which = "at least" if kind == "string_too_short" else "at most"
        return f"expected {which} {n} character{'' if n == 1 else 's'}"
    if kind == "finite_number":
        return "expected a finite number"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return "expected a table"
    return "expected " + msg.removeprefix("Input should be ")


def parse(model: type[M], data: Any, source: str, prefix: str = "") -> M:
    """``data`` validated against ``model``, or a :class:`ConfigError` (file, key, problem)."""
    if not isinstance(data, Mapping):
        raise ConfigError(source, prefix, f"expected a table, got {_shown(data)}")
    try:
        return model.model_validate(dict(data))
    except ValidationError as exc:
        raise config_error(exc, source, prefix) from None
    except RecursionError:
        raise ConfigError(source, prefix, "nested too deeply") from None


# --- the rig file (layout: cdpr.analysis.rig) ------------------------------------------------------


class RigSection(Schema):
    name: Text = "rig"
    description: Text = ""
    gravity_O_mps2: Accel3_mps2 = Field(default_factory=lambda: list(map(float, GRAVITY_O_MPS2)))
    reference_position_O_m: Vec3_m = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    reference_euler_rad: Euler_rad = Field(default_factory=lambda: [0.0, 0.0, 0.0])


Diameter_m = Annotated[float, _bounded(0.0, 1.0, gt=True)]
DragCoefficient = Annotated[float, _bounded(0.0, 100.0, gt=True)]
Stiffness_N = Annotated[float, _bounded(0.0, 1e12, gt=True)]
Area_m2 = Annotated[float, _bounded(0.0, 1e3)]


class PlatformSection(Schema):
    mass_kg: Mass_kg
    com_P_m: Vec3_m = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    inertia_P_kgm2: Inertia3_kgm2 = Field(default_factory=lambda: [[0.0] * 3 for _ in range(3)])
    windage_drag_area_m2: Area_m2 = 0.0


GeometrySd_m = Annotated[float, _bounded(0.0, 0.1)]
"""σ of a coordinate of the rig geometry (m): 0.1 m is not a measured rig."""
GeometrySd3_m = Annotated[list[GeometrySd_m], Field(min_length=3, max_length=3)]


class CableSection(Schema):
    name: Text | None = None
    anchor_O_m: Vec3_m
    attach_P_m: Vec3_m
    t_min_N: Tension_N
    t_max_N: Tension_N
    diameter_m: Diameter_m | None = None
    drag_coefficient: DragCoefficient | None = None
    EA_N: Stiffness_N | None = None
    max_speed_mps: Annotated[float, _bounded(0.0, 1e3, gt=True)] | None = None
    max_accel_mps2: Annotated[float, _bounded(0.0, 1e5, gt=True)] | None = None
    anchor_sd_m: GeometrySd_m | GeometrySd3_m | None = None
    attach_sd_m: GeometrySd_m | GeometrySd3_m | None = None


class UncertaintySection(Schema):
    """``[uncertainty]``: the rig geometry's σ per coordinate for every cable that gives none."""

    anchor_sd_m: GeometrySd_m | GeometrySd3_m | None = None
    attach_sd_m: GeometrySd_m | GeometrySd3_m | None = None


class RigFile(Schema):
    """A rig file: ``[rig]``, ``[platform]``, ``[[cables]]``, ``[uncertainty]``, ``[assumptions]``."""

    rig: RigSection = Field(default_factory=RigSection)
    platform: PlatformSection
    cables: Annotated[list[CableSection], Field(min_length=1, max_length=1000)]
    uncertainty: UncertaintySection = Field(default_factory=UncertaintySection)
    assumptions: dict[Text, Text | int | float | bool] = Field(default_factory=dict)


def rig_from_mapping(data: Mapping[str, Any], source: str = "<mapping>") -> Rig:
    """A validated :class:`~cdpr.analysis.rig.Rig` from a parsed rig file: the schema checks
    keys, types and ranges; the ``Rig`` checks its invariants (unique names, t_min < t_max,
    symmetric inertia, no zero-length cable)."""
    f = parse(RigFile, data, source)
    cables = f.cables
    return Rig(
        name=f.rig.name,
        description=f.rig.description,
        cable_names=tuple(
            c.name if c.name is not None else f"c{i + 1}" for i, c in enumerate(cables)
        ),
        anchors_O_m=np.array([c.anchor_O_m for c in cables]),
        attach_P_m=np.array([c.attach_P_m for c in cables]),
        mass_kg=f.platform.mass_kg,
        com_P_m=np.array(f.platform.com_P_m),
        inertia_P_kgm2=np.array(f.platform.inertia_P_kgm2),
        t_min_N=np.array([c.t_min_N for c in cables]),
        t_max_N=np.array([c.t_max_N for c in cables]),
        gravity_O_mps2=np.array(f.rig.gravity_O_mps2),
        reference_position_O_m=np.array(f.rig.reference_position_O_m),
        reference_euler_rad=np.array(f.rig.reference_euler_rad),
        assumptions={k: str(v) for k, v in f.assumptions.items()},
        source=source,
        cable_diameter_m=_per_cable([c.diameter_m for c in cables], DEFAULT_CABLE_DIAMETER_M),
        cable_drag_coefficient=_per_cable([c.drag_coefficient for c in cables], math.nan),
        cable_EA_N=_per_cable([c.EA_N for c in cables], DEFAULT_CABLE_EA_N),
        platform_drag_area_m2=f.platform.windage_drag_area_m2,
        cable_max_speed_mps=_per_cable([c.max_speed_mps for c in cables], math.inf),
        cable_max_accel_mps2=_per_cable([c.max_accel_mps2 for c in cables], math.inf),
        anchor_sd_m=_sd_per_cable([c.anchor_sd_m for c in cables], f.uncertainty.anchor_sd_m),
        attach_sd_m=_sd_per_cable([c.attach_sd_m for c in cables], f.uncertainty.attach_sd_m),
    )


def _sd_per_cable(values: list[Any], rig_wide: Any) -> np.ndarray:
    """A geometry σ per cable and coordinate (m, 3): the cable's own, else ``[uncertainty]``'s,
    else NaN (not given: the analysis takes its default and says so)."""
    out = np.full((len(values), 3), np.nan)
    for i, v in enumerate(values):
        v = rig_wide if v is None else v
        if v is not None:
            out[i] = v
    return out


def _per_cable(values: list[float | None], default: float) -> np.ndarray:
    """Optional per-cable numbers: ``default`` where a cable does not give one."""
    return np.array([default if v is None else v for v in values], dtype=np.float64)


def load_rig(path: str | os.PathLike[str]) -> Rig:
    """Load and validate a rig file (layout in :mod:`cdpr.analysis.rig`)."""
    return rig_from_mapping(load_toml(path), source=str(path))
