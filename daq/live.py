"""Terminal live view of a recording (rich): rates, latest tensions, slack/saturation, drops.

:class:`LiveView` polls :meth:`Recorder.status` ``refresh_hz`` times a second (default 4 Hz) from its
own thread and redraws one table; it is used only when stdout is a terminal and ``--quiet`` is not
given (the CLI decides).  Slack and saturation come from the status bits of the latest reading and,
when cable limits are given, from tensions (``T_<cable>_N`` fields) outside ``[t_min_N, t_max_N]``.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from typing import Any

from .recorder import Recorder, RecorderStatus
from .source import STATUS_GAP, STATUS_SATURATED, STATUS_SENSOR_FAULT, STATUS_SLACK


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
    per-cable DBC status bits (``status_<cable>``: 1 saturated, 2 slack, 4 fault)."""
    out: list[str] = []
    cables = [k[2:-2] for k in values if k.startswith("T_") and k.endswith("_N")]
    for i, c in enumerate(cables):
        v = values.get(f"T_{c}_N")
        st = values.get(f"status_{c}", 0) or 0
        if isinstance(v, float) and not math.isfinite(v):
            out.append(f"{c} missing")
            continue
        slack = bool(st & 2) or (t_min_N is not None and i < len(t_min_N) and v < t_min_N[i])
        sat = bool(st & 1) or (t_max_N is not None and i < len(t_max_N) and v > t_max_N[i])
        if slack:
            out.append(f"{c} slack")
        if sat:
            out.append(f"{c} saturated")
        if st & 4:
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
        return Group(streams, srcs)

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
        self._thread = threading.Thread(target=self._loop, name="live-view", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        try:
            self._live.update(self.render(self.recorder.status(), update_rates=False))
        finally:
            self._live.__exit__(None, None, None)
