"""Parameter checks shared by the public constructors: each raises ConfigError naming the parameter."""

from __future__ import annotations

import math
import numbers

import numpy as np

from .errors import ConfigError


def real(value, name: str, *, unit: str = "", lo=None, hi=None, lo_open=False, hi_open=False) -> float:
    """A finite real number (Python or NumPy; not bool, not str) within optional bounds, as float."""
    what = f" ({unit})" if unit else ""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ConfigError(f"{name} must be a number{what}, got {value!r}")
    v = float(value)
    ok = math.isfinite(v)
    if ok and lo is not None:
        ok = v > lo if lo_open else v >= lo
    if ok and hi is not None:
        ok = v < hi if hi_open else v <= hi
    if not ok:
        lo_s = "" if lo is None else f"{lo} {'<' if lo_open else '<='} "
        hi_s = "" if hi is None else f" {'<' if hi_open else '<='} {hi}"
        rng = f" (must satisfy {lo_s}{name}{hi_s})" if (lo is not None or hi is not None) else ""
        raise ConfigError(f"{name} must be a finite number{what}{rng}, got {value!r}")
    return v


def integer(value, name: str, *, lo=None, hi=None) -> int:
    """An integer (Python or NumPy; not bool) within optional inclusive bounds."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ConfigError(f"{name} must be an integer, got {value!r}")
    v = int(value)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ConfigError(f"{name} must be an integer in {lo}..{hi}, got {value!r}")
    return v


def float_array(value, name: str, shape_text: str) -> np.ndarray:
    """Convert to a contiguous float64 array, or raise ConfigError naming the parameter."""
    try:
        return np.ascontiguousarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name} must be numeric, shape {shape_text}: {exc}") from None
