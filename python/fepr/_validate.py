"""Parameter checks shared by the public constructors: each raises ConfigError naming the parameter.

Numbers in messages are printed compactly (:func:`shown`): ``1e+300``, not 301 digits. Some physical parameters are
also checked for magnitude (:func:`check_magnitude`, called by :func:`real` for the names in :data:`PLAUSIBLE`):
values that cannot work in double precision are a :class:`~fepr.errors.ConfigError`, implausible but computable
ones an :class:`~fepr.errors.ImplausibleValueWarning`.
"""

from __future__ import annotations

import math
import numbers
import re
import sys
import warnings
from typing import Dict, Optional, Tuple

import numpy as np

from .errors import ConfigError, ImplausibleValueWarning

#: Magnitudes fepr can compute with: a parameter outside ``[COMPUTABLE[0], COMPUTABLE[1]]`` is an error. Energies,
#: momenta and the projection's sums of squares multiply several such parameters (mass x velocity^2, Young's
#: modulus x volume x strain^2 / time step^2, energy^2) and must stay within float64's range (about 1e-308 to
#: 1e308); beyond 1e+-100 they overflow to infinity or vanish below rounding, so every projection fails or the
#: physics is lost. Such values are always a units mistake or a typo.
COMPUTABLE: Tuple[float, float] = (1e-100, 1e100)

#: Plausible ranges (warnings outside them): parameter -> (unit, low, high, what real values are).
PLAUSIBLE: Dict[str, Tuple[str, Optional[float], Optional[float], str]] = {
    "density": (
        "kg/m^3",
        1e-3,
        1e6,
        "real solids lie between about 0.2 kg/m^3 (aerogels) and 2.3e4 kg/m^3 (osmium)",
    ),
    "youngs_modulus": (
        "Pa",
        1.0,
        1e13,
        "real materials lie between about 10 Pa (the softest gels) and 1.2e12 Pa (diamond)",
    ),
    "dt": (
        "s",
        1e-9,
        1.0,
        "time steps of elastic simulations lie between about 1e-6 s and 0.1 s (above 1 s no elastic motion is "
        "resolved; below 1 ns a second of motion takes a billion steps)",
    ),
    "node_mass": ("kg", None, None, ""),
}


def shown(value, limit: int = 80) -> str:
    """A value as messages show it: numbers compactly (``1e+300``, ``0.001``; NumPy scalars as plain numbers, a huge
    int as ``1e+400``), other values as ``repr`` cut to ``limit`` characters."""
    if isinstance(value, (bool, np.bool_)):
        return repr(bool(value))
    if isinstance(value, numbers.Integral):
        text = str(int(value))
        digits = text.lstrip("-")
        if len(digits) <= 16:
            return text
        sign = "-" if text.startswith("-") else ""
        frac = digits[1:6].rstrip("0")
        return f"{sign}{digits[0]}{'.' + frac if frac else ''}e+{len(digits) - 1}"
    if isinstance(value, numbers.Real):
        return repr(float(value))  # the shortest text that round-trips: '1e+300', '0.1', never 300 digits
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


_LONG_NUMBER = re.compile(r"(?<![\w.])-?(?:\d+\.?\d*|\.\d+)(?![\w.])")


def compact_numbers(message: str) -> str:
    """``message`` with every number written with more than 20 digits (as Rust's ``{}`` and ``{:.6}`` print 1e300
    or 1e-300) shortened to 6 significant digits: ``got 1e+300`` instead of 301 digits."""

    def short(m: re.Match[str]) -> str:
        text = m.group(0)
        if sum(c.isdigit() for c in text) <= 20:
            return text
        try:
            return format(float(text), ".6g")
        except (ValueError, OverflowError):
            return text

    return _LONG_NUMBER.sub(short, message)


def _g(x) -> str:
    """A number with 6 significant digits: ``1e+07``, ``0.001``, ``1e+300``."""
    return format(float(x), ".6g")


def check_magnitude(value: float, name: str, *, warn: bool = True) -> None:
    """Raise ConfigError if ``value`` of parameter ``name`` (a key of :data:`PLAUSIBLE`) lies outside the range fepr
    can compute with (:data:`COMPUTABLE`); with ``warn``, warn (:class:`~fepr.errors.ImplausibleValueWarning`) if
    it lies outside the plausible range. Other names are not checked."""
    info = PLAUSIBLE.get(name)
    if info is None:
        return
    unit, lo, hi, why = info
    v = abs(float(value))
    if v == 0.0 or not math.isfinite(v):
        return  # left to the sign and finiteness checks
    u = f" {unit}" if unit else ""
    if not COMPUTABLE[0] <= v <= COMPUTABLE[1]:
        raise ConfigError(
            f"{name} = {_g(value)}{u} is outside the range fepr can compute with ({_g(COMPUTABLE[0])} to "
            f"{_g(COMPUTABLE[1])}{u}): energies, momenta and their squares would overflow or vanish in double "
            f"precision; check the value and its units (SI: {unit})"
        )
    if not warn:
        return
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        side = "below" if lo is not None and v < lo else "above"
        msg = (
            f"{name} = {_g(value)}{u} is implausible ({side} {_g(lo if side == 'below' else hi)}{u}): {why}; "
            f"check the value and its units (SI: {unit})"
        )
        w = ImplausibleValueWarning(msg)
        w.parameter = name
        warnings.warn(w, stacklevel=_user_stacklevel())


def _user_stacklevel() -> int:
    """The ``stacklevel`` that points a warning at the first frame outside the fepr package (and outside contextlib,
    whose frames a ``with`` block in fepr adds; dataclass-generated ``__init__`` methods count as their module's)."""
    frame = sys._getframe(1)  # the caller of this function: level 1 for warnings.warn called there
    level = 1
    while frame is not None:
        module = frame.f_globals.get("__name__", "")
        if not (module == "fepr" or module.startswith("fepr.") or module == "contextlib"):
            break
        frame = frame.f_back
        level += 1
    return level


def real(value, name: str, *, unit: str = "", lo=None, hi=None, lo_open=False, hi_open=False) -> float:
    """A finite real number (Python or NumPy; not bool, not str) within optional bounds, as float.

    The parameters named in :data:`PLAUSIBLE` (``density``, ``youngs_modulus``, ``dt``, ``node_mass``) are also
    checked for magnitude (:func:`check_magnitude`): an error outside :data:`COMPUTABLE`, a warning outside the
    plausible range.
    """
    what = f" ({unit})" if unit else ""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ConfigError(f"{name} must be a number{what}, got {shown(value)}")
    v = float(value)
    ok = math.isfinite(v)
    if ok and lo is not None:
        ok = v > lo if lo_open else v >= lo
    if ok and hi is not None:
        ok = v < hi if hi_open else v <= hi
    if not ok:
        lo_s = "" if lo is None else f"{shown(lo)} {'<' if lo_open else '<='} "
        hi_s = "" if hi is None else f" {'<' if hi_open else '<='} {shown(hi)}"
        rng = f" (must satisfy {lo_s}{name}{hi_s})" if (lo is not None or hi is not None) else ""
        raise ConfigError(f"{name} must be a finite number{what}{rng}, got {shown(value)}")
    check_magnitude(v, name)
    return v


def integer(value, name: str, *, lo=None, hi=None) -> int:
    """An integer (Python or NumPy; not bool) within optional inclusive bounds."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ConfigError(f"{name} must be an integer, got {shown(value)}")
    v = int(value)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ConfigError(f"{name} must be an integer in {lo}..{hi}, got {shown(value)}")
    return v


def float_array(value, name: str, shape_text: str) -> np.ndarray:
    """Convert to a contiguous float64 array, or raise ConfigError naming the parameter."""
    try:
        return np.ascontiguousarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name} must be numeric, shape {shape_text}: {exc}") from None
