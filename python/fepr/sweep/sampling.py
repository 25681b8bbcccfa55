"""Random parameters: the distributions of a sweep's ``[random]`` table and the seeded draw of each sample.

Sample ``k`` of parameter ``p`` is drawn from its own generator, seeded by the sweep's ``seed``, ``k`` and a hash
of ``p``'s name (:func:`sample_value`). So a sample does not depend on the other parameters, on the order of the
table, or on how many samples there are: adding a parameter or more samples leaves the earlier draws as they
were, and sample ``k`` is the same draw at every point of the grid (grid points are compared on the same random
conditions).

Distributions (``lo``, ``hi``, ``mean``, ``std`` are numbers, or lists of numbers of one length for a vector
parameter such as ``initial.velocity``, drawn per component):

- ``{ uniform = [lo, hi] }``: uniform in ``[lo, hi)``;
- ``{ loguniform = [lo, hi] }``: ``exp`` of uniform in ``[ln lo, ln hi)``, ``0 < lo < hi`` (moduli, densities);
- ``{ normal = [mean, std] }``: Gaussian, ``std >= 0``;
- ``{ integers = [lo, hi] }``: a whole number in ``lo..hi``, both included;
- ``{ choice = [a, b, ...] }``: one of the values, equally likely (any values: names, tables, vectors).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Any, Callable, List, Mapping, Union

import numpy as np

from .._validate import shown
from ..errors import ConfigError

__all__ = ["DISTRIBUTIONS", "Distribution", "parse_distribution", "sample_value"]

DISTRIBUTIONS = ("uniform", "loguniform", "normal", "integers", "choice")

Number = Union[float, List[float]]


@dataclass(frozen=True)
class Distribution:
    """One parameter's distribution: ``kind`` (a name of :data:`DISTRIBUTIONS`) and its ``args`` as given."""

    kind: str
    args: tuple

    def draw(self, rng: np.random.Generator) -> Any:
        """One value: a float, an int (``integers``), a list of floats (vector bounds) or a choice."""
        if self.kind == "choice":
            return self.args[int(rng.integers(len(self.args)))]
        a, b = (np.asarray(x, dtype=np.float64) for x in self.args)
        if self.kind == "uniform":
            x = rng.uniform(a, b)
        elif self.kind == "loguniform":
            x = np.exp(rng.uniform(np.log(a), np.log(b)))
        elif self.kind == "normal":
            x = rng.normal(a, b)
        else:
            x = rng.integers(a.astype(np.int64), b.astype(np.int64), endpoint=True)
            return int(x) if np.ndim(x) == 0 else [int(v) for v in x]
        return float(x) if np.ndim(x) == 0 else [float(v) for v in x]

    def as_json(self) -> dict:
        return {self.kind: list(self.args)}


def _numbers(value: Any, err: Callable[[str], ConfigError], what: str) -> Number:
    def ok(c: Any) -> bool:
        return not isinstance(c, bool) and isinstance(c, (int, float)) and math.isfinite(c)

    if ok(value):
        return float(value)
    if isinstance(value, list) and value and all(ok(c) for c in value):
        return [float(c) for c in value]
    raise err(f"{what} must be a finite number or a list of finite numbers, got {shown(value)}")


def parse_distribution(raw: Any, err: Callable[[str], ConfigError]) -> Distribution:
    """A :class:`Distribution` from its table (``{ uniform = [0, 1] }``); ``err(message)`` makes the error."""
    if not isinstance(raw, Mapping) or len(raw) != 1:
        raise err(
            f"must be a table with one distribution ({', '.join(DISTRIBUTIONS)}), e.g. {{ uniform = [1.0, 2.0] }}, "
            f"got {shown(raw)}"
        )
    ((kind, args),) = raw.items()
    if kind not in DISTRIBUTIONS:
        raise err(f"unknown distribution {kind!r} (known: {', '.join(DISTRIBUTIONS)})")
    if kind == "choice":
        if not isinstance(args, list) or not args:
            raise err(f"choice must be a non-empty list of values, got {shown(args)}")
        return Distribution(kind, tuple(args))
    if not isinstance(args, list) or len(args) != 2:
        names = {"normal": "[mean, std]"}.get(kind, "[lo, hi]")
        raise err(f"{kind} must be {names}, got {shown(args)}")
    a = _numbers(args[0], err, f"{kind}'s first value")
    b = _numbers(args[1], err, f"{kind}'s second value")
    if isinstance(a, list) != isinstance(b, list) or (isinstance(a, list) and len(a) != len(b)):
        raise err(f"{kind}: both values must be numbers, or lists of the same length, got {shown(args)}")
    lo, hi = np.atleast_1d(a), np.atleast_1d(b)
    if kind == "normal":
        if np.any(hi < 0):
            raise err(f"normal's std must be >= 0, got {shown(b)}")
    elif kind == "integers":
        if np.any(lo != np.round(lo)) or np.any(hi != np.round(hi)) or np.any(lo > hi):
            raise err(f"integers must be [lo, hi], whole numbers with lo <= hi, got {shown(args)}")
    else:
        if np.any(lo >= hi):
            raise err(f"{kind} must be [lo, hi] with lo < hi, got {shown(args)}")
        if kind == "loguniform" and np.any(lo <= 0):
            raise err(f"loguniform needs 0 < lo, got {shown(args)}")
    return Distribution(kind, (a, b))


def _path_key(path: str) -> int:
    """A stable 63-bit number for a parameter's name (the same in every process, unlike ``hash``)."""
    return int.from_bytes(hashlib.sha256(path.encode("utf-8")).digest()[:8], "little") >> 1


def sample_value(dist: Distribution, seed: int, sample: int, path: str) -> Any:
    """Sample ``sample`` of the parameter ``path``: drawn from a generator seeded by ``(seed, sample, path)``."""
    ss = np.random.SeedSequence(entropy=int(seed), spawn_key=(int(sample), _path_key(path)))
    return dist.draw(np.random.default_rng(ss))
