"""The test section and the model's blockage data from a test-matrix file: ``[tunnel]`` and the
``[model]`` keys the wall corrections need.

The campaign file's loader calls :func:`tunnel_section_from_mapping` with the whole parsed file.
``[tunnel]`` belongs to this module (unknown keys are errors); from ``[model]`` only the keys below
are read (the campaign owns the rest of that table).  Layout (all SI, frames as in
:mod:`cdpr.analysis.conventions`)::

    [tunnel]
    kind = "closed"              # "closed" | "open_jet" (the jet is the nozzle's section carried on)
    shape = "octagon"            # "octagon" (regular, flat top) | "rectangle" | "polygon"
    octagon_side_m = 0.376       # shape = "octagon"
    # width_m = 0.9, height_m = 0.6           # shape = "rectangle"
    # polygon_yz_m = [[y, z], ...]            # shape = "polygon": convex, counter-clockwise
    center_yz_m = [0.0, 0.335]   # the section's axis in {O}, m
    x_start_m = -0.0375          # the section spans x_start_m .. x_start_m + length_m in {O}
    length_m = 1.075
    area_m2 = 0.6826             # optional: overrides the polygon's area in the wall corrections
    delta = 0.125                # lift-interference boundary factor (BRP ch. 10)
    tau1 = 0.88                  # solid-blockage tunnel-shape factor (BRP ch. 10, Thom)
    tau2 = 0.05                  # streamline-curvature factor (BRP ch. 10)

    [model]
    volume_m3 = 5.6e-4           # body (fuselage) volume
    blockage_K3 = 0.94           # body shape factor (BRP ch. 10, vs fineness ratio)
    wing_volume_m3 = 5.2e-5      # optional, default 0 (lumped into volume_m3)
    wing_K1 = 1.0                # required when wing_volume_m3 > 0
    reference_area_m2 = 0.0125   # S
    span_m = 0.2441              # b
    chord_m = 0.051              # c (Reynolds number and Cm)
    lift_slope_per_rad = 4.0     # optional: default 2 pi AR/(AR + 2), AR = b^2/S (said in notes)

No value falls back silently: the boundary factors and the shape factors are required, and the one
default that is computed (the lift slope) is written into :attr:`TunnelSection.notes`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from cdpr.analysis.corrections import WallParameters
from cdpr.analysis.errors import ConfigError, InputError
from cdpr.analysis.test_section import SectionGeometry, rectangle, regular_octagon

TUNNEL_KEYS = {
    "kind",
    "shape",
    "octagon_side_m",
    "width_m",
    "height_m",
    "polygon_yz_m",
    "center_yz_m",
    "x_start_m",
    "length_m",
    "area_m2",
    "delta",
    "tau1",
    "tau2",
}
MODEL_KEYS = (
    "volume_m3",
    "blockage_K3",
    "wing_volume_m3",
    "wing_K1",
    "reference_area_m2",
    "span_m",
    "chord_m",
    "lift_slope_per_rad",
)


@dataclass(frozen=True)
class TunnelSection:
    """geometry: the section in {O} (windage); walls: the wall-correction parameters;
    chord_m, span_m: the model's reference lengths; notes: every computed default, in words."""

    geometry: SectionGeometry
    walls: WallParameters
    chord_m: float
    span_m: float
    notes: tuple[str, ...]


def _number(
    source: str,
    key: str,
    table: Mapping[str, Any],
    name: str,
    required: bool = True,
    default: float = math.nan,
    positive: bool = True,
) -> float:
    if name not in table:
        if required:
            raise ConfigError(source, key, "missing")
        return default
    v = table[name]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ConfigError(source, key, f"expected a finite number, got {v!r}")
    if positive and v <= 0:
        raise ConfigError(source, key, f"must be > 0, got {v}")
    return float(v)


def tunnel_section_from_mapping(data: Mapping[str, Any], source: str) -> TunnelSection:
    """Build the :class:`TunnelSection` of a parsed test-matrix file; :class:`ConfigError` names
    ``source``, the key and the problem."""
    tun = data.get("tunnel")
    model = data.get("model")
    if not isinstance(tun, Mapping):
        raise ConfigError(source, "tunnel", "missing (the wall corrections need the test section)")
    if not isinstance(model, Mapping):
        raise ConfigError(source, "model", "missing (the wall corrections need the model's volume)")
    unknown = sorted(set(tun) - TUNNEL_KEYS)
    if unknown:
        raise ConfigError(
            source, f"tunnel.{unknown[0]}", f"unknown key (allowed: {sorted(TUNNEL_KEYS)})"
        )
    kind = tun.get("kind")
    if kind not in ("closed", "open_jet"):
        raise ConfigError(source, "tunnel.kind", f"expected 'closed' or 'open_jet', got {kind!r}")
    center = tun.get("center_yz_m", [0.0, 0.0])
    if not (
        isinstance(center, list)
        and len(center) == 2
        and all(isinstance(c, int | float) and not isinstance(c, bool) for c in center)
    ):
        raise ConfigError(source, "tunnel.center_yz_m", f"expected 2 numbers, got {center!r}")
    shape = tun.get("shape")
    try:
        if shape == "octagon":
            side = _number(source, "tunnel.octagon_side_m", tun, "octagon_side_m")
            poly = regular_octagon(side, center)
        elif shape == "rectangle":
            poly = rectangle(
                _number(source, "tunnel.width_m", tun, "width_m"),
                _number(source, "tunnel.height_m", tun, "height_m"),
                center,
            )
        elif shape == "polygon":
            raw = tun.get("polygon_yz_m")
            try:
                poly = np.array(raw, dtype=np.float64)
            except (TypeError, ValueError):
                raise ConfigError(source, "tunnel.polygon_yz_m", "expected [[y, z], ...]") from None
        else:
            raise ConfigError(
                source,
                "tunnel.shape",
                f"expected 'octagon', 'rectangle' or 'polygon', got {shape!r}",
            )
        x0 = _number(source, "tunnel.x_start_m", tun, "x_start_m", positive=False)
        length = _number(source, "tunnel.length_m", tun, "length_m")
        geometry = SectionGeometry(x0, x0 + length, poly)
    except InputError as exc:
        raise ConfigError(
            source, f"tunnel.{'polygon_yz_m' if shape == 'polygon' else 'shape'}", str(exc)
        ) from None
    area = _number(
        source, "tunnel.area_m2", tun, "area_m2", required=False, default=geometry.area_m2
    )
    delta = _number(source, "tunnel.delta", tun, "delta", positive=False)
    if (kind == "closed") != (delta > 0):
        raise ConfigError(
            source,
            "tunnel.delta",
            f"a {kind} section has delta {'> 0' if kind == 'closed' else '< 0'}, got {delta}",
        )
    tau1 = _number(source, "tunnel.tau1", tun, "tau1")
    tau2 = _number(source, "tunnel.tau2", tun, "tau2", positive=False)

    S = _number(source, "model.reference_area_m2", model, "reference_area_m2")
    span = _number(source, "model.span_m", model, "span_m")
    chord = _number(source, "model.chord_m", model, "chord_m")
    wing_v = _number(
        source,
        "model.wing_volume_m3",
        model,
        "wing_volume_m3",
        required=False,
        default=0.0,
        positive=False,
    )
    wing_k1 = _number(source, "model.wing_K1", model, "wing_K1", required=wing_v > 0, default=0.0)
    notes: list[str] = []
    if "lift_slope_per_rad" in model:
        a = _number(source, "model.lift_slope_per_rad", model, "lift_slope_per_rad")
    else:
        ar = span * span / S
        a = 2 * math.pi * ar / (ar + 2)
        notes.append(f"lift slope not given: 2 pi AR/(AR + 2) = {a:.3f} /rad with AR = {ar:.2f}")
    walls = WallParameters(
        kind=kind,
        area_m2=area,
        delta=delta,
        tau1=tau1,
        tau2=tau2,
        body_volume_m3=_number(source, "model.volume_m3", model, "volume_m3"),
        body_K3=_number(source, "model.blockage_K3", model, "blockage_K3"),
        wing_volume_m3=wing_v,
        wing_K1=wing_k1,
        reference_area_m2=S,
        lift_slope_per_rad=a,
    )
    return TunnelSection(
        geometry=geometry, walls=walls, chord_m=chord, span_m=span, notes=tuple(notes)
    )
