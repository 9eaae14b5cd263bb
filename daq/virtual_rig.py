"""The virtual rig: a physics twin that sends what the tunnel would, through real transports.

Given a :class:`~cdpr.analysis.rig.Rig`, a :class:`Schedule` (poses, wind-off tares, wind steps,
durations, faults) and an :class:`~cdpr.daq.aero_model.AeroModel`, :class:`VirtualRig` computes at
every load-cell sample the true pose, the aero wrench ``W``, the gravity load ``G`` and the tensions
the controller commands, ``distribute(method, A, -(G + W), t_min, t_max)``; then the sensor model
(noise, drift, quantisation, latency, faults) and the transports:

- ``"virtual"``: python-can ``virtual`` bus in this process (frames per ``data_samples/loadcell.dbc``);
- ``"slcan"``: an slcan adapter emulated on a pseudo-terminal (:mod:`cdpr.daq.slcan_emulator`), read
  by python-can's ``slcan`` interface in any process;
- ``"serial"``: the ``$LC`` line protocol (:mod:`cdpr.daq.serial_protocol`) on a pseudo-terminal;
- tunnel conditions as ``$TUN`` lines on a second pseudo-terminal (any transport, if asked).

Usage (in-process, virtual bus)::

    vr = VirtualRig(rig, schedule)                 # truth is computed here (deterministic, seeded)
    kind, settings = vr.source_settings("virtual", channel="vrig-1")["loadcell"]
    src = create_source(kind, "loadcell", settings)   # after `import cdpr.daq.drivers`
    src.open()                                     # open readers BEFORE starting the sender
    run = vr.start("virtual", channel="vrig-1")    # a background thread; run.wait() / run.stop()
    ... src.read() ...
    vr.truth()                                     # dict of arrays; vr.write_truth("truth.npz")

Two processes (slcan or serial)::

    python -m cdpr.daq.virtual_rig --rig R.toml --schedule S.toml --transport slcan \\
        --pty-link /tmp/x/can0 [--tunnel-link /tmp/x/tunnel] [--truth truth.npz] [--wait-reader 10]

prints ``READY <link>`` on stdout once the link exists, waits for a reader (``--wait-reader``
seconds) and runs the schedule once in real time.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdpr.analysis.dynamics import gravity_wrench
from cdpr.analysis.errors import ConfigError
from cdpr.analysis.flow import sutherland_viscosity
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.rig import Rig
from cdpr.analysis.rotations import quaternion_from_euler, rotation_from_euler
from cdpr.analysis.tension import distribute
from cdpr.analysis.test_section import SectionGeometry
from cdpr.analysis.windage import windage_of_rig

from .aero_model import AeroModel, aero_from_mapping
from .files import atomic_output, load_toml
from .loadcell import INT24_MAX, INT24_MIN, Calibration, check_frame_budget

FloatArray = NDArray[np.float64]

FAULT_KINDS = (
    "dropout",
    "slack",
    "saturate",
    "stuck",
    "noise_burst",
    "sensor_fault",
    "port_vanish",
)
TRANSPORTS = ("virtual", "slcan", "serial")
CH_SATURATED, CH_SLACK, CH_FAULT = 1, 2, 4


# --------------------------------------------------------------------------------------------
# schedule
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Segment:
    """One constant test condition: pose of P in {O}, wind speed, duration.

    Values ramp linearly from the previous segment's over ``transition_s`` (quasi-static: the
    inertia of the slow move is neglected).  ``tare``: a wind-off tare segment (wind must be 0).
    """

    label: str
    duration_s: float
    wind_mps: float
    position_O_m: tuple[float, float, float]
    euler_rad: tuple[float, float, float]
    transition_s: float = 0.0
    tare: bool = False
    kind: str = ""
    target_aoa_deg: float = 0.0
    target_sideslip_deg: float = 0.0
    repeat_of: str = ""

    @property
    def is_test_point(self) -> bool:
        """A segment from a test matrix (it has a kind): the rig emits its test-point events."""
        return self.kind != ""


@dataclass(frozen=True)
class Fault:
    """A fault on demand, active over ``[start_s, start_s + duration_s)`` of schedule time.

    kind: one of :data:`FAULT_KINDS`; cable: channel index (0-based) for per-cable faults;
    factor: noise multiplier of ``noise_burst``; value_N: tension a slack cable reads.
    """

    kind: str
    start_s: float
    duration_s: float
    cable: int = -1
    factor: float = 50.0
    value_N: float = 0.3


@dataclass(frozen=True)
class SensorModel:
    """Noise, drift, quantisation (through the calibration), latency and flags of the load cells.

    noise_sd_N: white noise, N; drift_N_per_s: linear drift scale, each channel drifts at
    ``drift_N_per_s * d_i`` with ``d_i`` uniform in [-1, 1] from the seed; latency_s: delay from
    measurement to transmission; slack_threshold_N: below this the slack bit is set;
    offset_counts / gain_N_per_count: the amplifier's true calibration (also what the driver is
    told, unless ``driver_gain_error`` scales the gain the driver is told).
    """

    noise_sd_N: float = 0.05
    drift_N_per_s: float = 0.002
    latency_s: float = 0.002
    slack_threshold_N: float = 2.0
    offset_counts: tuple[float, ...] | None = None
    gain_N_per_count: float | tuple[float, ...] = 5.0e-5
    tunnel_airspeed_sd_mps: float = 0.05
    tunnel_pressure_sd_Pa: float = 2.0
    tunnel_temperature_sd_K: float = 0.02


@dataclass(frozen=True)
class Schedule:
    """A virtual-rig run: segments, faults, rates and models (see the TOML format in the docs)."""

    name: str
    segments: tuple[Segment, ...]
    rate_hz: float = 200.0
    tunnel_rate_hz: float = 10.0
    method: str = "exact"
    seed: int = 0
    bitrate: int = 1_000_000
    faults: tuple[Fault, ...] = ()
    sensor: SensorModel = field(default_factory=SensorModel)
    aero: AeroModel = field(default_factory=AeroModel)
    source: str = "<memory>"

    @property
    def duration_s(self) -> float:
        return float(sum(s.duration_s for s in self.segments))


_SCHED_KEYS = {"name", "rate_hz", "tunnel_rate_hz", "method", "seed", "bitrate"}
_SEG_KEYS = {
    "label",
    "duration_s",
    "wind_mps",
    "position_O_m",
    "euler_rad",
    "euler_deg",
    "transition_s",
    "tare",
    "kind",
    "target_aoa_deg",
    "target_sideslip_deg",
    "repeat_of",
}
POINT_KINDS = ("wind_on", "tare", "zero", "windage")
_FAULT_KEYS = {"kind", "start_s", "duration_s", "cable", "factor", "value_N"}
_TOP = {"schedule", "segments", "faults", "sensor", "aero"}


def _f(source: str, key: str, v: Any, lo: float | None = None, strict: bool = False) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise ConfigError(source, key, f"expected a number, got {v!r}") from None
    if not math.isfinite(x):
        raise ConfigError(source, key, "expected a finite number")
    if lo is not None and (x < lo or (strict and x == lo)):
        raise ConfigError(source, key, f"must be {'>' if strict else '>='} {lo:g}, got {x:g}")
    return x


def _vec3(source: str, key: str, v: Any) -> tuple[float, float, float]:
    if not isinstance(v, list | tuple) or len(v) != 3:
        raise ConfigError(source, key, f"expected 3 numbers, got {v!r}")
    a, b, c = (_f(source, key, x) for x in v)
    return (a, b, c)


def _table(source: str, key: str, value: Any, allowed: Collection[str]) -> Mapping[str, Any]:
    """``value`` as a table whose keys are all in ``allowed`` (else ConfigError at ``key``)."""
    if not isinstance(value, Mapping):
        raise ConfigError(source, key, "expected a table")
    for k in value:
        if k not in allowed:
            raise ConfigError(source, f"{key}.{k}", f"unknown key (allowed: {sorted(allowed)})")
    return value


def schedule_from_mapping(data: Mapping[str, Any], source: str, rig: Rig) -> Schedule:
    """Build and validate a :class:`Schedule` from a parsed schedule file (TOML mapping).

    ``rig`` gives the default pose (its reference pose) and the cable names faults may use.
    Errors are :class:`ConfigError` naming ``source`` and the key (``segments[2].wind_mps``).
    """
    unknown = sorted(set(data) - _TOP)
    if unknown:
        raise ConfigError(source, unknown[0], f"unknown key (allowed: {sorted(_TOP)})")
    sch = _table(source, "schedule", data.get("schedule", {}), _SCHED_KEYS)
    rate = _f(source, "schedule.rate_hz", sch.get("rate_hz", 200.0), 0.0, True)
    t_rate = _f(source, "schedule.tunnel_rate_hz", sch.get("tunnel_rate_hz", 10.0), 0.0, True)
    method = str(sch.get("method", "exact"))
    from cdpr.analysis.tension import METHODS

    if method not in METHODS:
        raise ConfigError(
            source,
            "schedule.method",
            f"unknown tension method {method!r} (known: {sorted(METHODS)})",
        )
    segs_raw = data.get("segments")
    if not isinstance(segs_raw, list) or not segs_raw:
        raise ConfigError(source, "segments", "expected a non-empty array of [[segments]] tables")
    segs = []
    rp, re_ = rig.reference_position_O_m, rig.reference_euler_rad
    ref_p = (float(rp[0]), float(rp[1]), float(rp[2]))
    ref_e = (float(re_[0]), float(re_[1]), float(re_[2]))
    prev_p, prev_e = ref_p, ref_e
    for i, s_raw in enumerate(segs_raw):
        k = f"segments[{i}]"
        s = _table(source, k, s_raw, _SEG_KEYS)
        if "duration_s" not in s:
            raise ConfigError(source, f"{k}.duration_s", "missing")
        dur = _f(source, f"{k}.duration_s", s["duration_s"], 0.0, True)
        wind = _f(source, f"{k}.wind_mps", s.get("wind_mps", 0.0), 0.0)
        kind = s.get("kind", "")
        if kind != "" and kind not in POINT_KINDS:
            raise ConfigError(
                source, f"{k}.kind", f"expected one of {list(POINT_KINDS)}, got {kind!r}"
            )
        tare = bool(s.get("tare", False)) or kind in ("tare", "zero")
        if kind in ("wind_on", "windage") and wind == 0:
            raise ConfigError(source, f"{k}.wind_mps", f"a {kind} point needs wind > 0")
        if tare and wind != 0:
            raise ConfigError(source, f"{k}.wind_mps", "a tare segment is wind-off: must be 0")
        pos = (
            _vec3(source, f"{k}.position_O_m", s["position_O_m"]) if "position_O_m" in s else prev_p
        )
        if "euler_rad" in s and "euler_deg" in s:
            raise ConfigError(source, f"{k}.euler_deg", "give euler_rad or euler_deg, not both")
        if "euler_rad" in s:
            eul = _vec3(source, f"{k}.euler_rad", s["euler_rad"])
        elif "euler_deg" in s:
            d = _vec3(source, f"{k}.euler_deg", s["euler_deg"])
            eul = (math.radians(d[0]), math.radians(d[1]), math.radians(d[2]))
        else:
            eul = prev_e
        trans = _f(source, f"{k}.transition_s", s.get("transition_s", 0.0), 0.0)
        if trans > dur:
            raise ConfigError(source, f"{k}.transition_s", f"longer than the segment ({dur:g} s)")
        repeat_of = s.get("repeat_of", "")
        if not isinstance(repeat_of, str):
            raise ConfigError(source, f"{k}.repeat_of", f"expected a label, got {repeat_of!r}")
        segs.append(
            Segment(
                str(s.get("label", f"seg{i}")),
                dur,
                wind,
                pos,
                eul,
                trans,
                tare,
                kind,
                _f(source, f"{k}.target_aoa_deg", s.get("target_aoa_deg", 0.0)),
                _f(source, f"{k}.target_sideslip_deg", s.get("target_sideslip_deg", 0.0)),
                repeat_of,
            )
        )
        prev_p, prev_e = pos, eul
    total = sum(s.duration_s for s in segs)
    faults = []
    f_raw = data.get("faults", [])
    if not isinstance(f_raw, list):
        raise ConfigError(source, "faults", "expected an array of [[faults]] tables")
    for i, fr_raw in enumerate(f_raw):
        k = f"faults[{i}]"
        fr = _table(source, k, fr_raw, _FAULT_KEYS)
        kind = fr.get("kind")
        if kind not in FAULT_KINDS:
            raise ConfigError(
                source, f"{k}.kind", f"expected one of {list(FAULT_KINDS)}, got {kind!r}"
            )
        start = _f(source, f"{k}.start_s", fr.get("start_s", 0.0), 0.0)
        dur = _f(source, f"{k}.duration_s", fr.get("duration_s", 0.0), 0.0, True)
        if start >= total:
            raise ConfigError(
                source, f"{k}.start_s", f"after the end of the schedule ({total:g} s)"
            )
        cable = -1
        if kind in ("slack", "saturate", "stuck", "sensor_fault"):
            if "cable" not in fr:
                raise ConfigError(
                    source, f"{k}.cable", f"a {kind} fault needs a cable (name or index)"
                )
            c = fr["cable"]
            if isinstance(c, str):
                if c not in rig.cable_names:
                    raise ConfigError(
                        source,
                        f"{k}.cable",
                        f"unknown cable {c!r} (rig has {list(rig.cable_names)})",
                    )
                cable = rig.cable_names.index(c)
            elif isinstance(c, int) and 0 <= c < rig.n_cables:
                cable = c
            else:
                raise ConfigError(
                    source, f"{k}.cable", f"expected a cable name or 0..{rig.n_cables - 1}"
                )
        faults.append(
            Fault(
                kind,
                start,
                dur,
                cable,
                _f(source, f"{k}.factor", fr.get("factor", 50.0), 0.0),
                _f(source, f"{k}.value_N", fr.get("value_N", 0.3)),
            )
        )
    sens_raw = data.get("sensor", {})
    if not isinstance(sens_raw, Mapping):
        raise ConfigError(source, "sensor", "expected a table")
    sens_fields = SensorModel.__dataclass_fields__
    kw: dict[str, Any] = {}
    for key, v in sens_raw.items():
        if key not in sens_fields:
            raise ConfigError(
                source, f"sensor.{key}", f"unknown key (allowed: {sorted(sens_fields)})"
            )
        if key == "offset_counts" or (key == "gain_N_per_count" and isinstance(v, list)):
            if not isinstance(v, list) or len(v) != rig.n_cables:
                raise ConfigError(source, f"sensor.{key}", f"expected {rig.n_cables} numbers")
            kw[key] = tuple(_f(source, f"sensor.{key}", x) for x in v)
        else:
            kw[key] = _f(source, f"sensor.{key}", v, 0.0)
    if np.any(np.asarray(kw.get("gain_N_per_count", 1.0)) <= 0):
        raise ConfigError(source, "sensor.gain_N_per_count", "must be > 0")
    seed = sch.get("seed", 0)
    if not isinstance(seed, int):
        raise ConfigError(source, "schedule.seed", f"expected an integer, got {seed!r}")
    bitrate = sch.get("bitrate", 1_000_000)
    if not isinstance(bitrate, int) or bitrate <= 0:
        raise ConfigError(
            source, "schedule.bitrate", f"expected a positive integer, got {bitrate!r}"
        )
    # the CAN transports send 4 frames per sample (data_samples/loadcell.dbc): they must fit the bus
    check_frame_budget(source, "schedule", bitrate, rate, 4)
    return Schedule(
        name=str(sch.get("name", Path(source).stem)),
        segments=tuple(segs),
        rate_hz=rate,
        tunnel_rate_hz=t_rate,
        method=method,
        seed=seed,
        bitrate=bitrate,
        faults=tuple(faults),
        sensor=SensorModel(**kw),
        aero=aero_from_mapping(data.get("aero"), source),
        source=source,
    )


def load_schedule(path: str | os.PathLike[str], rig: Rig) -> Schedule:
    """Read a schedule TOML file (errors name the file and key)."""
    return schedule_from_mapping(load_toml(path), str(Path(path)), rig)


# --------------------------------------------------------------------------------------------
# truth
# --------------------------------------------------------------------------------------------
def _atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    with atomic_output(path, "wb") as fh:
        fh.write(data)


class VirtualRig:
    """The physics twin; all truth is computed at construction (deterministic for a seed).

    rig: the rig; schedule: the run; aero: overrides ``schedule.aero``; seed: overrides
    ``schedule.seed``.  Times: ``t_rel_ns`` from the schedule start; ``t0_ns`` (host epoch ns) is
    set when a transport starts (or by the caller) and ``true_pose_at`` takes host times.
    """

    def __init__(
        self,
        rig: Rig,
        schedule: Schedule,
        aero: AeroModel | None = None,
        seed: int | None = None,
        section: SectionGeometry | None = None,
    ) -> None:
        self.rig = rig
        self.section = section  # the test section: cable drag is on when given
        self.schedule = schedule
        self.aero = aero if aero is not None else schedule.aero
        self.seed = schedule.seed if seed is None else int(seed)
        self.t0_ns: int | None = None
        self.speed = 1.0  # time scale of the run that set t0_ns (host time = t0 + t_rel / speed)
        self.cable_names = list(rig.cable_names)
        m = rig.n_cables
        rng = np.random.default_rng(self.seed)
        sens = schedule.sensor
        if sens.offset_counts is not None:
            off = np.asarray(sens.offset_counts, dtype=np.float64)
        else:
            off = rng.integers(-60_000, 60_000, size=m).astype(np.float64)
        gain = np.broadcast_to(np.asarray(sens.gain_N_per_count, dtype=np.float64), (m,))
        self.calibration = Calibration(off, gain.copy())
        self.drift_rate_N_per_s = sens.drift_N_per_s * rng.uniform(-1.0, 1.0, size=m)
        self._compute_truth(rng)

    # -- physics ---------------------------------------------------------------------------
    def _cable_drag_O(self, pos: FloatArray, R: FloatArray, wind: FloatArray) -> FloatArray:
        """Cable (and platform) windage at P in {O} (n, 6), N and N m: zero without a section.

        The one hook of the cable drag: :func:`cdpr.analysis.windage.windage_of_rig` (the rig's
        cable diameters and drag coefficients) with the aero model's p and T.  The wrench does
        not depend on the tensions (only the cables' turn angles do), so no iteration is needed.
        """
        if self.section is None:
            return np.zeros((pos.shape[0], 6))
        rig, aero = self.rig, self.aero
        return windage_of_rig(
            rig,
            self.section,
            pos,
            R,
            np.ones((pos.shape[0], rig.n_cables)),
            wind,
            aero.air_density(aero.static_pressure_Pa, aero.temperature_K),
            sutherland_viscosity(aero.temperature_K),
        ).wrench_N

    def _state_at(
        self, t_s: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int64]]:
        """(position (n,3), euler (n,3), wind (n,), segment index (n,)) at schedule times t_s."""
        segs = self.schedule.segments
        ends = np.cumsum([s.duration_s for s in segs])
        starts = ends - np.array([s.duration_s for s in segs])
        idx = np.minimum(np.searchsorted(ends, t_s, side="right"), len(segs) - 1)
        P = np.array([s.position_O_m for s in segs])
        E = np.array([s.euler_rad for s in segs])
        V = np.array([s.wind_mps for s in segs])
        ref_p = self.rig.reference_position_O_m
        ref_e = self.rig.reference_euler_rad
        P_prev = np.vstack([P[0] if segs[0].transition_s == 0 else ref_p, P[:-1]])
        E_prev = np.vstack([E[0] if segs[0].transition_s == 0 else ref_e, E[:-1]])
        V_prev = np.concatenate([[0.0], V[:-1]])
        tr = np.array([s.transition_s for s in segs])
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.where(tr[idx] > 0, (t_s - starts[idx]) / tr[idx], 1.0)
        frac = np.clip(frac, 0.0, 1.0)
        pos = P_prev[idx] + frac[:, None] * (P[idx] - P_prev[idx])
        eul = E_prev[idx] + frac[:, None] * (E[idx] - E_prev[idx])
        wind = V_prev[idx] + frac * (V[idx] - V_prev[idx])
        return pos, eul, wind, idx

    def physics(
        self,
        position_O_m: FloatArray,
        R_O_P: FloatArray,
        airspeed_mps: FloatArray,
        model_on: NDArray[np.bool_],
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The loads on the platform at P in {O} (each (n, 6), N and N m): ``(W_aero, G, D)``.

        W_aero: the model's aero wrench at the airspeed (zero where ``model_on`` is False: a
        model-off windage point); G: gravity of platform + model from the rig file; D: the
        cable (and platform) windage from :meth:`_cable_drag_O` (zero without a test section;
        present on model-off points too, which is what a measured windage tare sees).  The
        cables carry ``A T = -(G + W_aero + D)``.  Every load the twin simulates is added here.
        """
        rig = self.rig
        W = self.aero.wrench_O(airspeed_mps, R_O_P) * model_on[:, None]
        G = gravity_wrench(rig.mass_kg, rig.com_P_m, R_O_P, rig.gravity_O_mps2)
        D = self._cable_drag_O(position_O_m, R_O_P, airspeed_mps)
        return W, G, D

    def _compute_truth(self, rng: np.random.Generator) -> None:
        sch, rig, sens = self.schedule, self.rig, self.schedule.sensor
        n = max(1, int(round(sch.duration_s * sch.rate_hz)))
        k = np.arange(n)
        self.t_rel_ns = np.round(k * 1e9 / sch.rate_hz).astype(np.int64)
        t_s = self.t_rel_ns.astype(np.float64) * 1e-9
        pos, eul, wind, seg = self._state_at(t_s)
        # tensions at the unique states only (a few per segment), then broadcast
        model_on = np.array([s.kind != "windage" for s in sch.segments], dtype=np.float64)[seg]
        state = np.concatenate([pos, eul, wind[:, None], model_on[:, None]], axis=1)
        uniq, inv = np.unique(np.round(state, 12), axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        R_u = rotation_from_euler(uniq[:, 3:6])
        A_u = structure_matrix(rig.anchors_O_m, rig.attach_P_m, uniq[:, :3], R_u)
        W_u, G_u, D_u = self.physics(uniq[:, :3], R_u, uniq[:, 6], uniq[:, 7] > 0.5)
        res = distribute(sch.method, A_u, -(G_u + W_u + D_u), rig.t_min_N, rig.t_max_N)
        bad = np.flatnonzero(~np.asarray(res.feasible))
        if bad.size:
            j = int(np.flatnonzero(inv == bad[0])[0])
            s = int(seg[j])
            raise ConfigError(
                sch.source,
                f"segments[{s}]",
                f"no feasible tensions with method {sch.method!r} at t = {t_s[j]:.3f} s "
                f"(wind {wind[j]:.2f} m/s): residual {float(res.residual_N[bad[0]]):.3g}, "
                f"limit violation {float(res.max_violation_N[bad[0]]):.3g} N",
            )
        T_true = np.asarray(res.tensions_N)[inv]
        self.position_O_m = pos
        self.euler_rad = eul
        self.wind_mps = wind
        self.segment_index = seg.astype(np.int64)
        self.wrench_aero_O = W_u[inv]
        self.wrench_gravity_O = G_u[inv]
        self.wrench_cable_drag_O = D_u[inv]
        self.tensions_true_N = T_true

        # -- sensor model ------------------------------------------------------------------
        m = rig.n_cables
        noise_sd = np.full((n, m), sens.noise_sd_N)
        sent = np.ones(n, dtype=bool)
        port_up = np.ones(n, dtype=bool)
        fault_code = np.zeros((n, m), dtype=np.int64)
        windows = []
        for f in sch.faults:
            w = (t_s >= f.start_s) & (t_s < f.start_s + f.duration_s)
            windows.append((f, w))
            if f.kind == "noise_burst":
                noise_sd[w] *= f.factor
            elif f.kind == "dropout":
                sent[w] = False
            elif f.kind == "port_vanish":
                port_up[w] = False
        T_meas = (
            T_true + self.drift_rate_N_per_s * t_s[:, None] + rng.standard_normal((n, m)) * noise_sd
        )
        for f, w in windows:
            if f.kind == "slack":
                T_meas[w, f.cable] = f.value_N + sens.noise_sd_N * rng.standard_normal(int(w.sum()))
                fault_code[w, f.cable] |= 1
        counts_f = np.rint(self.calibration.to_counts(T_meas))
        status = np.zeros((n, m), dtype=np.int64)
        status[T_meas < sens.slack_threshold_N] |= CH_SLACK
        for f, w in windows:
            c = f.cable
            if f.kind == "saturate":
                counts_f[w, c] = INT24_MAX
                fault_code[w, c] |= 2
            elif f.kind == "stuck":
                first = int(np.flatnonzero(w)[0]) if w.any() else 0
                counts_f[w, c] = counts_f[max(first - 1, 0), c]
                fault_code[w, c] |= 4
            elif f.kind == "sensor_fault":
                counts_f[w, c] = 0
                status[w, c] |= CH_FAULT
                fault_code[w, c] |= 8
        sat = (counts_f >= INT24_MAX) | (counts_f <= INT24_MIN)
        counts = np.clip(counts_f, INT24_MIN, INT24_MAX).astype(np.int64)
        status[sat] |= CH_SATURATED
        self.tensions_sensor_N = T_meas
        self.counts = counts
        self.channel_status = status
        self.sent = sent
        self.port_up = port_up
        self.fault_code = fault_code

        # -- tunnel conditions ---------------------------------------------------------------
        nt = max(1, int(round(sch.duration_s * sch.tunnel_rate_hz)))
        self.tunnel_t_rel_ns = np.round(np.arange(nt) * 1e9 / sch.tunnel_rate_hz).astype(np.int64)
        _, _, wind_t, _ = self._state_at(self.tunnel_t_rel_ns.astype(np.float64) * 1e-9)
        self.tunnel_airspeed_true_mps = wind_t
        self.tunnel_airspeed_mps = np.maximum(
            0.0, wind_t + sens.tunnel_airspeed_sd_mps * rng.standard_normal(nt)
        )
        self.tunnel_static_pressure_Pa = (
            self.aero.static_pressure_Pa + sens.tunnel_pressure_sd_Pa * rng.standard_normal(nt)
        )
        self.tunnel_temperature_K = (
            self.aero.temperature_K + sens.tunnel_temperature_sd_K * rng.standard_normal(nt)
        )

    # -- truth API ---------------------------------------------------------------------------
    @property
    def n_samples(self) -> int:
        return int(self.t_rel_ns.shape[0])

    def truth(self) -> dict[str, np.ndarray]:
        """Ground truth arrays, one row per load-cell sample ``k`` (counter ``k % 256``, serial seq
        ``k``): ``t_rel_ns`` (n,), ``t_ns`` (n,, host epoch, -1 before start), ``position_O_m``
        (n, 3), ``euler_rad`` (n, 3), ``quaternion_wxyz`` (n, 4), ``wind_mps`` (n,),
        ``wrench_aero_O`` (n, 6), ``wrench_gravity_O`` (n, 6) and ``wrench_cable_drag_O`` (n, 6,
        zero without a test section) at P in {O} (N, N m),
        ``tensions_true_N`` (n, m) physics, ``tensions_sensor_N`` (n, m) after noise/drift/faults
        before quantisation, ``counts`` (n, m), ``channel_status`` (n, m) bits 1 sat 2 slack
        4 fault, ``sent`` (n,) False in dropouts, ``port_up`` (n,), ``fault_code`` (n, m), segment
        index, the calibration, and the tunnel arrays (``tunnel_*``)."""
        return {
            "t_rel_ns": self.t_rel_ns,
            "t_ns": self._host_ns(self.t_rel_ns),
            "position_O_m": self.position_O_m,
            "euler_rad": self.euler_rad,
            "quaternion_wxyz": quaternion_from_euler(self.euler_rad),
            "wind_mps": self.wind_mps,
            "segment_index": self.segment_index,
            "wrench_aero_O": self.wrench_aero_O,
            "wrench_gravity_O": self.wrench_gravity_O,
            "wrench_cable_drag_O": self.wrench_cable_drag_O,
            "tensions_true_N": self.tensions_true_N,
            "tensions_sensor_N": self.tensions_sensor_N,
            "counts": self.counts,
            "channel_status": self.channel_status,
            "sent": self.sent,
            "port_up": self.port_up,
            "fault_code": self.fault_code,
            "offset_counts": self.calibration.offset_counts,
            "gain_N_per_count": self.calibration.gain_N_per_count,
            "tunnel_t_rel_ns": self.tunnel_t_rel_ns,
            "tunnel_t_ns": self._host_ns(self.tunnel_t_rel_ns),
            "tunnel_airspeed_true_mps": self.tunnel_airspeed_true_mps,
            "tunnel_airspeed_mps": self.tunnel_airspeed_mps,
            "tunnel_static_pressure_Pa": self.tunnel_static_pressure_Pa,
            "tunnel_temperature_K": self.tunnel_temperature_K,
        }

    def _host_ns(self, t_rel_ns: np.ndarray) -> np.ndarray:
        if self.t0_ns is None:
            return np.full_like(t_rel_ns, -1)
        return self.t0_ns + np.round(t_rel_ns / self.speed).astype(np.int64)

    def segment_events(self) -> list[dict[str, Any]]:
        """One event per segment start: ``t_rel_ns``, ``t_ns`` (host, -1 before the start),
        ``label``, ``wind_mps``, ``tare``, ``position_O_m``, ``euler_rad`` (for an events stream)."""
        out = []
        t = 0.0
        for i, s in enumerate(self.schedule.segments):
            t_rel = int(round(t * 1e9))
            out.append(
                {
                    "segment": i,
                    "t_rel_ns": t_rel,
                    "t_ns": int(self._host_ns(np.array([t_rel], dtype=np.int64))[0]),
                    "label": s.label,
                    "wind_mps": s.wind_mps,
                    "tare": s.tare,
                    "position_O_m": list(s.position_O_m),
                    "euler_rad": list(s.euler_rad),
                }
            )
            t += s.duration_s
        return out

    def test_point_events(self) -> list[dict[str, Any]]:
        """The ``test_point`` events of the schedule's test-matrix segments, in time order.

        A point starts when its ramp ends (``transition_s`` into the segment) and ends with its
        segment.  Each: ``t_rel_ns`` and the event fields agreed for ``/events``: ``name``
        ("test_point"), ``point``, ``phase`` ("start" | "end"), ``kind``, ``target_aoa_deg``,
        ``target_sideslip_deg``, ``target_airspeed_mps``, ``repeat_of``, ``message``.
        """
        out = []
        t = 0.0
        for s in self.schedule.segments:
            if s.is_test_point:
                for phase, t_s in (("start", t + s.transition_s), ("end", t + s.duration_s)):
                    out.append(
                        {
                            "t_rel_ns": int(round(t_s * 1e9)),
                            "message": f"test point {s.label} {phase}",
                            "name": "test_point",
                            "point": s.label,
                            "phase": phase,
                            "kind": s.kind,
                            "target_aoa_deg": s.target_aoa_deg,
                            "target_sideslip_deg": s.target_sideslip_deg,
                            "target_airspeed_mps": s.wind_mps,
                            "repeat_of": s.repeat_of,
                        }
                    )
            t += s.duration_s
        return out

    def write_calibration(self, path: str | os.PathLike[str]) -> Path:
        """Write the amplifiers' true calibration as a load-cell calibration file (the format
        ``cdpr calibrate loadcells`` writes), atomically: what ``cdpr import`` of this rig's CAN
        frames needs."""
        from .loadcell import calibration_file_text

        text = calibration_file_text(
            self.cable_names,
            self.calibration,
            f"virtual-rig:{self.schedule.name}:seed{self.seed}",
            {"source": f"virtual rig {self.rig.name}, schedule {self.schedule.name}"},
        )
        _atomic_write_bytes(path, text.encode())
        return Path(path)

    def write_truth(self, path: str | os.PathLike[str]) -> Path:
        """Write the truth atomically: ``.npz`` (all arrays plus ``cable_names``, ``segment_labels``)
        or ``.csv`` (one row per sample: times, pose, wind, wrench, true and sensor tensions)."""
        p = Path(path)
        tr = self.truth()
        if p.suffix == ".npz":
            buf = io.BytesIO()
            arrays: dict[str, Any] = {
                "cable_names": np.array(self.cable_names),
                "segment_labels": np.array([s.label for s in self.schedule.segments]),
                "segment_kinds": np.array([s.kind for s in self.schedule.segments]),
                **tr,
            }
            np.savez(buf, allow_pickle=False, **arrays)
            _atomic_write_bytes(p, buf.getvalue())
        elif p.suffix == ".csv":
            cols: dict[str, np.ndarray] = {
                "sample": np.arange(self.n_samples),
                "t_rel_ns": tr["t_rel_ns"],
                "t_ns": tr["t_ns"],
                "segment": self.segment_index,
            }
            for j, c in enumerate(("x_m", "y_m", "z_m")):
                cols[c] = self.position_O_m[:, j]
            for j, c in enumerate(("roll_rad", "pitch_rad", "yaw_rad")):
                cols[c] = self.euler_rad[:, j]
            cols["wind_mps"] = self.wind_mps
            for j, c in enumerate(("fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm")):
                cols[c] = self.wrench_aero_O[:, j]
            for j, name in enumerate(self.cable_names):
                cols[f"T_{name}_N"] = self.tensions_true_N[:, j]
            for j, name in enumerate(self.cable_names):
                cols[f"Tsensor_{name}_N"] = self.tensions_sensor_N[:, j]
            cols["sent"] = self.sent.astype(int)
            header = ",".join(cols) + "\n"
            body = np.column_stack([np.asarray(v, dtype=np.float64) for v in cols.values()])
            out = io.StringIO()
            out.write(
                f"# virtual-rig truth: rig {self.rig.name}, schedule {self.schedule.name}, "
                f"method {self.schedule.method}, seed {self.seed}\n"
            )
            out.write(header)
            np.savetxt(out, body, delimiter=",", fmt="%.10g")
            _atomic_write_bytes(p, out.getvalue().encode())
        else:
            raise ValueError(f"truth path must end in .npz or .csv, got {p.name}")
        return p

    def pose_at_rel(self, t_rel_ns: Any) -> tuple[FloatArray, FloatArray]:
        """True pose at schedule times ``t_rel_ns`` (...,): (position_O_m (..., 3), R_O_P (..., 3, 3))."""
        t = np.asarray(t_rel_ns, dtype=np.float64) * 1e-9
        shape = t.shape
        pos, eul, _, _ = self._state_at(np.clip(t.reshape(-1), 0.0, self.schedule.duration_s))
        return pos.reshape(shape + (3,)), rotation_from_euler(eul).reshape(shape + (3, 3))

    def true_pose_at(self, t_ns: Any) -> tuple[FloatArray, FloatArray]:
        """True pose at host times ``t_ns`` (..., epoch ns): (position_O_m (..., 3), R_O_P (..., 3, 3)).

        Host time maps to schedule time as ``(t_ns - t0_ns) * speed``; times before the start (or
        any time while ``t0_ns`` is None: the rig has not started) give the initial pose, times
        after the end the final pose.
        """
        t = np.asarray(t_ns, dtype=np.int64)
        if self.t0_ns is None:
            return self.pose_at_rel(np.zeros(t.shape))
        return self.pose_at_rel((t - self.t0_ns).astype(np.float64) * self.speed)

    # -- frames and lines ------------------------------------------------------------------
    def can_frames(self) -> tuple[list[int], NDArray[np.uint8]]:
        """CAN frame ids (per the DBC) and data bytes (n, n_frames, 8) of every sample.

        The little-endian (Intel) signals of the DBC are packed with numpy in one go; a sample of
        frames is cross-checked against cantools' own encoder.
        """
        from .can_source import DEFAULT_DBC, load_dbc

        db = load_dbc(DEFAULT_DBC)
        m = self.rig.n_cables
        if m > 8:
            raise ValueError("the shipped DBC carries 8 channels")
        msgs = [msg for msg in db.messages if any(s.name.endswith("_Counts") for s in msg.signals)]
        msgs.sort(key=lambda x: x.frame_id)
        n = self.n_samples
        bits = {"Saturated": CH_SATURATED, "Slack": CH_SLACK, "Fault": CH_FAULT}

        def signal_values(name: str) -> NDArray[np.int64]:
            if name == "Counter":
                return np.arange(n, dtype=np.int64) % 256
            ch = int(name[2 : name.index("_")]) - 1
            what = name[name.index("_") + 1 :]
            if ch >= m:
                return np.zeros(n, dtype=np.int64)
            if what == "Counts":
                return self.counts[:, ch].astype(np.int64)
            return ((self.channel_status[:, ch] & bits[what]) != 0).astype(np.int64)

        out = np.zeros((n, len(msgs), 8), dtype=np.uint8)
        for j, msg in enumerate(msgs):
            word = np.zeros(n, dtype=np.uint64)
            for sig in msg.signals:
                if sig.byte_order != "little_endian":
                    raise ValueError(f"{msg.name}.{sig.name}: only Intel byte order is packed")
                v = signal_values(sig.name) & ((1 << sig.length) - 1)  # two's complement
                word |= v.astype(np.uint64) << np.uint64(sig.start)
            out[:, j, :] = word.astype("<u8").view(np.uint8).reshape(n, 8)[:, : msg.length]
            for k in {0, n // 2, n - 1}:  # cross-check with cantools
                ref = msg.encode(
                    {sg.name: int(signal_values(sg.name)[k]) for sg in msg.signals},
                    scaling=False,
                    strict=False,
                )
                if bytes(out[k, j]) != ref:
                    raise AssertionError(f"{msg.name}: numpy packing disagrees with cantools")
        return [msg.frame_id for msg in msgs], out

    def serial_line(self, k: int) -> bytes:
        """The ``$LC`` line of sample ``k``."""
        from .serial_protocol import format_loadcell_line

        st = 0
        for i in range(self.rig.n_cables):
            st |= int(self.channel_status[k, i]) << (3 * i)
        t_dev_us = int(self.t_rel_ns[k] // 1000)
        return format_loadcell_line(k, t_dev_us, self.counts[k].tolist(), st)

    def tunnel_line(self, j: int) -> bytes:
        from .serial_protocol import format_tunnel_line

        return format_tunnel_line(
            j,
            float(self.tunnel_airspeed_mps[j]),
            float(self.tunnel_static_pressure_Pa[j]),
            float(self.tunnel_temperature_K[j]),
        )

    # -- driver settings for the matching readers -------------------------------------------
    def source_settings(
        self,
        transport: str,
        channel: str | None = None,
        link: str | None = None,
        tunnel_link: str | None = None,
    ) -> dict[str, tuple[str, dict[str, Any]]]:
        """Driver kind and settings that read this rig's output: ``{"loadcell": (kind, settings),
        "tunnel": (kind, settings)}`` (tunnel only if ``tunnel_link``), for ``create_source``."""
        cal = {
            "cables": list(self.cable_names),
            "offset_counts": self.calibration.offset_counts.tolist(),
            "gain_N_per_count": self.calibration.gain_N_per_count.tolist(),
            "rate_hz": self.schedule.rate_hz,
        }
        out: dict[str, tuple[str, dict[str, Any]]] = {}
        if transport == "virtual":
            out["loadcell"] = (
                "can_loadcell",
                {
                    "interface": "virtual",
                    "channel": channel or "vrig",
                    "bitrate": self.schedule.bitrate,
                    "bus_options": {"receive_own_messages": False},
                    **cal,
                },
            )
        elif transport == "slcan":
            if link is None:
                raise ValueError("slcan: the pty link path is required")
            out["loadcell"] = (
                "can_loadcell",
                {
                    "interface": "slcan",
                    "channel": str(link),
                    "bitrate": self.schedule.bitrate,
                    "bus_options": {"sleep_after_open": 0.0, "tty_baudrate": 115200},
                    **cal,
                },
            )
        elif transport == "serial":
            if link is None:
                raise ValueError("serial: the pty link path is required")
            out["loadcell"] = ("serial_loadcell", {"port": str(link), "baudrate": 921600, **cal})
        else:
            raise ValueError(f"transport: expected one of {TRANSPORTS}, got {transport!r}")
        if tunnel_link is not None:
            out["tunnel"] = (
                "serial_tunnel",
                {
                    "port": str(tunnel_link),
                    "baudrate": 115200,
                    "rate_hz": self.schedule.tunnel_rate_hz,
                },
            )
        return out

    def make_sources(
        self,
        transport: str,
        channel: str | None = None,
        link: str | None = None,
        tunnel_link: str | None = None,
        origin: str = "<virtual rig>",
    ) -> dict[str, Any]:
        """The reader :class:`~cdpr.daq.source.Source` objects of :meth:`source_settings`, built
        with ``create_source`` (not opened): ``{"loadcell": Source, "tunnel": Source}``."""
        from . import drivers  # noqa: F401  (registers the driver kinds)
        from .source import create_source

        settings = self.source_settings(transport, channel, link, tunnel_link)
        return {
            name: create_source(kind, name, st, origin) for name, (kind, st) in settings.items()
        }

    # -- transports --------------------------------------------------------------------------
    def start(
        self,
        transport: str = "virtual",
        channel: str | None = None,
        link: str | os.PathLike[str] | None = None,
        tunnel_link: str | os.PathLike[str] | None = None,
        wait_reader_s: float = 0.0,
        speed: float = 1.0,
    ) -> RigRun:
        """Start sending in a background thread; returns a :class:`RigRun` (``wait()``, ``stop()``).

        transport: ``"virtual"`` (python-can virtual bus ``channel``), ``"slcan"`` or ``"serial"``
        (a pty published at ``link``); tunnel_link: also send ``$TUN`` lines on a pty there.
        wait_reader_s: for pty transports, wait up to this long for a reader (slcan: for ``O``)
        before the clock starts.  speed: time scale (2.0 = twice real time).
        """
        run = RigRun(self, transport, channel, link, tunnel_link, wait_reader_s, speed)
        run.start()
        return run

    def run_transport(self, transport: str = "virtual", **kwargs: Any) -> RigRun:
        """Run the whole schedule, blocking until it has been sent, then close the transports;
        same arguments as :meth:`start` (``kind=`` is accepted as an alias of ``transport``)."""
        transport = kwargs.pop("kind", transport)
        run = self.start(transport, **kwargs)
        try:
            run.wait()
        finally:
            run.stop()
        return run


class RigRun:
    """A running virtual rig (a sender thread); created by :meth:`VirtualRig.start`."""

    def __init__(
        self,
        vr: VirtualRig,
        transport: str,
        channel: str | None,
        link: str | os.PathLike[str] | None,
        tunnel_link: str | os.PathLike[str] | None,
        wait_reader_s: float,
        speed: float,
    ) -> None:
        if transport not in TRANSPORTS:
            raise ValueError(f"transport: expected one of {TRANSPORTS}, got {transport!r}")
        if transport != "virtual" and link is None:
            raise ValueError(f"transport {transport!r} needs a pty link path")
        self.vr = vr
        self.transport = transport
        self.channel = channel or "vrig"
        self.link = None if link is None else Path(link)
        self.tunnel_link = None if tunnel_link is None else Path(tunnel_link)
        self.wait_reader_s = float(wait_reader_s)
        self.speed = float(speed)
        self.samples_sent = 0
        self.frames_sent = 0
        self.tunnel_sent = 0
        self.error: BaseException | None = None
        self.done = threading.Event()
        self.started = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._main, name="virtual-rig", daemon=True)
        self._send_sample: Callable[[int], int] | None = None
        self._closers: list[Callable[[], None]] = []
        self._vanishers: list[tuple[Callable[[], None], Callable[[], None]]] = []
        self._tunnel_port: Any = None
        self._setup()

    def _setup(self) -> None:
        vr = self.vr
        if self.transport in ("virtual", "slcan"):
            ids, data = vr.can_frames()
            self._frame_ids, self._frame_data = ids, data
        if self.transport == "virtual":
            import can

            bus = can.Bus(
                interface="virtual",
                channel=self.channel,
                bitrate=vr.schedule.bitrate,
                receive_own_messages=False,
            )
            self._closers.append(bus.shutdown)

            def send_virtual(k: int) -> int:
                for j, fid in enumerate(self._frame_ids):
                    bus.send(
                        can.Message(
                            arbitration_id=fid,
                            data=self._frame_data[k, j].tobytes(),
                            is_extended_id=False,
                            timestamp=time.time(),
                        )
                    )
                return len(self._frame_ids)

            self._send_sample = send_virtual
        elif self.transport == "slcan":
            from .slcan_emulator import SlcanEmulator

            assert self.link is not None
            emu = SlcanEmulator(self.link)
            self.emulator = emu
            self._closers.append(emu.close)
            self._vanishers.append((emu.vanish, emu.restore))

            def send_slcan(k: int) -> int:
                n = 0
                for j, fid in enumerate(self._frame_ids):
                    n += emu.send(fid, self._frame_data[k, j].tobytes())
                return n

            self._send_sample = send_slcan
        else:
            from .slcan_emulator import PtyPort

            assert self.link is not None
            port = PtyPort(self.link)
            self.port = port
            self._closers.append(port.close)
            self._vanishers.append((port.vanish, port.restore))

            def send_serial(k: int) -> int:
                return int(port.write(vr.serial_line(k)))

            self._send_sample = send_serial
        if self.tunnel_link is not None:
            from .slcan_emulator import PtyPort

            tp = PtyPort(self.tunnel_link)
            self._tunnel_port = tp
            self._closers.append(tp.close)

    def _wait_reader(self) -> None:
        if self.wait_reader_s <= 0 or self.transport == "virtual":
            return
        end = time.monotonic() + self.wait_reader_s
        while time.monotonic() < end and not self._stop.is_set():
            if self.transport == "slcan":
                if self.emulator.is_open and self.emulator.port.reader_attached():
                    break
            elif self.port.reader_attached():
                break
            time.sleep(0.005)
        if self._tunnel_port is not None:
            while time.monotonic() < end and not self._tunnel_port.reader_attached():
                time.sleep(0.005)

    def start(self) -> None:
        self._thread.start()

    def _main(self) -> None:
        vr = self.vr
        try:
            self._wait_reader()
            t0 = time.time_ns()
            vr.t0_ns = t0
            vr.speed = self.speed
            self.started.set()
            lat_ns = int(vr.schedule.sensor.latency_s * 1e9)
            ev_t = np.concatenate([vr.t_rel_ns + lat_ns, vr.tunnel_t_rel_ns])
            ev_kind = np.concatenate(
                [np.zeros(vr.n_samples, np.int8), np.ones(vr.tunnel_t_rel_ns.shape[0], np.int8)]
            )
            ev_idx = np.concatenate(
                [np.arange(vr.n_samples), np.arange(vr.tunnel_t_rel_ns.shape[0])]
            )
            order = np.argsort(ev_t, kind="stable")
            vanished = False
            mono0 = time.monotonic_ns()
            for e in order:
                if self._stop.is_set():
                    break
                target = mono0 + int(ev_t[e] / self.speed)
                delay = (target - time.monotonic_ns()) * 1e-9
                if delay > 0:
                    self._flush_ports()
                    if self._stop.wait(max(0.0, (target - time.monotonic_ns()) * 1e-9)):
                        break
                k = int(ev_idx[e])
                if ev_kind[e] == 1:
                    if self._tunnel_port is not None:
                        self.tunnel_sent += int(self._tunnel_port.write(vr.tunnel_line(k)))
                    continue
                up = bool(vr.port_up[k])
                if not up and not vanished and self._vanishers:
                    for v, _ in self._vanishers:
                        v()
                    vanished = True
                elif up and vanished:
                    for _, r in self._vanishers:
                        r()
                    vanished = False
                if vr.sent[k] and up:
                    assert self._send_sample is not None
                    n = self._send_sample(k)
                    self.frames_sent += n
                    self.samples_sent += int(n > 0)
            if vanished:
                for _, r in self._vanishers:
                    r()
            end = time.monotonic() + 2.0  # drain what the ptys have not taken yet
            while self._flush_ports() and time.monotonic() < end and not self._stop.is_set():
                time.sleep(0.005)
        except BaseException as exc:  # reported to the caller through wait()
            self.error = exc
        finally:
            self.done.set()

    def _flush_ports(self) -> int:
        """Flush every pty; the bytes still pending."""
        ports = [getattr(self, "port", None), self._tunnel_port]
        if self.transport == "slcan":
            ports.append(self.emulator.port)
        return sum(p.flush() for p in ports if p is not None)

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for the schedule to finish; re-raises an error of the sender thread."""
        self._thread.join(timeout_s)
        if self.error is not None:
            raise self.error
        return self.done.is_set()

    def stop(self) -> None:
        """Stop sending and close the transports (idempotent)."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(5.0)
        while self._closers:
            closer = self._closers.pop()
            with contextlib.suppress(Exception):
                closer()

    def __enter__(self) -> RigRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# --------------------------------------------------------------------------------------------
# command line (two-process runs)
# --------------------------------------------------------------------------------------------
def _load_rig(path: str) -> Rig:
    from cdpr.analysis.rig import rig_from_mapping

    return rig_from_mapping(load_toml(path), source=str(Path(path)))


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m cdpr.daq.virtual_rig``: run a schedule on a pty transport (see module doc)."""
    ap = argparse.ArgumentParser(
        prog="python -m cdpr.daq.virtual_rig", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--rig", required=True)
    ap.add_argument("--schedule", required=True)
    ap.add_argument("--transport", choices=TRANSPORTS, default="slcan")
    ap.add_argument("--pty-link", help="path of the symlink to the emulated port (slcan, serial)")
    ap.add_argument("--channel", default="vrig", help="virtual bus channel (transport virtual)")
    ap.add_argument("--tunnel-link", help="also send $TUN lines on a pty published here")
    ap.add_argument("--truth", help="write the truth here (.npz or .csv) after the run")
    ap.add_argument("--wait-reader", type=float, default=10.0, help="seconds to wait for a reader")
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--seed", type=int)
    ap.add_argument(
        "--linger", type=float, default=0.5, help="seconds to keep the ports open after the run"
    )
    a = ap.parse_args(argv)
    if a.transport != "virtual" and not a.pty_link:
        ap.error(f"--transport {a.transport} needs --pty-link PATH")
    import signal

    stop = threading.Event()

    def _terminate(signum: int, frame: Any) -> None:
        stop.set()  # stop early, but still close the ports and write the truth

    signal.signal(signal.SIGTERM, _terminate)
    signal.signal(signal.SIGINT, _terminate)
    from cdpr.analysis.errors import CdprError

    try:
        rig = _load_rig(a.rig)
        sch = load_schedule(a.schedule, rig)
        vr = VirtualRig(rig, sch, seed=a.seed)
        run = vr.start(
            a.transport,
            channel=a.channel,
            link=a.pty_link,
            tunnel_link=a.tunnel_link,
            wait_reader_s=a.wait_reader,
            speed=a.speed,
        )
    except CdprError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"READY {a.pty_link or a.channel}", flush=True)
    try:
        while not stop.is_set() and not run.started.wait(0.05):
            pass
        if run.started.is_set():  # the schedule's host start time, for a camera in the parent
            print(f"STARTED {vr.t0_ns}", flush=True)
        while not stop.is_set() and not run.done.wait(0.05):
            pass
        if not stop.is_set():
            stop.wait(max(0.0, a.linger))  # let the reader drain the pty before it closes
    finally:
        run.stop()
        if a.truth:
            vr.write_truth(a.truth)
    if run.error is not None:
        print(f"error: {run.error}", file=sys.stderr)
        return 1
    print(
        f"DONE samples={run.samples_sent} frames={run.frames_sent} tunnel={run.tunnel_sent}",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
