"""Checks on the raw arrays a reader returns, done before validation (which lives in :class:`fepr.TetMesh`)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import MeshError


def check_duplicate_tets(path: Path, tets: np.ndarray, lines: Optional[Sequence[int]] = None) -> None:
    """Raise :class:`MeshError` if two tets use the same four vertices (in any order).

    The message names the file, both tet indices (0-based, in reading order) and, when ``lines`` gives the
    line of every tet, both lines.
    """
    t = np.asarray(tets)
    if len(t) < 2:
        return
    keys = np.sort(t, axis=1)
    order = np.lexsort(keys.T[::-1])
    sk = keys[order]
    same = np.flatnonzero(np.all(sk[1:] == sk[:-1], axis=1))
    if same.size == 0:
        return
    # the first duplicate in reading order: among all equal pairs, the one whose later member comes first
    pairs = np.stack([order[same], order[same + 1]], axis=1)
    pairs.sort(axis=1)
    a, b = (int(x) for x in pairs[np.argmin(pairs[:, 1])])
    # the earliest tet with this key
    a = int(np.flatnonzero(np.all(keys == keys[b], axis=1))[0])
    where = f"{path} line {lines[b]}" if lines is not None else f"{path}"
    first = f" (line {lines[a]})" if lines is not None else ""
    raise MeshError(
        f"{where}: tet {b} {t[b].tolist()} duplicates tet {a}{first} {t[a].tolist()}: both use vertices "
        f"{sorted(int(x) for x in t[a])}; remove one of them (total {int(same.size)} duplicate(s))"
    )
