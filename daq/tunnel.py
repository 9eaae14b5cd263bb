"""Tunnel conditions: airspeed, static pressure and temperature, from a serial link or by hand.

Stream ``tunnel``: ``airspeed_mps``, ``static_pressure_Pa``, ``temperature_K``, ``density_kgpm3``
(ideal gas, ``p / (287.05 T)``; moist air when the humidity is known), optional
``relative_humidity`` (fraction 0..1: only in the messages of a link that sends it), ``seq``, and
``label`` (the test point, manual source only).

- :class:`SerialTunnelSource` (``serial_tunnel``): ``$TUN`` lines (:mod:`cdpr.daq.serial_protocol`)
  on a serial port, with the bad-line and reopen behaviour of every line driver.  With
  ``test_points = true`` it also reads the controller's ``$TPT`` lines on the same link: each
  becomes a reading on the ``events`` stream with the fields every test-point event has
  (``name = "test_point"``, ``point``, ``phase``, ``kind``, ``target_aoa_deg``,
  ``target_sideslip_deg``, ``target_airspeed_mps``, ``repeat_of``, ``message``; a line without
  targets leaves ``kind`` and the targets out), stamped with the line's arrival time (lines that
  arrive in one read block: 1 ns apart, in their order).  An ``end``
  with no matching open point, a ``start`` while another point is open, and a gap in the ``$TPT``
  counter are kept as they came and each adds a ``test_point_warning`` event (level warning,
  ``point``, ``phase``, ``problem``) and a logged warning; ``stats.extra["test_point_warnings"]``
  counts them.  Without ``test_points`` a ``$TPT`` line is a bad line (kept in ``serial_bad``).
- :class:`ManualTunnelSource` (``manual_tunnel``): values entered per test point (config or command
  line) when the tunnel has no data link; emitted at open, then every ``1 / rate_hz`` s, and at once
  after :meth:`ManualTunnelSource.set_point`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

from cdpr.analysis.errors import CdprError
from cdpr.analysis.flow import air_density as flow_air_density

from .schema import plain
from .serial_protocol import is_test_point_line, parse_test_point_line, parse_tunnel_line
from .serial_source import SERIAL_BAD_DESCRIPTION, SerialLineSource, check_serial_budget
from .source import FieldDescription, Reading, Source, StreamDescription

log = logging.getLogger(__name__)

_TUNNEL_FIELDS = {
    "airspeed_mps": FieldDescription("m/s"),
    "static_pressure_Pa": FieldDescription("Pa"),
    "temperature_K": FieldDescription("K"),
    "density_kgpm3": FieldDescription("kg/m^3"),
    "seq": FieldDescription("", "int64"),
}
_SERIAL_FIELDS = {**_TUNNEL_FIELDS, "relative_humidity": FieldDescription("1 (fraction 0..1)")}
TEST_POINT_WARNING = "test_point_warning"
"""``name`` of the warning events of a ``$TPT`` sequence that does not pair up."""


def air_density(
    static_pressure_Pa: float, temperature_K: float, relative_humidity: float | None = None
) -> float:
    """The density of the air a tunnel reports, kg/m^3 (:func:`cdpr.analysis.flow.air_density`:
    moist air with a humidity, else dry); NaN where p or T is not physical (the reading keeps it
    rather than a made-up value)."""
    try:
        rh = 0.0 if relative_humidity is None else relative_humidity
        return float(flow_air_density(static_pressure_Pa, temperature_K, rh))
    except CdprError:
        return float("nan")


class SerialTunnelSource(SerialLineSource):
    """Tunnel conditions as ``$TUN`` lines on a serial port (settings: port, baudrate, rate_hz,
    test_points: also read the controller's ``$TPT`` test-point lines, default false)."""

    kind = "serial_tunnel"

    def __init__(
        self,
        name: str,
        port: str,
        baudrate: int = 115200,
        rate_hz: float = 10.0,
        reopen_backoff_s: Sequence[float] = (0.05, 2.0),
        test_points: bool = False,
        origin: str = "<config>",
    ) -> None:
        super().__init__(name, port, baudrate, reopen_backoff_s, origin)
        self.rate_hz = float(rate_hz)
        self.test_points = bool(test_points)
        check_serial_budget(origin, self.prefix, self.baudrate, self.rate_hz, 64)
        self._open_point: str | None = None
        self._last_tpt_seq: int | None = None
        self._last_tpt_t_ns: int | None = None

    def settings(self) -> dict[str, Any]:
        return {
            "port": self.port,
            "baudrate": self.baudrate,
            "rate_hz": self.rate_hz,
            "test_points": self.test_points,
        }

    def describe(self) -> dict[str, StreamDescription]:
        out = {
            "tunnel": StreamDescription(dict(_SERIAL_FIELDS), self.rate_hz, "tunnel conditions"),
            "serial_bad": SERIAL_BAD_DESCRIPTION,
        }
        if self.test_points:
            from .vrig_events import EVENT_FIELDS

            f = dict(EVENT_FIELDS)
            f["problem"] = FieldDescription("", "str")
            out["events"] = StreamDescription(
                f, 0.0, "test points announced by the tunnel controller ($TPT lines)"
            )
        return out

    def _warn(self, out: list[Reading], t_ns: int, point: str, phase: str, problem: str) -> None:
        self.stats.extra["test_point_warnings"] = self.stats.extra.get("test_point_warnings", 0) + 1
        log.warning("%s: test point %s %s: %s", self.name, point, phase, problem)
        out.append(
            Reading(
                "events",
                t_ns,
                {
                    "message": f"test point {point} {phase}: {problem}",
                    "level": "warning",
                    "name": TEST_POINT_WARNING,
                    "point": point,
                    "phase": phase,
                    "problem": problem,
                },
            )
        )

    def _parse_test_point(self, line: bytes, t_ns: int) -> list[Reading]:
        from .serial_protocol import LineError

        if not self.test_points:
            raise LineError(
                f"a $TPT test-point line, but {self.prefix}.test_points is false (not read)"
            )
        p = parse_test_point_line(line)
        # lines of one read block share its arrival time: keep their order in time (1 ns apart),
        # so a start that interrupts an open point never carries the open point's own time
        if self._last_tpt_t_ns is not None and t_ns <= self._last_tpt_t_ns:
            t_ns = self._last_tpt_t_ns + 1
        self._last_tpt_t_ns = t_ns
        out: list[Reading] = []
        values: dict[str, Any] = {
            "message": f"test point {p.label} {p.phase}",
            "name": "test_point",
            "point": p.label,
            "phase": p.phase,
        }
        if p.kind is not None:
            values.update(
                kind=p.kind,
                target_aoa_deg=p.target_aoa_deg,
                target_sideslip_deg=p.target_sideslip_deg,
                target_airspeed_mps=p.target_airspeed_mps,
            )
        values["repeat_of"] = ""
        out.append(Reading("events", t_ns, values))
        if self._last_tpt_seq is not None:
            step = (p.seq - self._last_tpt_seq) % self.seq_modulus
            if 1 < step < self.seq_modulus // 2:
                self.stats.lost += step - 1
                self._warn(
                    out, t_ns, p.label, p.phase,
                    f"{step - 1} test-point line(s) lost before this one (seq "
                    f"{self._last_tpt_seq} -> {p.seq}): a start or end may be missing",
                )  # fmt: skip
        self._last_tpt_seq = p.seq
        if p.phase == "start":
            if self._open_point is not None:
                self._warn(
                    out, t_ns, p.label, p.phase,
                    f"starts while point {self._open_point} is open (no end for it): kept, the "
                    "analysis ends the open point here and flags it",
                )  # fmt: skip
            self._open_point = p.label
        else:
            if self._open_point != p.label:
                was = "no point" if self._open_point is None else f"point {self._open_point}"
                self._warn(
                    out, t_ns, p.label, p.phase,
                    f"ends while {was} is open (no matching start): kept, it marks no data",
                )  # fmt: skip
            else:
                self._open_point = None
        return out

    def _parse(self, line: bytes, t_ns: int) -> Reading | list[Reading]:
        if is_test_point_line(line):
            return self._parse_test_point(line, t_ns)
        p = parse_tunnel_line(line)
        self._check_seq(p.seq)
        values: dict[str, Any] = {
            "airspeed_mps": p.airspeed_mps,
            "static_pressure_Pa": p.static_pressure_Pa,
            "temperature_K": p.temperature_K,
            "density_kgpm3": air_density(
                p.static_pressure_Pa, p.temperature_K, p.relative_humidity
            ),
            "seq": p.seq,
        }
        if p.relative_humidity is not None:  # the optional fifth value of the line
            values["relative_humidity"] = p.relative_humidity
        return Reading("tunnel", t_ns, values)


def _check_point(
    origin: str, prefix: str, airspeed_mps: Any, static_pressure_Pa: Any, temperature_K: Any
) -> tuple[float, float, float]:
    """A test point checked by the schema (:class:`cdpr.daq.source_schema.TunnelPoint`)."""
    from .schema import parse
    from .source_schema import TunnelPoint

    p = parse(
        TunnelPoint,
        plain(
            {
                "airspeed_mps": airspeed_mps,
                "static_pressure_Pa": static_pressure_Pa,
                "temperature_K": temperature_K,
            }
        ),
        origin,
        prefix,
    )
    return p.airspeed_mps, p.static_pressure_Pa, p.temperature_K


class ManualTunnelSource(Source):
    """Tunnel conditions typed in per test point.

    Settings: airspeed_mps (>= 0), static_pressure_Pa (> 0, default 101325), temperature_K (> 0,
    default 293.15), rate_hz (repeat rate, default 1 Hz), label (test-point name).
    """

    kind = "manual_tunnel"
    accepts_origin = True

    def __init__(
        self,
        name: str,
        airspeed_mps: float,
        static_pressure_Pa: float = 101325.0,
        temperature_K: float = 293.15,
        rate_hz: float = 1.0,
        label: str = "",
        origin: str = "<config>",
    ) -> None:
        super().__init__(name)
        self.origin = origin
        self.prefix = f"sources.{name}"
        self.point = _check_point(
            origin, self.prefix, airspeed_mps, static_pressure_Pa, temperature_K
        )
        self.rate_hz = float(rate_hz)  # > 0: cdpr.daq.source_schema.ManualTunnelSettings
        self.label = str(label)
        self._seq = 0
        self._next = 0.0

    def set_point(
        self,
        airspeed_mps: float,
        static_pressure_Pa: float | None = None,
        temperature_K: float | None = None,
        label: str | None = None,
    ) -> None:
        """Enter a new test point (emitted at the next read)."""
        p = self.point
        self.point = _check_point(
            "<set_point>",
            self.prefix,
            airspeed_mps,
            p[1] if static_pressure_Pa is None else static_pressure_Pa,
            p[2] if temperature_K is None else temperature_K,
        )
        if label is not None:
            self.label = str(label)
        self._next = 0.0

    def settings(self) -> dict[str, Any]:
        v, p, t = self.point
        return {
            "airspeed_mps": v,
            "static_pressure_Pa": p,
            "temperature_K": t,
            "rate_hz": self.rate_hz,
            "label": self.label,
        }

    def describe(self) -> dict[str, StreamDescription]:
        f = dict(_TUNNEL_FIELDS)
        f["label"] = FieldDescription("", "str")
        return {"tunnel": StreamDescription(f, self.rate_hz, "tunnel conditions entered by hand")}

    def _open(self) -> None:
        self._next = 0.0

    def _close(self) -> None:
        pass

    def _read(self, timeout_s: float) -> list[Reading]:
        now = time.monotonic()
        if now < self._next:
            time.sleep(min(timeout_s, self._next - now))
            if time.monotonic() < self._next:
                return []
        self._next = time.monotonic() + 1.0 / self.rate_hz
        v, p, t = self.point
        r = Reading(
            "tunnel",
            time.time_ns(),
            {
                "airspeed_mps": v,
                "static_pressure_Pa": p,
                "temperature_K": t,
                "density_kgpm3": air_density(p, t),
                "seq": self._seq,
                "label": self.label,
            },
        )
        self._seq += 1
        return [r]
