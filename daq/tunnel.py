"""Tunnel conditions: airspeed, static pressure and temperature, from a serial link or by hand.

Stream ``tunnel``: ``airspeed_mps``, ``static_pressure_Pa``, ``temperature_K``, ``density_kgpm3``
(ideal gas, ``p / (287.05 T)``; moist air when the humidity is known), optional
``relative_humidity`` (fraction 0..1: only in the messages of a link that sends it), ``seq``, and
``label`` (the test point, manual source only).

- :class:`SerialTunnelSource` (``serial_tunnel``): ``$TUN`` lines (:mod:`cdpr.daq.serial_protocol`)
  on a serial port, with the bad-line and reopen behaviour of every line driver.
- :class:`ManualTunnelSource` (``manual_tunnel``): values entered per test point (config or command
  line) when the tunnel has no data link; emitted at open, then every ``1 / rate_hz`` s, and at once
  after :meth:`ManualTunnelSource.set_point`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from cdpr.analysis.errors import CdprError
from cdpr.analysis.flow import air_density as moist_air_density

from .aero_model import R_AIR_J_PER_KGK
from .schema import plain
from .serial_protocol import parse_tunnel_line
from .serial_source import SERIAL_BAD_DESCRIPTION, SerialLineSource, check_serial_budget
from .source import FieldDescription, Reading, Source, StreamDescription

_TUNNEL_FIELDS = {
    "airspeed_mps": FieldDescription("m/s"),
    "static_pressure_Pa": FieldDescription("Pa"),
    "temperature_K": FieldDescription("K"),
    "density_kgpm3": FieldDescription("kg/m^3"),
    "seq": FieldDescription("", "int64"),
}
_SERIAL_FIELDS = {**_TUNNEL_FIELDS, "relative_humidity": FieldDescription("1 (fraction 0..1)")}


def air_density(static_pressure_Pa: float, temperature_K: float) -> float:
    """Ideal-gas density, kg/m^3."""
    return static_pressure_Pa / (R_AIR_J_PER_KGK * temperature_K)


class SerialTunnelSource(SerialLineSource):
    """Tunnel conditions as ``$TUN`` lines on a serial port (settings: port, baudrate, rate_hz)."""

    kind = "serial_tunnel"

    def __init__(
        self,
        name: str,
        port: str,
        baudrate: int = 115200,
        rate_hz: float = 10.0,
        reopen_backoff_s: Sequence[float] = (0.05, 2.0),
        origin: str = "<config>",
    ) -> None:
        super().__init__(name, port, baudrate, reopen_backoff_s, origin)
        self.rate_hz = float(rate_hz)
        check_serial_budget(origin, self.prefix, self.baudrate, self.rate_hz, 64)

    def settings(self) -> dict[str, Any]:
        return {"port": self.port, "baudrate": self.baudrate, "rate_hz": self.rate_hz}

    def describe(self) -> dict[str, StreamDescription]:
        return {
            "tunnel": StreamDescription(dict(_SERIAL_FIELDS), self.rate_hz, "tunnel conditions"),
            "serial_bad": SERIAL_BAD_DESCRIPTION,
        }

    def _parse(self, line: bytes, t_ns: int) -> Reading:
        p = parse_tunnel_line(line)
        self._check_seq(p.seq)
        values: dict[str, Any] = {
            "airspeed_mps": p.airspeed_mps,
            "static_pressure_Pa": p.static_pressure_Pa,
            "temperature_K": p.temperature_K,
            "density_kgpm3": air_density(p.static_pressure_Pa, p.temperature_K),
            "seq": p.seq,
        }
        if p.relative_humidity is not None:  # the optional fifth value of the line
            values["relative_humidity"] = p.relative_humidity
            try:
                values["density_kgpm3"] = float(
                    moist_air_density(p.static_pressure_Pa, p.temperature_K, p.relative_humidity)
                )
            except CdprError:  # p or T not physical: the dry value (NaN-free) as before
                pass
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
