"""Terminal live view of a recording (rich): the test point, steadiness, the wrench estimate,
alarms, tensions by cable with their limits, stream rates and source counters.

:class:`LiveView` polls :meth:`Recorder.status` ``refresh_hz`` times a second (default 4 Hz) from its
own thread and redraws; it is used only when stdout is a terminal and ``--quiet`` is not given (the
CLI decides).  Slack and saturation come from the status bits of the latest reading and, when cable
limits are given, from tensions (``T_<cable>_N`` fields) outside ``[t_min_N, t_max_N]``.

- **Test point**: with a list of test points (a test matrix's ``.points``: mappings or objects with
  ``point``, ``kind``, ``target_aoa_deg``, ``target_sideslip_deg``, ``target_airspeed_mps``,
  ``repeat_of``), the operator presses SPACE (or Enter) to start the current point and again to end
  it (then the next one is current); ``n`` / ``p`` move to the next / previous point without
  recording.  Each start and end is an event on ``/events`` (the topic ``cdpr analyze`` reads;
  ``/event`` when the recorder does not declare ``events``) with ``name = "test_point"``,
  ``phase`` ``"start"``/``"end"`` and the point's fields (:class:`TestPointStepper`).
- **Steady**: the largest standard deviation over cables of the last ``steady_window_s`` of
  tensions below ``steady_sd_N``.
- **Wrench**: ``W = -A T - G`` (absolute method, N and N m at P in {O} axes) from the mean tensions
  of that window, at the latest camera pose if there is one, else at the rig's reference pose.
- **On-line**: with the on-line reduction (``online``: a callable giving its line, see
  :mod:`cdpr.daq.live_server`), the open point's wrench and coefficients with σ from the reduction
  core, at least once a second; ``final`` once the point has ended.
- **Alarms**: sources that stalled or never delivered, and the faults seen so far.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from cdpr.analysis.conventions import (
    CHANNEL_STATUS_FAULT,
    CHANNEL_STATUS_SATURATED,
    CHANNEL_STATUS_SLACK,
)

from .recorder import Recorder, RecorderStatus
from .source import STATUS_GAP, STATUS_SATURATED, STATUS_SENSOR_FAULT, STATUS_SLACK
from .vrig_events import MOTION_EVENT_FIELDS

#: fields of a test point copied into its ``test_point`` events
POINT_FIELDS = (
    "point",
    "kind",
    "target_aoa_deg",
    "target_sideslip_deg",
    "target_airspeed_mps",
    "repeat_of",
)


def _field(point: Any, key: str) -> Any:
    v = point.get(key) if isinstance(point, dict) else getattr(point, key, None)
    if isinstance(v, np.generic):
        v = v.item()
    return "" if v is None and key in ("kind", "repeat_of") else v


TEST_POINT_STREAM = "events"
"""The stream (topic ``/events``) of the test-point events: the one ``cdpr analyze`` reads."""


def test_point_streams() -> dict[str, Any]:
    """The ``extra_streams`` a :class:`~cdpr.daq.recorder.Recorder` declares so the live view's
    test points go on ``/events`` (``cdpr record --test-matrix``)."""
    from .source import StreamDescription
    from .vrig_events import EVENT_FIELDS

    return {
        TEST_POINT_STREAM: StreamDescription(
            dict(EVENT_FIELDS), 0.0, "test points marked in the live view"
        )
    }


def test_point_writer(recorder: Recorder) -> Any:
    """The ``event`` callback of a :class:`TestPointStepper` that records on ``/events`` when
    the recorder declares that stream (``cdpr record --test-matrix`` does), else on ``/event``."""
    if recorder.declares(TEST_POINT_STREAM):
        return lambda message, **kw: recorder.stream_event(TEST_POINT_STREAM, message, **kw)
    return recorder.event


test_point_streams.__test__ = False  # type: ignore[attr-defined]
test_point_writer.__test__ = False  # type: ignore[attr-defined]


class TestPointStepper:
    """The operator's place in a list of test points; :meth:`toggle` starts or ends the current
    point and records it as a ``test_point`` event (see the module docstring)."""

    __test__ = False  # not a pytest class

    def __init__(self, points: Sequence[Any], event: Any) -> None:
        self.points = list(points)
        self.event = event
        self.index = 0
        self.active_since: float | None = None
        self.done = 0
        self._lock = threading.Lock()

    @property
    def current(self) -> Any:
        return self.points[self.index] if self.index < len(self.points) else None

    def _emit(self, phase: str) -> None:
        p = self.current
        fields = {k: _field(p, k) for k in POINT_FIELDS}
        for k in MOTION_EVENT_FIELDS:  # an oscillation point's motion and inertia tare
            v = _field(p, k)
            if v is not None:
                fields[k] = v
        self.event(
            f"test point {fields['point']} {phase}",
            level="info",
            name="test_point",
            phase=phase,
            **fields,
        )

    def toggle(self) -> None:
        with self._lock:
            if self.current is None:
                return
            if self.active_since is None:
                self._emit("start")
                self.active_since = time.monotonic()
            else:
                self._emit("end")
                self.active_since = None
                self.done += 1
                self.index += 1

    def move(self, step: int) -> None:
        """Next (+1) or previous (-1) point, when none is running."""
        with self._lock:
            if self.active_since is None:
                self.index = min(max(self.index + step, 0), len(self.points))

    def finish(self) -> None:
        """End a point still running when the recording stops."""
        if self.active_since is not None:
            self.toggle()

    def line(self) -> str:
        p = self.current
        if p is None:
            return f"all {len(self.points)} test points done"
        label = _field(p, "point")
        targets = ", ".join(
            f"{name} {v:g}{unit}"
            for name, key, unit in (
                ("aoa", "target_aoa_deg", "°"),
                ("sideslip", "target_sideslip_deg", "°"),
                ("airspeed", "target_airspeed_mps", " m/s"),
            )
            if isinstance((v := _field(p, key)), int | float)
        )
        rep = f", repeat of {_field(p, 'repeat_of')}" if _field(p, "repeat_of") else ""
        where = f"{self.index + 1}/{len(self.points)}"
        if self.active_since is not None:
            run = time.monotonic() - self.active_since
            return f"{where} {label} RUNNING {run:5.1f} s ({targets}{rep})  [SPACE: end point]"
        return f"{where} {label} next ({targets}{rep})  [SPACE: start, n/p: next/previous]"


class _Keys:
    """Single key presses from the terminal (cbreak mode) handed to ``on_key`` from a thread."""

    def __init__(self, on_key: Any) -> None:
        self.on_key = on_key
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._saved: Any = None

    def __enter__(self) -> _Keys:
        import sys
        import termios
        import tty

        if not sys.stdin.isatty():
            return self
        fd = sys.stdin.fileno()
        self._saved = termios.tcgetattr(fd)
        tty.setcbreak(fd)
        self._thread = threading.Thread(target=self._loop, args=(fd,), name="keys", daemon=True)
        self._thread.start()
        return self

    def _loop(self, fd: int) -> None:
        import os
        import select

        while not self._stop.is_set():
            if select.select([fd], [], [], 0.1)[0]:
                data = os.read(fd, 32)
                if not data:
                    return
                for ch in data.decode(errors="replace"):
                    self.on_key(ch)

    def __exit__(self, *exc: object) -> None:
        import sys
        import termios

        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        if self._saved is not None:
            termios.tcsetattr(sys.stdin.fileno(), termios.TCSADRAIN, self._saved)


def status_flags(status: int) -> list[str]:
    """Names of the bits set in a reading's status."""
    names = [
        (STATUS_SATURATED, "saturated"),
        (STATUS_SLACK, "slack"),
        (STATUS_SENSOR_FAULT, "fault"),
        (STATUS_GAP, "gap"),
    ]
    return [n for bit, n in names if status & bit]


def tension_warnings(
    values: dict[str, Any], t_min_N: Sequence[float] | None, t_max_N: Sequence[float] | None
) -> list[str]:
    """``"<cable> slack"`` / ``"<cable> saturated"`` for tensions outside the cable limits, and
    per-cable channel status bits (``status_<cable>``,
    :data:`cdpr.analysis.conventions.CHANNEL_TO_STATUS`)."""
    out: list[str] = []
    cables = [k[2:-2] for k in values if k.startswith("T_") and k.endswith("_N")]
    for i, c in enumerate(cables):
        v = values.get(f"T_{c}_N")
        st = values.get(f"status_{c}", 0) or 0
        if isinstance(v, float) and not math.isfinite(v):
            out.append(f"{c} missing")
            continue
        slack = bool(st & CHANNEL_STATUS_SLACK) or (
            t_min_N is not None and i < len(t_min_N) and v < t_min_N[i]
        )
        sat = bool(st & CHANNEL_STATUS_SATURATED) or (
            t_max_N is not None and i < len(t_max_N) and v > t_max_N[i]
        )
        if slack:
            out.append(f"{c} slack")
        if sat:
            out.append(f"{c} saturated")
        if st & CHANNEL_STATUS_FAULT:
            out.append(f"{c} fault")
    return out


class LiveView:
    """A rich ``Live`` table refreshed from a :class:`Recorder` (context manager)."""

    def __init__(
        self,
        recorder: Recorder,
        *,
        refresh_hz: float = 4.0,
        t_min_N: Sequence[float] | None = None,
        t_max_N: Sequence[float] | None = None,
        title: str = "",
        console: Any = None,
        rig: Any = None,
        test_points: Sequence[Any] | None = None,
        keys: bool = True,
        steady_window_s: float = 1.0,
        steady_sd_N: float = 0.5,
        online: Any = None,
    ) -> None:
        if refresh_hz < 2.0:
            raise ValueError(f"refresh_hz must be >= 2, got {refresh_hz}")
        self.recorder = recorder
        self.refresh_hz = refresh_hz
        self.t_min_N = t_min_N
        self.t_max_N = t_max_N
        self.title = title or str(recorder.path)
        self._console = console
        self._prev: tuple[float, dict[str, int]] | None = None
        self._rates: dict[str, float] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._live: Any = None
        self.frames = 0
        self.rig = rig
        self.steady_window_s = float(steady_window_s)
        self.steady_sd_N = float(steady_sd_N)
        self.stepper = (
            TestPointStepper(test_points, test_point_writer(recorder))
            if test_points is not None
            else None
        )
        self._keys = _Keys(self._on_key) if keys and self.stepper is not None else None
        #: () -> the on-line reduction's line (cdpr.daq.live_server.LiveServer.online_line)
        self.online = online

    def _on_key(self, ch: str) -> None:
        assert self.stepper is not None
        if ch in (" ", "\n", "\r"):
            self.stepper.toggle()
        elif ch == "n":
            self.stepper.move(1)
        elif ch == "p":
            self.stepper.move(-1)

    def _state(self) -> tuple[str, str]:
        """(steadiness, wrench) lines from the latest tensions."""
        cables, t_ns, T = self.recorder.recent_tensions()
        if T.shape[0] < 2:
            return "steady   (no tensions yet)", ""
        keep = t_ns >= t_ns[-1] - int(self.steady_window_s * 1e9)
        win = T[keep]
        ok = np.all(np.isfinite(win), axis=1)
        if ok.sum() < 2:
            return "steady   (no complete samples)", ""
        sd = float(np.max(np.std(win[ok], axis=0)))
        steady = sd < self.steady_sd_N
        line = (
            f"{'STEADY  ' if steady else 'UNSTEADY'} max σ {sd:6.3f} N over "
            f"{self.steady_window_s:g} s (limit {self.steady_sd_N:g} N)"
        )
        return line, self._wrench(cables, win[ok].mean(axis=0))

    def _wrench(self, cables: list[str], T_N: np.ndarray) -> str:
        if self.rig is None or list(self.rig.cable_names) != cables:
            return ""
        from cdpr.analysis.dynamics import gravity_wrench
        from cdpr.analysis.kinematics import structure_matrix
        from cdpr.analysis.rotations import rotation_from_euler, rotation_from_quaternion
        from cdpr.analysis.wrench import wrench_absolute

        rig = self.rig
        pose = self.recorder.status().latest.get("pose")
        where = "reference pose"
        p, R = rig.reference_position_O_m, rotation_from_euler(rig.reference_euler_rad)
        if pose is not None and pose.status == 0:
            p = np.asarray(pose.values["position_O_m"], np.float64)
            R = rotation_from_quaternion(np.asarray(pose.values["quaternion_wxyz"], np.float64))
            where = "camera pose"
        A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, p, R)
        G = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
        w = wrench_absolute(A, T_N, G)
        names = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
        f = " ".join(f"{n} {v:7.2f}" for n, v in zip(names[:3], w[:3], strict=True))
        m = " ".join(f"{n} {v:7.3f}" for n, v in zip(names[3:], w[3:], strict=True))
        return f"wrench   {f} N  {m} N·m  (absolute, at the {where})"

    def _cables(self, st: RecorderStatus) -> Any:
        from rich.table import Table
        from rich.text import Text

        r = next((v for k, v in st.latest.items() if k.endswith("tensions")), None)
        tab = Table(title="tensions", expand=False)
        for col in ("cable", "T N", "min N", "max N", "state"):
            tab.add_column(col)
        if r is None:
            return tab
        values = dict(r.values)
        cables = [k[2:-2] for k in values if k.startswith("T_") and k.endswith("_N")]
        for i, c in enumerate(cables):
            v = values[f"T_{c}_N"]
            lo = self.t_min_N[i] if self.t_min_N is not None and i < len(self.t_min_N) else None
            hi = self.t_max_N[i] if self.t_max_N is not None and i < len(self.t_max_N) else None
            warn = [
                w.split(" ", 1)[1]
                for w in tension_warnings({f"T_{c}_N": v, f"status_{c}": values.get(f"status_{c}")},
                                          None if lo is None else [lo],
                                          None if hi is None else [hi])
            ]  # fmt: skip
            tab.add_row(
                c,
                f"{v:8.2f}" if isinstance(v, float) else str(v),
                "" if lo is None else f"{lo:g}",
                "" if hi is None else f"{hi:g}",
                Text(", ".join(warn), style="bold red") if warn else Text("ok", style="green"),
            )
        return tab

    def render(self, st: RecorderStatus, update_rates: bool = True) -> Any:
        """The table for one status snapshot (rates over the time since the previous one)."""
        from rich.console import Group
        from rich.table import Table
        from rich.text import Text

        now = time.monotonic()
        if self._prev is not None and update_rates:
            dt = now - self._prev[0]
            if dt > 0:
                self._rates = {k: (v - self._prev[1].get(k, 0)) / dt for k, v in st.counts.items()}
        self._prev = (now, dict(st.counts))

        streams = Table(title=f"{self.title}  {st.elapsed_s:7.1f} s", expand=False)
        for col in ("stream", "messages", "rate /s", "latest", "warnings"):
            streams.add_column(col)
        for name, n in sorted(st.counts.items()):
            r = st.latest.get(name)
            latest, warn = "", []
            if r is not None:
                warn = status_flags(r.status)
                if name.endswith("tensions"):
                    ts = [
                        f"{v:6.1f}"
                        for k, v in r.values.items()
                        if k.startswith("T_") and k.endswith("_N") and isinstance(v, float)
                    ]
                    latest = " ".join(ts) + " N"
                    warn = sorted(
                        set(warn)
                        | set(tension_warnings(dict(r.values), self.t_min_N, self.t_max_N))
                    )
                elif name == "event":
                    latest = str(r.values.get("message", ""))[:60]
                else:
                    nums = [
                        f"{k}={v:.4g}"
                        for k, v in r.values.items()
                        if isinstance(v, float | int) and not isinstance(v, bool)
                    ][:3]
                    latest = " ".join(nums)
            streams.add_row(
                name,
                str(n),
                f"{self._rates.get(name, 0.0):8.1f}",
                latest,
                Text(", ".join(warn), style="bold red") if warn else "",
            )
        srcs = Table(title="sources", expand=False)
        for col in ("source", "read", "dropped", "queued", "lost", "bad", "errors", "last error"):
            srcs.add_column(col)
        for c in st.sources.values():
            srcs.add_row(
                c.name,
                str(c.read),
                Text(str(c.dropped), style="bold red" if c.dropped else ""),
                str(c.queued),
                str(c.lost),
                str(c.bad),
                str(c.errors),
                c.last_error[:50],
            )
        self.frames += 1
        head: list[Any] = [Text(f"{self.title}  {st.elapsed_s:7.1f} s", style="bold")]
        if self.stepper is not None:
            head.append(Text("test point  " + self.stepper.line(), style="bold cyan"))
        steady, wrench = self._state()
        head.append(Text(steady, style="green" if steady.startswith("STEADY ") else "yellow"))
        if wrench:
            head.append(Text(wrench))
        line = self.online() if self.online is not None else None
        if line:
            head.append(Text(line, style="bold magenta"))
        alarms = list(st.alarms)
        alarms += [f for f in st.faults if not any(f.startswith(a.split(":")[0]) for a in alarms)]
        if st.failure:
            alarms.insert(0, st.failure)
        if alarms:
            head += [Text("ALARM  " + a, style="bold white on red") for a in alarms[:6]]
        else:
            head.append(Text("no alarms", style="green"))
        return Group(*head, self._cables(st), streams, srcs)

    def _loop(self) -> None:
        period = 1.0 / self.refresh_hz
        while not self._stop.wait(period):
            self._live.update(self.render(self.recorder.status()))

    def __enter__(self) -> LiveView:
        from rich.live import Live

        self._live = Live(
            self.render(self.recorder.status()),
            console=self._console,
            refresh_per_second=self.refresh_hz,
            transient=False,
        )
        self._live.__enter__()
        if self._keys is not None:
            self._keys.__enter__()
        self._thread = threading.Thread(target=self._loop, name="live-view", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._keys is not None:
            self._keys.__exit__()
        if self.stepper is not None:
            self.stepper.finish()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        try:
            self._live.update(self.render(self.recorder.status(), update_rates=False))
        finally:
            self._live.__exit__(None, None, None)
