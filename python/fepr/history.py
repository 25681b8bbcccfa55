"""Per-step diagnostics: :class:`History` (what ``sim.history`` returns) and the store behind it.

A simulation's diagnostics grow by one row of ~60 float64 per step. The core hands its rows over after every
batch of steps and keeps only the last (:class:`HistoryStore` takes them), so memory does not grow inside the
core; the store keeps its rows in chunks, and past :attr:`HistoryStore.memory_rows` rows it writes the oldest
chunks to a temporary folder and reads them back (memory-mapped) only when a column is asked for. Reading a
column costs the rows of that column; the last row costs nothing (:attr:`HistoryStore.last`).
"""

from __future__ import annotations

import math
import shutil
import tempfile
import weakref
from pathlib import Path
from typing import Dict, FrozenSet, Iterator, List, Optional, Sequence, Union

import numpy as np

from . import _core
from .errors import ConfigError

__all__ = ["History", "HistoryStore", "DEFAULT_MEMORY_ROWS"]

#: Rows a chunk holds once full (the small batches the core hands over are gathered into chunks of this size).
CHUNK_ROWS = 4096

#: Rows of history kept in memory by default (about 8 MB for a single body); older rows go to a temporary
#: folder. ``sim.history_memory_rows`` (or ``HistoryStore(memory_rows=...)``) changes it; ``None`` keeps all.
DEFAULT_MEMORY_ROWS = 4 * CHUNK_ROWS


class HistoryStore:
    """The rows of a history, appended in batches, in chunks of :data:`CHUNK_ROWS` rows.

    ``memory_rows`` (int or None): full chunks beyond this many rows in memory are written to a temporary folder
    (removed when the store is collected) and memory-mapped back when read. ``None``: everything in memory.
    """

    def __init__(self, columns: Sequence[str], memory_rows: Optional[int] = DEFAULT_MEMORY_ROWS):
        self.columns: List[str] = list(columns)
        self.memory_rows = memory_rows
        self._full: List[Union[np.ndarray, Path]] = []  # full chunks, in memory or spilled (a .npy path)
        self._open: List[np.ndarray] = []  # the batches after the last full chunk
        self._open_rows = 0
        self._rows = 0
        self._in_memory = 0
        self._last: Optional[np.ndarray] = None
        self._spill: Optional[Path] = None
        self._cleanup = None

    @property
    def memory_rows(self) -> Optional[int]:
        return self._memory_rows

    @memory_rows.setter
    def memory_rows(self, value: Optional[int]) -> None:
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0):
            raise ConfigError(f"history_memory_rows must be a non-negative integer or None, got {value!r}")
        self._memory_rows = None if value is None else int(value)

    def __len__(self) -> int:
        return self._rows

    @property
    def last(self) -> Optional[np.ndarray]:
        """The last row, (columns,) float64 (None when empty)."""
        return self._last

    @property
    def spilled_rows(self) -> int:
        """Rows written to the temporary folder."""
        return self._rows - self._in_memory

    def clear(self) -> None:
        self._full, self._open, self._open_rows, self._rows, self._in_memory = [], [], 0, 0, 0
        self._last = None

    def append(self, rows: np.ndarray) -> None:
        """Append a (k, columns) float64 batch."""
        rows = np.asarray(rows, dtype=np.float64)
        if rows.ndim != 2 or rows.shape[1] != len(self.columns):
            raise ValueError(f"history rows must have shape (k, {len(self.columns)}), got {rows.shape}")
        if not len(rows):
            return
        self._open.append(rows)
        self._open_rows += len(rows)
        self._rows += len(rows)
        self._in_memory += len(rows)
        self._last = rows[-1].copy()
        if self._open_rows >= CHUNK_ROWS:
            merged = np.concatenate(self._open) if len(self._open) > 1 else self._open[0]
            k = (len(merged) // CHUNK_ROWS) * CHUNK_ROWS
            self._full.extend(merged[i : i + CHUNK_ROWS].copy() for i in range(0, k, CHUNK_ROWS))
            rest = merged[k:]
            self._open = [rest.copy()] if len(rest) else []
            self._open_rows = len(rest)
            self._spill_old()

    def _spill_old(self) -> None:
        """Write the oldest in-memory full chunks to the temporary folder while more than ``memory_rows`` rows
        are in memory."""
        if self._memory_rows is None:
            return
        for i, chunk in enumerate(self._full):
            if self._in_memory <= self._memory_rows:
                break
            if isinstance(chunk, Path):
                continue
            if self._spill is None:
                self._spill = Path(tempfile.mkdtemp(prefix="fepr-history-"))
                self._cleanup = weakref.finalize(self, shutil.rmtree, str(self._spill), True)
            path = self._spill / f"chunk{i:08d}.npy"
            np.save(path, chunk)
            self._full[i] = path
            self._in_memory -= len(chunk)

    def _chunks(self, stop: int, start: int = 0) -> Iterator[np.ndarray]:
        """The parts of the chunks holding rows ``[start, stop)``, in order (chunks outside are not read)."""
        seen = 0
        for chunk in [*self._full, *self._open]:
            if seen >= stop:
                return
            n = CHUNK_ROWS if isinstance(chunk, Path) else len(chunk)
            if seen + n > start:
                a = np.load(chunk, mmap_mode="r") if isinstance(chunk, Path) else chunk
                yield a[max(start - seen, 0) : min(n, stop - seen)]
            seen += n

    def column(self, index: int, stop: Optional[int] = None, start: int = 0) -> np.ndarray:
        """Column ``index`` over rows ``[start, stop)`` as a new (rows,) float64 array."""
        stop = self._rows if stop is None else stop
        parts = [np.asarray(c[:, index]) for c in self._chunks(stop, start)]
        return np.concatenate(parts) if parts else np.zeros(0)

    def table(self, stop: Optional[int] = None, start: int = 0) -> np.ndarray:
        """Rows ``[start, stop)`` as one (rows, columns) float64 array."""
        stop = self._rows if stop is None else stop
        parts = [np.asarray(c) for c in self._chunks(stop, start)]
        return np.concatenate(parts) if parts else np.zeros((0, len(self.columns)))

    def batches(self, start: int = 0, stop: Optional[int] = None) -> Iterator[np.ndarray]:
        """Rows ``[start, stop)`` chunk by chunk (for writing without holding the whole table)."""
        stop = self._rows if stop is None else stop
        for c in self._chunks(stop, start):
            if len(c):
                yield np.asarray(c)


class History:
    """Per-step diagnostics, one row per step; row 0 is the initial state.

    ``h["total"]`` is a column as a (rows,) float64 array; ``h.columns`` lists the names; ``h.as_dict()``
    gives all columns; ``h.last`` the last row as a dict. Energies in J, momenta in kg m/s, angular momenta
    (about the centre of mass) in kg m^2/s, times in s, wall times in ms. Every column is described in
    ``docs/concepts.md`` (Diagnostics). The counts and 0/1 flags (:attr:`INTEGER_COLUMNS`) are int64 arrays
    (``h["inverted"]``, ``h["proj_converged"]``; the other columns float64) and integers in the CSV that
    :meth:`to_csv` writes.

    A history taken from a simulation is a snapshot: later steps do not change it. Reading a column reads only
    that column's rows (older rows may come back from the simulation's temporary folder, see
    :class:`HistoryStore`).
    """

    #: The columns that hold counts or 0/1 flags (written as integers by :meth:`to_csv`).
    INTEGER_COLUMNS: FrozenSet[str] = frozenset(_core.HISTORY_INTEGER_COLUMNS)

    def __init__(self, data, columns: Sequence[str], *, rows: Optional[int] = None):
        """``data``: a (rows, columns) float64 array, or a :class:`HistoryStore` (its first ``rows`` rows)."""
        self.columns: List[str] = list(columns)
        self._index = {c: i for i, c in enumerate(self.columns)}
        if isinstance(data, HistoryStore):
            self._store: Optional[HistoryStore] = data
            self._data: Optional[np.ndarray] = None
            self._rows = len(data) if rows is None else int(rows)
        else:
            self._store = None
            self._data = np.asarray(data)
            self._rows = int(self._data.shape[0])

    def __len__(self) -> int:
        return self._rows

    def _col(self, i: int) -> np.ndarray:
        if self._store is not None:
            return self._store.column(i, self._rows)
        return self._data[:, i]

    def __getitem__(self, name: str) -> np.ndarray:
        """Column ``name``, (rows,): int64 for the counts and flags (:attr:`INTEGER_COLUMNS`), float64 else."""
        try:
            i = self._index[name]
        except KeyError:
            raise KeyError(f"no history column {name!r} (columns: {', '.join(self.columns)})") from None
        return _typed(name, self._col(i))

    def _slice(self, name: str, start: int, stop: int) -> np.ndarray:
        """Column ``name`` over rows ``[start, stop)`` (reading only those rows)."""
        i = self._index[name]
        if self._store is not None:
            return self._store.column(i, min(stop, self._rows), start)
        return self._data[start:stop, i]

    @property
    def last(self) -> Dict[str, float]:
        """The last row as ``{column: value}`` (O(1) for a simulation's history)."""
        if not self._rows:
            raise IndexError("the history is empty")
        if self._store is not None and self._rows == len(self._store):
            row = self._store.last
        else:
            row = self._table()[-1]
        return dict(zip(self.columns, row.tolist()))

    def _table(self) -> np.ndarray:
        return self._store.table(self._rows) if self._store is not None else self._data

    def _batches(self) -> Iterator[np.ndarray]:
        if self._store is not None:
            yield from self._store.batches(0, self._rows)
        else:
            yield self._data

    def __iter__(self) -> Iterator[Dict[str, float]]:
        for batch in self._batches():
            for row in batch:
                yield dict(zip(self.columns, row.tolist()))

    def as_dict(self, columns: Optional[Sequence[str]] = None) -> Dict[str, np.ndarray]:
        """Every column (or those of ``columns`` it has), as new arrays; the rows are read once."""
        names = [c for c in (self.columns if columns is None else columns) if c in self._index]
        if self._store is not None:
            idx = [self._index[c] for c in names]
            parts = [np.asarray(c)[:, idx] for c in self._store._chunks(self._rows)]
            table = np.concatenate(parts) if parts else np.zeros((0, len(idx)))
            return {c: _typed(c, np.array(table[:, k])) for k, c in enumerate(names)}
        return {c: _typed(c, np.array(self._data[:, self._index[c]])) for c in names}

    def to_csv(self, path: Union[str, Path], *, start: int = 0, header: bool = True, append: bool = False) -> None:
        """Write the history as CSV: a header of column names, then one row per step. The counts and flags
        (:attr:`INTEGER_COLUMNS`) are written as integers (``3``, not ``3.0``), the other columns as floats
        (shortest round-trip form; ``nan`` where undefined). ``start``: the first row to write; ``append``:
        add to an existing file (``header`` False then)."""
        ints = [c in self.INTEGER_COLUMNS for c in self.columns]
        with open(path, "a" if append else "w", newline="") as fh:
            write_csv_rows(fh, self.columns if header else None, ints, self._rows_from(start))

    def _rows_from(self, start: int) -> Iterator[np.ndarray]:
        if self._store is not None:
            yield from self._store.batches(start, self._rows)
        else:
            yield self._data[start:]

    def __repr__(self) -> str:
        return f"History({len(self)} rows, columns={self.columns})"


def _typed(name: str, column: np.ndarray) -> np.ndarray:
    """A count or flag column as int64 (when every value is finite, as in a simulation's history)."""
    if name in History.INTEGER_COLUMNS and np.all(np.isfinite(column)):
        return column.astype(np.int64)
    return column


def write_csv_rows(fh, columns: Optional[Sequence[str]], ints: Sequence[bool], batches) -> None:
    """Write a header (unless ``columns`` is None) and the rows of ``batches`` to an open text file: the columns
    flagged in ``ints`` as integers where finite, the others in Python's shortest round-trip form (``repr``), so
    that reading the file back gives the same bits. Rows end in CRLF, as the csv module writes them."""
    if columns is not None:
        fh.write(",".join(columns) + "\r\n")
    int_columns = [i for i, flag in enumerate(ints) if flag]
    for batch in batches:
        lines = []
        for row in np.asarray(batch, dtype=np.float64).tolist():
            text = list(map(repr, row))
            for i in int_columns:
                v = row[i]
                if v == v and v != math.inf and v != -math.inf:
                    text[i] = str(int(v))
            lines.append(",".join(text))
        if lines:
            fh.write("\r\n".join(lines) + "\r\n")
