"""Flow conditions against published reference values (ISA tables, humid-air tables)."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr.analysis.errors import InputError
from cdpr.analysis.flow import (
    air_density,
    flow_conditions,
    saturation_vapour_pressure,
    sutherland_viscosity,
)


def test_isa_sea_level() -> None:
    # ISA sea level (ICAO Doc 7488): rho 1.2250 kg/m^3, mu 1.7894e-5 Pa s, a 340.294 m/s
    fc = flow_conditions([0.0, 34.0294], 101325.0, 288.15, chord_m=0.1, relative_humidity=0.0)
    assert fc.density_kgpm3 == pytest.approx(1.2250, abs=2e-4)
    assert fc.viscosity_Pas == pytest.approx(1.7894e-5, rel=2e-4)
    assert fc.speed_of_sound_mps == pytest.approx(340.294, abs=0.01)
    assert fc.mach[1] == pytest.approx(0.1, rel=1e-4)
    # q = 0.5 * 1.2250 * 34.0294^2 = 709.27 Pa; Re = 1.2250 * 34.0294 * 0.1 / 1.7894e-5 = 232 960
    assert fc.q_Pa[1] == pytest.approx(709.27, rel=5e-4)
    assert fc.reynolds[1] == pytest.approx(2.3296e5, rel=5e-4)
    assert fc.record.flags == ()


def test_humid_air_and_vapour_pressure() -> None:
    # saturation pressure of water at 20 degC: 2339 Pa (IAPWS); humid air at 20 degC, 100 % RH,
    # 101325 Pa: 1.194 kg/m^3 (dry: 1.204)
    assert saturation_vapour_pressure(293.15) == pytest.approx(2339.0, rel=1e-3)
    assert air_density(101325.0, 293.15, 1.0) == pytest.approx(1.1936, rel=1e-3)
    # dry air by hand: p / (R_d T) = 101325 / (287.05287 * 293.15) = 1.20410 kg/m^3
    assert air_density(101325.0, 293.15) == pytest.approx(
        101325.0 / (287.05287 * 293.15), rel=1e-12
    )
    # measured viscosity of air at 20 degC: 1.82e-5 Pa s (Lemmon & Jacobsen 2004); Sutherland's
    # law is within 1 % of it
    assert sutherland_viscosity(293.15) == pytest.approx(1.82e-5, rel=1e-2)


def test_missing_humidity_is_flagged_and_bad_input_raises() -> None:
    fc = flow_conditions(np.array([17.27, 25.51]), 101325.0, 293.15, chord_m=0.05)
    assert fc.record.flags == ("humidity_not_given",)
    with pytest.raises(InputError, match="relative_humidity"):
        air_density(101325.0, 293.15, 1.5)
    with pytest.raises(InputError, match="temperature_K"):
        flow_conditions(10.0, 101325.0, -3.0, chord_m=0.05)
