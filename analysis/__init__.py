"""Pure numerics of the cable-driven parallel robot force balance.

Arrays in, arrays out: no files, no hardware, no globals.  Conventions (SI units, integer
nanoseconds for time, wrench order ``[Fx, Fy, Fz, Mx, My, Mz]``, frames {O} tunnel and {P}
platform, Z-Y-X Euler angles) are defined in :mod:`cdpr.analysis.conventions`.
"""
