"""The reduction engine: per-point arrays flowing through an ordered list of stages.

A :class:`Points` holds one row per test point: its inputs (mean tensions and their covariance,
mean pose and its covariance, airspeed, density, kind), what the stages add (the wrench, each σ
term, axes, coefficients), one tuple of flag words per point, and the log of the stages that ran.

A *stage* is a thin function ``stage(points, **settings) -> Points`` around exactly one public pure
function of :mod:`cdpr.analysis` (the one its tests check), wrapped by :func:`stage`: it returns a
new :class:`Points` (inputs are never modified), adds its correction, adds its covariance term under
its own name in ``cov_terms`` (so σ can be listed by source), flags the points it could not treat,
and the decorator appends a :class:`Step` (name, the wrapped function, settings, points flagged) to
the log.  A stage that cannot run for a point leaves NaN and a flag there, never a nominal value in
silence.  The stages and their one canonical order are in :mod:`cdpr.analysis.stages`.

Keys in ``Points.arrays`` (s points, m cables; frames and units in the names):

- inputs (:func:`new_points`): ``kind`` (s,) str (:data:`cdpr.analysis.conventions.POINT_KINDS`, or
  ``unknown``), ``start_ns`` (s,) int, ``tension_N`` (s, m), ``tension_cov_N2`` (s, m, m),
  ``pose_O_m_rad`` (s, 6) the mean pose (position of P in {O}, m; Z-Y-X Euler angles, rad),
  ``pose_cov_O_m_rad`` (s, 6, 6) the covariance of that mean, ``airspeed_mps`` (s,) (NaN when
  unknown), ``density_kgpm3`` (s,), ``input_flags`` (s,) str (``;``-separated words from upstream);
- added by the stages: ``structure_matrix_O`` (s, 6, m), ``wrench_P_O_N_Nm`` (s, 6) the aerodynamic
  wrench on the platform at P in {O} axes (N, N m), ``tare_index`` (s,) (-1: none), then the axes,
  coefficients and corrections (each stage's docstring names what it adds).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError

FloatArray = NDArray[np.float64]

WRENCH = "wrench_P_O_N_Nm"
"""The key of the aerodynamic wrench on the platform at P in {O} axes (N, N m)."""
POSE = "pose_O_m_rad"
"""The key of the mean pose: position of P in {O} (m) and Z-Y-X Euler angles (rad)."""
POSE_COV = "pose_cov_O_m_rad"
"""The key of the covariance of the mean pose (m², m·rad, rad²)."""
STRUCTURE_MATRIX = "structure_matrix_O"
"""The key of the structure matrix at the mean pose: unit vectors and moment arms in {O} (m)."""


@dataclass(frozen=True)
class Step:
    """What one stage did: its name, the pure function it wraps (``module.function``), its settings
    (plain values), the number of points whose flags it extended, and a note."""

    name: str
    settings: Mapping[str, Any]
    flagged: int
    note: str = ""
    function: str = ""


@dataclass(frozen=True)
class Points:
    """Per-point arrays flowing through the stages (see the module docstring for the keys).

    cov_terms: name -> (s, 6, 6) covariance of ``wrench_P_O_N_Nm`` from that source, in the
    current axes and reference point of the wrench; flags: one tuple of words per point; steps:
    the stage log; meta: results that are not per point (the weight model, correction records).
    """

    arrays: Mapping[str, NDArray[Any]]
    cov_terms: Mapping[str, FloatArray] = field(default_factory=dict)
    flags: tuple[tuple[str, ...], ...] = ()
    steps: tuple[Step, ...] = ()
    meta: Mapping[str, Any] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(len(self.arrays["kind"]))

    def __getitem__(self, key: str) -> NDArray[Any]:
        return self.arrays[key]

    @property
    def wrench_cov(self) -> FloatArray:
        """Total covariance (s, 6, 6) of ``wrench_P_O_N_Nm``: the sum of every term."""
        tot = np.zeros((self.n, 6, 6))
        for c in self.cov_terms.values():
            tot = tot + c
        return tot

    def flag_text(self) -> list[str]:
        """One ``;``-separated string of flag words per point."""
        return [";".join(f) for f in self.flags]


INPUT_SHAPES: dict[str, Callable[[int, int], tuple[int, ...]]] = {
    "start_ns": lambda s, m: (s,),
    "tension_N": lambda s, m: (s, m),
    "tension_cov_N2": lambda s, m: (s, m, m),
    POSE: lambda s, m: (s, 6),
    POSE_COV: lambda s, m: (s, 6, 6),
    "airspeed_mps": lambda s, m: (s,),
    "density_kgpm3": lambda s, m: (s,),
}
"""The inputs every :class:`Points` starts from, with their shapes for s points and m cables."""


def new_points(**arrays: ArrayLike) -> Points:
    """A :class:`Points` from the input arrays (shapes checked, see :data:`INPUT_SHAPES`), with
    empty flags and log.  ``input_flags`` (s,) (words from upstream) defaults to none; other
    arrays are kept as given."""
    kind = np.asarray(arrays["kind"]).astype(str)
    s = kind.shape[0]
    T = np.asarray(arrays["tension_N"], dtype=np.float64)
    m = T.shape[-1] if T.ndim == 2 else -1
    out: dict[str, NDArray[Any]] = {"kind": kind}
    for key, shape_of in INPUT_SHAPES.items():
        if key not in arrays:
            raise InputError(f"new_points: {key} missing")
        dtype = np.int64 if key == "start_ns" else np.float64
        a = np.asarray(arrays[key], dtype=dtype)
        if a.shape != shape_of(s, m):
            raise InputError(f"{key}: expected shape {shape_of(s, m)}, got {a.shape}")
        out[key] = a
    words = np.asarray(arrays.get("input_flags", [""] * s)).astype(str)
    if words.shape != (s,):
        raise InputError(f"input_flags: expected shape ({s},), got {words.shape}")
    out["input_flags"] = words
    for key, val in arrays.items():
        out.setdefault(key, np.asarray(val))
    return Points(out, {}, tuple(() for _ in range(s)))


Stage = Callable[[Points], Points]
"""A stage with its settings bound (``functools.partial``): points in, points out."""


def stage(
    name: str, wraps: Callable[..., Any] | None
) -> Callable[[Callable[..., Points]], Callable[..., Points]]:
    """Decorator of a stage named ``name`` around the public pure function ``wraps`` (None only
    for stages that move data and compute nothing): runs the stage and appends a :class:`Step`
    with its plain settings and the number of points whose flags it extended.  The wrapper keeps
    ``stage_name`` and ``wraps`` as attributes (the docs' stage table and its test read them)."""

    def deco(fn: Callable[..., Points]) -> Callable[..., Points]:
        target = "" if wraps is None else f"{wraps.__module__}.{wraps.__qualname__}"

        @functools.wraps(fn)
        def run(points: Points, **settings: Any) -> Points:
            out = fn(points, **settings)
            flagged = sum(
                1 for a, b in zip(points.flags, out.flags, strict=True) if len(b) > len(a)
            )
            plain = {k: _plain(v) for k, v in settings.items()}
            note = str(out.meta.get("_note", ""))
            meta = {k: v for k, v in out.meta.items() if k != "_note"}
            step = Step(name, plain, flagged, note, target)
            return replace(out, steps=out.steps + (step,), meta=meta)

        run.stage_name = name  # type: ignore[attr-defined]
        run.wraps = wraps  # type: ignore[attr-defined]
        return run

    return deco


def _plain(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return f"<array {v.shape}>" if v.size > 12 else v.tolist()
    if isinstance(v, list | tuple):
        return f"<{len(v)} values>" if len(v) > 12 else [_plain(x) for x in v]
    if isinstance(v, float | int | str | bool) or v is None:
        return v
    name = getattr(v, "name", None)  # a rig: its name; a settings object: its type
    return name if isinstance(name, str) else type(v).__name__


def with_updates(
    p: Points,
    arrays: Mapping[str, NDArray[Any]] | None = None,
    terms: Mapping[str, FloatArray] | None = None,
    flag: Mapping[str, NDArray[np.bool_]] | None = None,
    meta: Mapping[str, Any] | None = None,
    replace_terms: bool = False,
) -> Points:
    """A new :class:`Points` with ``arrays`` added or replaced, σ ``terms`` added (or, with
    ``replace_terms``, replacing all), the word of each ``flag`` mask (s,) appended to those points,
    and ``meta`` merged (``"_note"``: a sentence for the stage log).  What a stage returns."""
    a = dict(p.arrays)
    a.update(arrays or {})
    t = dict(terms or {}) if replace_terms else {**p.cov_terms, **(terms or {})}
    flags = [list(f) for f in p.flags]
    for word, mask in (flag or {}).items():
        for i in np.flatnonzero(mask):
            if word not in flags[i]:
                flags[i].append(word)
    return replace(
        p,
        arrays=a,
        cov_terms=t,
        flags=tuple(tuple(f) for f in flags),
        meta={**p.meta, **(meta or {})},
    )


def flag_masks(words: Sequence[str]) -> dict[str, NDArray[np.bool_]]:
    """One boolean mask (s,) per flag word found in ``words`` (one ``;``-separated string per
    point), in the order the words first appear."""
    n = len(words)
    out: dict[str, NDArray[np.bool_]] = {}
    for i, text in enumerate(words):
        for word in filter(None, str(text).split(";")):
            out.setdefault(word, np.zeros(n, bool))[i] = True
    return out


def run_stages(points: Points, stages: Sequence[Stage]) -> Points:
    """Run the stages in order."""
    for st in stages:
        points = st(points)
    return points
