"""The cap on decompressed mesh data: how much memory the arrays of one mesh file may take once inflated.

Compressed mesh files (zlib- or lzma-compressed ``.vtu`` data arrays, deflated ``.npz`` members) can inflate to far
more than their size on disk: a 2.6 MB ``.vtu`` can hold 2 GB of zeros. Before such a file is read, its arrays are
checked against the counts the file declares (:mod:`fepr.io._prescan`, :mod:`fepr.io.npz`) and against an absolute
cap on the decompressed bytes of the whole file: :data:`DEFAULT_MAX_MESH_BYTES` (1 GiB, about 44 million vertices
in float64, far more than a simulation can step), raised or lowered with the environment variable
``FEPR_MAX_MESH_BYTES``, e.g. ``FEPR_MAX_MESH_BYTES=8GiB`` (a number of bytes, with an optional suffix ``K``,
``M``, ``G``, ``T``, ``KiB``, ..., all powers of 1024).
"""

from __future__ import annotations

import os
import re

from ..errors import ConfigError

__all__ = ["DEFAULT_MAX_MESH_BYTES", "ENV_VAR", "describe_bytes", "max_mesh_bytes", "over_limit"]

#: The environment variable that sets the cap (bytes).
ENV_VAR = "FEPR_MAX_MESH_BYTES"

#: The cap when ``FEPR_MAX_MESH_BYTES`` is not set: 1 GiB of decompressed array data per mesh file.
DEFAULT_MAX_MESH_BYTES = 1 << 30

_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}
_PATTERN = re.compile(r"^\s*(\d+(?:\.\d*)?(?:[eE]\+?\d+)?)\s*([kKmMgGtT]?)(?:i?[bB])?\s*$")


def max_mesh_bytes() -> int:
    """The cap on the decompressed bytes of one mesh file: ``FEPR_MAX_MESH_BYTES`` or 1 GiB.

    Raises :class:`~fepr.errors.ConfigError` naming the variable when it is set to something other than a
    positive number of bytes.
    """
    raw = os.environ.get(ENV_VAR)
    if raw is None or not raw.strip():
        return DEFAULT_MAX_MESH_BYTES
    m = _PATTERN.match(raw)
    value = float(m.group(1)) * _UNITS[m.group(2).lower()] if m else 0.0
    if not m or not 1 <= value < 2**63:
        raise ConfigError(
            f"environment variable {ENV_VAR}={raw!r}: must be a positive number of bytes, such as 4000000000 or "
            "4GiB (suffixes K, M, G, T are powers of 1024)"
        )
    return int(value)


def describe_bytes(n: int) -> str:
    """``1073741824 bytes (1 GiB)``: exact, with a rounded binary size for large values."""
    if n < 1 << 10:
        return f"{n} bytes"
    for unit, size in (("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= size:
            return f"{n} bytes ({n / size:.3g} {unit})"
    return f"{n} bytes"  # pragma: no cover


def over_limit(cap: int) -> str:
    """The end of a message about the cap: ``more than the limit ..., N bytes; ... raise it with ...``."""
    example = f"{max(2 * cap, 8 << 30) >> 30}GiB"
    return (
        f"more than the limit on decompressed mesh data, {describe_bytes(cap)}; if the file is trusted, raise the "
        f"limit with the environment variable {ENV_VAR} (e.g. {ENV_VAR}={example})"
    )
