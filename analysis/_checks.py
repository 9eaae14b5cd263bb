"""Input checks at the boundary: name what was expected and what came."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import InputError


def as_float_array(value: Any, name: str) -> NDArray[np.float64]:
    """Return ``value`` as a float64 array, or raise :class:`InputError` naming ``name``."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a numeric array, got {type(value).__name__}") from exc
    return arr


def check_trailing(
    value: Any, name: str, trailing: tuple[int, ...], allow_nan: bool = False
) -> NDArray[np.float64]:
    """Check that the array's last dimensions equal ``trailing`` and that it is finite (with
    ``allow_nan``: NaN marks a missing row, inf is still refused)."""
    arr = as_float_array(value, name)
    n = len(trailing)
    if arr.ndim < n or tuple(arr.shape[arr.ndim - n :]) != tuple(trailing):
        want = "(...," + ",".join(str(t) for t in trailing) + ")"
        raise InputError(f"{name}: expected shape {want}, got {arr.shape}")
    if allow_nan:
        if np.any(np.isinf(arr)):
            raise InputError(f"{name}: expected finite values or NaN, got inf")
    elif not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: expected finite values, got NaN or inf")
    return arr
