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
import io
import os
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdpr.analysis.dynamics import gravity_wrench
from cdpr.analysis.errors import ConfigError
from cdpr.analysis.flow import sutherland_viscosity
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.motion import Motion, motion_tensions, oscillation_offset
from cdpr.analysis.rig import Rig
from cdpr.analysis.rotations import quaternion_from_euler, rotation_from_euler
from cdpr.analysis.tension import distribute
from cdpr.analysis.test_section import SectionGeometry
from cdpr.analysis.windage import windage_of_rig

from .aero_model import DERIVATIVE_NAMES, AeroModel
from .files import atomic_output
from .loadcell import INT24_MAX, INT24_MIN, Calibration
from .schema import load_rig
from .vrig_events import oscillation_event_fields
from .vrig_schedule import (  # noqa: F401  (the schedule API, re-exported for its users)
    FAULT_KINDS,
    POINT_KINDS,
    Fault,
    Schedule,
    Segment,
    SensorModel,
    load_schedule,
    schedule_from_mapping,
)
from .vrig_transports import TRANSPORTS, RigRun

FloatArray = NDArray[np.float64]

CH_SATURATED, CH_SLACK, CH_FAULT = 1, 2, 4


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
        self.deflection = self._segment_deflections()
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
            aero.air_density(aero.static_pressure_Pa, aero.temperature_K, aero.relative_humidity),
            sutherland_viscosity(aero.temperature_K),
        ).wrench_N

    def _segment_deflections(self) -> FloatArray:
        """(n_segments, 6) the steady pose change of each held segment under its wind's load
        ``x = K^-1 (W_aero + D)`` ([position m, Euler angles rad]), K the cables' stiffness
        (elastic and geometric, gravity's term with it; :func:`cdpr.analysis.stiffness.
        stiffness_matrix`) at the commanded pose and its wind-off tensions: the winches hold the
        cable lengths, the cables stretch, the platform yields, as a real balance does.  Zero for
        wind-off and oscillation segments."""
        from cdpr.analysis.rotations import euler_rate_matrix
        from cdpr.analysis.stiffness import stiffness_matrix

        rig, segs = self.rig, self.schedule.segments
        out = np.zeros((len(segs), 6))
        held = [
            i
            for i, sg in enumerate(segs)
            if sg.wind_mps > 0 and getattr(sg, "oscillation", None) is None
        ]
        if not held:
            return out
        p = np.array([segs[i].position_O_m for i in held], dtype=np.float64)
        e = np.array([segs[i].euler_rad for i in held], dtype=np.float64)
        R = rotation_from_euler(e)
        V = np.array([segs[i].wind_mps for i in held], dtype=np.float64)
        on = np.array([segs[i].kind != "windage" for i in held])
        W, G, D = self.physics(p, R, V, on)
        A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, p, R)
        T0 = np.asarray(
            distribute(self.schedule.method, A, -G, rig.t_min_N, rig.t_max_N).tensions_N
        )
        # a load the cables cannot hold at the commanded pose is refused there, not deflected
        held_ok = np.asarray(
            distribute(self.schedule.method, A, -(G + W + D), rig.t_min_N, rig.t_max_N).feasible
        )
        K = stiffness_matrix(
            rig.anchors_O_m, rig.attach_P_m, p, R, T0, rig.cable_EA_N, rig.mass_kg, rig.com_P_m,
            rig.gravity_O_mps2,
        ).K  # fmt: skip
        x = np.linalg.solve(K, (W + D)[..., None])[..., 0]  # [dp; dtheta]
        x[:, 3:] = np.einsum("nij,nj->ni", np.linalg.inv(euler_rate_matrix(e)), x[:, 3:])
        out[held] = np.where(np.isfinite(x) & held_ok[:, None], x, 0.0)
        return out

    def _segment_starts(self) -> FloatArray:
        d = np.array([s.duration_s for s in self.schedule.segments])
        return np.concatenate([[0.0], np.cumsum(d)[:-1]])

    def _state_at(
        self, t_s: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int64]]:
        """(position (n,3), euler (n,3), wind (n,), segment index (n,)) at schedule times t_s,
        the oscillation of an oscillation segment included (:meth:`_motion_at`)."""
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
        # the steady deflection under the wind's load, ramped with the load (wind squared)
        X = getattr(self, "deflection", None)
        if X is not None and np.any(X != 0.0):
            X_prev = np.vstack([np.zeros(6), X[:-1]])
            with np.errstate(divide="ignore", invalid="ignore"):
                w_now = np.where(V[idx] > 0, (wind / V[idx]) ** 2, 0.0)
                w_prev = np.where(V_prev[idx] > 0, (wind / V_prev[idx]) ** 2, 0.0)
            # from the last segment's to this one's over the transition (continuous)
            x = (1.0 - frac)[:, None] * w_prev[:, None] * X_prev[idx]
            x = x + (frac * w_now)[:, None] * X[idx]
            pos = pos + x[:, :3]
            eul = eul + x[:, 3:]
        off, _, _ = self._motion_at(t_s, idx)
        return pos + off[:, :3], eul + off[:, 3:], wind, idx

    def _motion_at(
        self, t_s: FloatArray, idx: NDArray[np.int64]
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The oscillation's pose offset from the segment's mean pose, its rate and acceleration
        (each (n, 6)) at schedule times ``t_s`` in segments ``idx``; zero outside oscillation
        segments.  The motion starts when the segment's ramp ends (its ``start`` event)."""
        n = t_s.shape[0]
        off, rate, acc = np.zeros((n, 6)), np.zeros((n, 6)), np.zeros((n, 6))
        starts = self._segment_starts()
        for i, seg in enumerate(self.schedule.segments):  # segments, not samples
            osc = seg.oscillation
            if osc is None:
                continue
            sel = np.flatnonzero(idx == i)
            if sel.size == 0:
                continue
            x, xd, xdd = oscillation_offset(t_s[sel] - starts[i] - seg.transition_s, osc)
            j = osc.index
            off[sel, j], rate[sel, j], acc[sel, j] = x, xd, xdd
        return off, rate, acc

    def motion_start_s(self, segment: int) -> float:
        """Schedule time (s) at which segment ``segment``'s point starts (its ramp over)."""
        return float(self._segment_starts()[segment] + self.schedule.segments[segment].transition_s)

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

    def physics_moving(
        self, motion: Motion, airspeed_mps: FloatArray, model_on: NDArray[np.bool_]
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """:meth:`physics` of a moving platform: the aero wrench of the moving model (its
        dynamic derivatives, :meth:`~cdpr.daq.aero_model.AeroModel.wrench_moving_O`), gravity,
        and the cable windage at the instantaneous pose (the cables' own motion neglected)."""
        rig = self.rig
        q = motion.pose
        R = rotation_from_euler(q[:, 3:])
        W = self.aero.wrench_moving_O(airspeed_mps, q, motion.rate, motion.accel)
        W = W * model_on[:, None]
        G = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
        D = self._cable_drag_O(q[:, :3], R, airspeed_mps)
        return W, G, D

    def _refuse_infeasible(
        self,
        res: Any,
        rows: NDArray[np.intp],
        t_s: FloatArray,
        wind: FloatArray,
        seg: NDArray[np.int64],
        inv: NDArray[np.intp],
    ) -> None:
        """A ConfigError naming the segment of the first sample (``rows[k]``) whose tensions are
        not feasible; ``inv`` maps samples to the rows of ``res``."""
        bad = np.flatnonzero(~np.asarray(res.feasible))
        if not bad.size:
            return
        k = int(np.flatnonzero(inv == bad[0])[0])
        j = int(rows[k])
        s = int(seg[j])
        raise ConfigError(
            self.schedule.source,
            f"segments[{s}]",
            f"no feasible tensions with method {self.schedule.method!r} at t = {t_s[j]:.3f} s "
            f"(wind {wind[j]:.2f} m/s): residual {float(res.residual_N[bad[0]]):.3g}, "
            f"limit violation {float(res.max_violation_N[bad[0]]):.3g} N",
        )

    def _compute_truth(self, rng: np.random.Generator) -> None:
        sch, rig, sens = self.schedule, self.rig, self.schedule.sensor
        n = max(1, int(round(sch.duration_s * sch.rate_hz)))
        k = np.arange(n)
        self.t_rel_ns = np.round(k * 1e9 / sch.rate_hz).astype(np.int64)
        t_s = self.t_rel_ns.astype(np.float64) * 1e-9
        pos, eul, wind, seg = self._state_at(t_s)
        _, rate, acc = self._motion_at(t_s, seg)
        moving = np.any(rate != 0.0, axis=1) | np.any(acc != 0.0, axis=1)
        model_on = np.array([s.kind != "windage" for s in sch.segments], dtype=np.float64)[seg]
        T_true = np.empty((n, rig.n_cables))
        W_all, G_all, D_all = np.empty((n, 6)), np.empty((n, 6)), np.empty((n, 6))
        inertia = np.zeros((n, 6))
        # held still: tensions at the unique states only (a few per segment), then broadcast
        still = np.flatnonzero(~moving)
        if still.size:
            state = np.concatenate(
                [pos[still], eul[still], wind[still, None], model_on[still, None]], axis=1
            )
            uniq, inv = np.unique(np.round(state, 12), axis=0, return_inverse=True)
            inv = inv.reshape(-1)
            R_u = rotation_from_euler(uniq[:, 3:6])
            A_u = structure_matrix(rig.anchors_O_m, rig.attach_P_m, uniq[:, :3], R_u)
            W_u, G_u, D_u = self.physics(uniq[:, :3], R_u, uniq[:, 6], uniq[:, 7] > 0.5)
            res = distribute(sch.method, A_u, -(G_u + W_u + D_u), rig.t_min_N, rig.t_max_N)
            self._refuse_infeasible(res, still, t_s, wind, seg, inv)
            T_true[still] = np.asarray(res.tensions_N)[inv]
            W_all[still], G_all[still], D_all[still] = W_u[inv], G_u[inv], D_u[inv]
        # moving (an oscillation): the cables carry the motion, A T = D - G - W at every sample
        mv = np.flatnonzero(moving)
        if mv.size:
            motion = Motion(np.concatenate([pos[mv], eul[mv]], axis=1), rate[mv], acc[mv])
            W_m, _, D_m = self.physics_moving(motion, wind[mv], model_on[mv] > 0.5)
            mt = motion_tensions(rig, motion, W_m + D_m, sch.method)
            self._refuse_infeasible(mt.result, mv, t_s, wind, seg, np.arange(mv.size))
            T_true[mv] = mt.result.tensions_N
            W_all[mv], G_all[mv], D_all[mv] = W_m, mt.gravity_O, D_m
            inertia[mv] = mt.inertia_O
        self.position_O_m = pos
        self.euler_rad = eul
        self.pose_rate = rate
        self.pose_accel = acc
        self.wind_mps = wind
        self.segment_index = seg.astype(np.int64)
        self.wrench_aero_O = W_all
        self.wrench_gravity_O = G_all
        self.wrench_cable_drag_O = D_all
        self.wrench_inertia_O = inertia
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
        zero without a test section) at P in {O} (N, N m), ``pose_rate`` and ``pose_accel``
        (n, 6) the pose's derivatives (zero except on oscillation points), ``wrench_inertia_O``
        (n, 6) ``D = M qdd + C`` of the rig file's mass and inertia (the cables carry
        ``A T = D - G - W_aero - W_cable_drag``), ``camera_clock_offset_ns`` (a scalar: the
        camera's clock minus the load cells'), ``tensions_true_N`` (n, m) physics,
        ``tensions_sensor_N`` (n, m) after noise/drift/faults before quantisation, ``counts``
        (n, m), ``channel_status`` (n, m) bits 1 sat 2 slack 4 fault, ``sent`` (n,) False in
        dropouts, ``port_up`` (n,), ``fault_code`` (n, m), segment index, the calibration, and
        the tunnel arrays (``tunnel_*``)."""
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
            "pose_rate": self.pose_rate,
            "pose_accel": self.pose_accel,
            "wrench_inertia_O": self.wrench_inertia_O,
            "camera_clock_offset_ns": np.int64(self.schedule.camera_clock_offset_ns),
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
                osc = s.oscillation
                start = t + s.transition_s
                end = t + s.duration_s if osc is None else start + osc.window_s[1]
                extra = {} if osc is None else oscillation_event_fields(s)
                for phase, t_s in (("start", start), ("end", end)):
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
                            **extra,
                        }
                    )
            t += s.duration_s
        return out

    def aero_derivatives(self) -> tuple[list[str], FloatArray]:
        """The dynamic derivatives a noiseless reduction of each oscillation segment would find
        (:meth:`~cdpr.daq.aero_model.AeroModel.oscillation_derivatives` at the segment's motion,
        mean pose and wind): ``(names, values (n_segments, k))``, NaN rows for other segments
        and wind-off ones."""
        names = list(DERIVATIVE_NAMES)
        out = np.full((len(self.schedule.segments), len(names)), np.nan)
        for i, s in enumerate(self.schedule.segments):  # segments, not samples
            osc = s.oscillation
            if osc is not None and s.wind_mps > 0 and s.kind != "windage":
                mean = np.array([*s.position_O_m, *s.euler_rad])
                d = self.aero.oscillation_derivatives(osc, mean, s.wind_mps)
                out[i] = [d[k] for k in names]
        return names, out

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
        """Write the truth atomically: ``.npz`` (all arrays of :meth:`truth` plus ``cable_names``,
        ``segment_labels``, ``segment_kinds``, per segment its motion (``segment_motion_axis``,
        ``_amplitude`` (rad or m), ``_frequency_Hz``, ``_cycles``, ``_settling_cycles``,
        ``_start_rel_ns`` the motion's start, ``segment_inertia_tare``), the dynamic derivatives
        of :meth:`aero_derivatives` (``derivative_names``, ``segment_derivatives``) and the aero
        model's coefficients (``aero_model_names``, ``aero_model_values``: CL_alpha, Cmq, Cnr,
        ...)) or ``.csv`` (one row per sample: times, pose, wind, wrench, true and sensor
        tensions)."""
        p = Path(path)
        tr = self.truth()
        if p.suffix == ".npz":
            buf = io.BytesIO()
            segs = self.schedule.segments
            d_names, d_values = self.aero_derivatives()
            aero = self.aero.to_mapping()
            coef = [k for k, v in aero.items() if isinstance(v, float) and k[:1] in "CkK"]
            arrays: dict[str, Any] = {
                "cable_names": np.array(self.cable_names),
                "segment_labels": np.array([s.label for s in segs]),
                "segment_kinds": np.array([s.kind for s in segs]),
                "segment_motion_axis": np.array([s.motion_axis for s in segs]),
                "segment_motion_amplitude": np.array([s.motion_amplitude for s in segs]),
                "segment_motion_frequency_Hz": np.array([s.motion_frequency_Hz for s in segs]),
                "segment_motion_cycles": np.array([s.motion_cycles for s in segs], np.int64),
                "segment_motion_settling_cycles": np.array(
                    [s.motion_settling_cycles for s in segs], np.int64
                ),
                "segment_motion_start_rel_ns": np.array(
                    [round(self.motion_start_s(i) * 1e9) for i in range(len(segs))], np.int64
                ),
                "segment_inertia_tare": np.array([s.inertia_tare for s in segs]),
                "derivative_names": np.array(d_names),
                "segment_derivatives": d_values,
                "aero_model_names": np.array(coef),
                "aero_model_values": np.array([aero[k] for k in coef], np.float64),
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

    def camera_pose_at(self, t_cam_ns: Any) -> tuple[FloatArray, FloatArray]:
        """The true pose a camera whose clock runs ``schedule.camera_clock_offset_ns`` ahead of
        the load cells' sees in the frame it stamps ``t_cam_ns``: the pose at
        ``t_cam_ns - offset`` (host times; :meth:`true_pose_at`)."""
        t = np.asarray(t_cam_ns, dtype=np.int64) - np.int64(self.schedule.camera_clock_offset_ns)
        return self.true_pose_at(t)

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
        from .can_dbc import DEFAULT_DBC, load_dbc

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

    def test_point_link_events(self) -> tuple[np.ndarray, list[bytes]]:
        """The ``$TPT`` lines the tunnel controller sends when the schedule says
        ``test_points_on_link``: their schedule times (ns, int64) and the lines, one per
        :meth:`test_point_events` event (its own counter from 0); empty otherwise."""
        from .serial_protocol import format_test_point_line

        if not self.schedule.test_points_on_link:
            return np.zeros(0, np.int64), []
        evs = self.test_point_events()
        lines = [
            format_test_point_line(
                j, e["phase"], e["point"], e["kind"], e["target_aoa_deg"],
                e["target_sideslip_deg"], e["target_airspeed_mps"],
            )
            for j, e in enumerate(evs)
        ]  # fmt: skip
        return np.array([e["t_rel_ns"] for e in evs], np.int64), lines

    def tunnel_line(self, j: int) -> bytes:
        from .serial_protocol import format_tunnel_line

        return format_tunnel_line(
            j,
            float(self.tunnel_airspeed_mps[j]),
            float(self.tunnel_static_pressure_Pa[j]),
            float(self.tunnel_temperature_K[j]),
            self.aero.relative_humidity,  # None (the default): the four-value line, no humidity
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
                    "test_points": self.schedule.test_points_on_link,
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


# --------------------------------------------------------------------------------------------
# command line (two-process runs)
# --------------------------------------------------------------------------------------------
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
        rig = load_rig(a.rig)
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
