"""A run's output folder: checked before the first step, never half-written, described by ``run.json``.

:class:`RunFolder` is what ``fepr run`` writes into:

- before the first step it creates the folder and writes a probe file, so that a folder that cannot be written
  is found before any work is done;
- a folder that holds an earlier run's files (its ``run.json``, or any of the names a run writes) is refused
  unless ``overwrite`` (which removes the files that run's manifest lists, and nothing else) or ``resume``;
- every file goes through a temporary name in the same folder and is renamed when complete
  (:func:`fepr.io.atomic.atomic_path`);
- ``run.json`` (the manifest) says what the run is (scene, fepr version, settings), how far it got (status
  ``running``, ``complete``, ``interrupted`` or ``failed``, steps, time), its checkpoint and the files it wrote,
  with their sizes and SHA-256 hashes.

The diagnostics are written while the run goes (:class:`CsvStream`, on a worker thread, :class:`OutputWorker`,
while the core steps without the GIL) to a temporary name that becomes ``diagnostics.csv`` when the run ends or
stops, so that stopping costs the last rows, not the whole history. The checkpoint of a run with
``--checkpoint-every`` (or an interrupted one) lives in ``checkpoint/``: the simulation's state
(``state_<step>.npz``, :meth:`fepr.Simulation.save_checkpoint` without its history) and, for the animation files
written at the end (glb, usd), the surface of each frame since the last checkpoint (``frames_<first>_<last>.npz``);
the manifest records how many rows and bytes of each diagnostics file belong to the checkpoint, so that a resumed
run cuts the files there and reads its history back from them.
"""

from __future__ import annotations

import hashlib
import json
import os
import queue
import shutil
import threading
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..errors import ConfigError
from ..io.atomic import atomic_path

__all__ = ["RunFolder", "CsvStream", "OutputWorker", "MANIFEST", "CHECKPOINT_DIR"]

MANIFEST = "run.json"
CHECKPOINT_DIR = "checkpoint"
#: Names an earlier run may have left (checked when there is no manifest to say).
_RUN_NAMES = ("diagnostics.csv", "final_state.npz", CHECKPOINT_DIR, "export", MANIFEST)


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes, hex (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class RunFolder:
    """The output folder of one run (see the module docs).

    Parameters
    ----------
    path : Path
        The folder (created if needed).
    overwrite : bool
        Remove an earlier run's files (those its manifest lists) instead of refusing.
    resume : bool
        Continue the earlier run in the folder (its manifest and checkpoint must be there).
    """

    def __init__(self, path, *, overwrite: bool = False, resume: bool = False):
        self.path = Path(path)
        self.overwrite = overwrite
        self.resume = resume
        self.manifest: Dict[str, Any] = {}
        self.earlier: Optional[Dict[str, Any]] = None
        #: SHA-256 of files hashed as they were written: ``path -> (size, mtime_ns, sha256)``.
        self.hashes: Dict[Path, Tuple[int, int, str]] = {}
        self._hash_lock = threading.Lock()

    # --- before the first step ---------------------------------------------------------------------------
    def prepare(self) -> None:
        """Create the folder, check that it can be written, and deal with an earlier run's files."""
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OSError(f"cannot create the output folder {self.path}: {exc.strerror or exc}") from None
        try:
            with atomic_path(self.path / ".fepr-write-probe") as tmp:
                Path(tmp).write_bytes(b"")
            (self.path / ".fepr-write-probe").unlink()
        except OSError as exc:
            raise OSError(f"the output folder {self.path} cannot be written: {exc.strerror or exc}") from None
        manifest = self.path / MANIFEST
        if manifest.is_file():
            try:
                self.earlier = json.loads(manifest.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise ConfigError(f"{manifest}: not a readable run manifest ({exc})") from None
        if self.resume:
            if self.earlier is None:
                raise ConfigError(f"--resume {self.path}: no {MANIFEST} there (not a fepr run folder)")
            if self.earlier.get("status") == "complete":
                raise ConfigError(f"--resume {self.path}: that run is complete; nothing to resume")
            ck = self.earlier.get("checkpoint") or {}
            if not (ck.get("state") and (self.path / CHECKPOINT_DIR / ck["state"]).is_file()):
                raise ConfigError(
                    f"--resume {self.path}: the run has no checkpoint (its {MANIFEST} names none, or the file is "
                    "gone); a run keeps one with --checkpoint-every K, or when it is interrupted"
                )
            return
        found = sorted(n for n in _RUN_NAMES if (self.path / n).exists())
        found += sorted(p.name for p in self.path.glob("diagnostics_*.csv"))
        if not found:
            return
        if not self.overwrite:
            status = f" (status: {self.earlier.get('status', '?')})" if self.earlier else ""
            raise ConfigError(
                f"the output folder {self.path} holds an earlier run's files{status}: {', '.join(found)}; use "
                "--overwrite to replace them, --resume to continue that run, or another --out"
            )
        self._remove_earlier(found)

    def _remove_earlier(self, found: Sequence[str]) -> None:
        """Remove the earlier run's files: those its manifest lists (or, without one, the names a run writes)."""
        listed = [f["path"] for f in (self.earlier or {}).get("files", [])]
        names = listed if self.earlier is not None else list(found)
        for rel in names + [CHECKPOINT_DIR, "export", MANIFEST]:
            p = (self.path / rel).resolve()
            if self.path.resolve() not in p.parents:
                continue  # a manifest entry outside the folder is not this run's to remove
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            elif p.exists():
                p.unlink()

    # --- the manifest ------------------------------------------------------------------------------------
    def write_manifest(self, **fields: Any) -> None:
        """Update the manifest with ``fields`` and write it atomically."""
        self.manifest.update(fields)
        self.manifest["updated"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        with atomic_path(self.path / MANIFEST) as tmp:
            Path(tmp).write_text(json.dumps(self.manifest, indent=2, allow_nan=True) + "\n", encoding="utf-8")

    def note_hash(self, path: Path, sha256: Optional[str] = None) -> None:
        """Hash ``path`` now (or record the ``sha256`` its writer computed), for :meth:`file_entries`."""
        path = Path(path)
        st = path.stat()
        digest = sha256 if sha256 is not None else file_sha256(path)
        with self._hash_lock:
            self.hashes[path] = (st.st_size, st.st_mtime_ns, digest)

    def file_entries(self, paths: Sequence[Path]) -> List[Dict[str, Any]]:
        """``{path, size, sha256}`` of each file (path relative to the folder), for the manifest; a file hashed as
        it was written (:meth:`note_hash`) and unchanged since is not read again."""
        out = []
        for p in paths:
            p = Path(p)
            if not p.is_file():
                continue
            st = p.stat()
            with self._hash_lock:
                known = self.hashes.get(p)
            digest = known[2] if known and known[:2] == (st.st_size, st.st_mtime_ns) else file_sha256(p)
            out.append({"path": p.relative_to(self.path).as_posix(), "size": st.st_size, "sha256": digest})
        return out

    def all_files(self) -> List[Path]:
        """Every file in the folder but the manifest (what the run wrote), sorted."""
        return sorted(p for p in self.path.rglob("*") if p.is_file() and p.name != MANIFEST)

    # --- checkpoints -------------------------------------------------------------------------------------
    @property
    def checkpoint_dir(self) -> Path:
        return self.path / CHECKPOINT_DIR

    def write_frames(self, first: int, last: int, arrays: Dict[str, np.ndarray]) -> str:
        """The exported frames of steps ``first..last`` (for the animation files written at the end) as one block
        file; returns its name."""
        self.checkpoint_dir.mkdir(exist_ok=True)
        from ..io.npz import save_npz

        name = f"frames_{first:012d}_{last:012d}.npz"
        save_npz(self.checkpoint_dir / name, arrays)
        return name

    def read_blocks(self, names: Sequence[str]) -> Dict[str, List[np.ndarray]]:
        """The blocks ``names`` (as :meth:`write_frames` wrote them), per array name, in order."""
        out: Dict[str, List[np.ndarray]] = {}
        for name in names:
            path = self.checkpoint_dir / name
            try:
                with np.load(path, allow_pickle=False) as z:
                    for k in z.files:
                        out.setdefault(k, []).append(z[k])
            except (OSError, ValueError) as exc:
                raise ConfigError(f"--resume: the checkpoint block {path} cannot be read ({exc})") from None
        return out

    def remove_stale(self, keep: Sequence[str]) -> None:
        """Remove checkpoint files the manifest does not list (written after the last checkpoint of a run that
        was killed) and temporary files anywhere in the folder."""
        if self.checkpoint_dir.is_dir():
            for p in self.checkpoint_dir.iterdir():
                if p.is_file() and p.name not in keep:
                    p.unlink()
        for p in self.path.rglob(".*.part*"):
            if p.is_file() and not p.name.startswith(".diagnostics"):
                p.unlink()


class OutputWorker:
    """One thread that writes outputs while the run steps (the core releases the GIL): jobs run in order;
    :meth:`submit` waits while more than ``backlog`` jobs are queued, so a run never gets far ahead of its
    files (and stopping it costs at most that backlog). An error in a job is raised by the next
    :meth:`submit`, :meth:`drain` or :meth:`close`."""

    def __init__(self, backlog: int = 8):
        self._jobs: queue.Queue[Optional[Callable[[], None]]] = queue.Queue(maxsize=backlog)
        self._error: Optional[BaseException] = None
        self._thread = threading.Thread(target=self._run, name="fepr-outputs", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            try:
                if job is None:
                    return
                if self._error is None:
                    job()
            except BaseException as exc:  # kept for the caller's thread
                self._error = exc
            finally:
                self._jobs.task_done()

    def _raise(self) -> None:
        if self._error is not None:
            err, self._error = self._error, None
            raise err

    def submit(self, job: Callable[[], None]) -> None:
        self._raise()
        self._jobs.put(job)

    def drain(self) -> None:
        """Wait until every job submitted so far is done."""
        self._jobs.join()
        self._raise()

    def close(self) -> None:
        if self._thread.is_alive():
            self._jobs.put(None)
            self._thread.join()
        self._raise()


class CsvStream:
    """A CSV file written as its rows come: to ``.<name>.part`` in the folder, renamed to ``name`` by
    :meth:`finish`. Rows are formatted as :func:`fepr.history.write_csv_rows` formats them (exact round trip);
    the SHA-256 of the bytes is kept as they are written.

    :meth:`mark` says how many rows and bytes are written (a checkpoint records it); :meth:`resume` opens the file
    of an earlier part of the run again, cut at such a mark.
    """

    def __init__(self, folder: RunFolder, name: str, columns: Sequence[str], ints: Sequence[bool]):
        self.folder, self.name = folder, name
        self.columns, self.ints = list(columns), list(ints)
        self.path = folder.path / name
        self.part = folder.path / f".{name}.part"
        self.rows = 0
        self.bytes = 0
        self._sha = hashlib.sha256()
        self._fh = None

    def open(self) -> None:
        self._fh = open(self.part, "w", encoding="ascii", newline="")
        self._write_text(",".join(self.columns) + "\r\n")

    def resume(self, rows: int, size: int) -> np.ndarray:
        """Open the earlier part's file (renamed or still ``.part``) cut at ``rows`` rows (``size`` bytes);
        returns those rows, (rows, columns) float64 (the history to resume with)."""
        src = self.part if self.part.is_file() else self.path
        if not src.is_file() or src.stat().st_size < size:
            raise ConfigError(f"--resume: {self.path} is missing or shorter than at the checkpoint")
        if src != self.part:
            os.replace(src, self.part)
        with open(self.part, "r+b") as fh:
            fh.truncate(size)
            for block in iter(lambda: fh.read(1 << 20), b""):
                self._sha.update(block)
        self.bytes = size
        table = np.loadtxt(self.part, delimiter=",", skiprows=1, ndmin=2, dtype=np.float64)
        if table.shape[0] != rows or (rows and table.shape[1] != len(self.columns)):
            raise ConfigError(f"--resume: {self.path} does not hold the {rows} rows of the checkpoint")
        self.rows = rows
        self._fh = open(self.part, "a", encoding="ascii", newline="")
        return table

    def _write_text(self, text: str) -> None:
        data = text.encode("ascii")
        self._fh.write(text)
        self._sha.update(data)
        self.bytes += len(data)

    def append(self, rows: np.ndarray) -> None:
        """Append rows (a (k, columns) array); called on the worker thread."""
        import io

        from ..history import write_csv_rows

        buf = io.StringIO()
        write_csv_rows(buf, None, self.ints, [rows])
        self._write_text(buf.getvalue())
        self.rows += len(rows)

    def mark(self) -> Dict[str, int]:
        """Rows and bytes written so far (after the worker drained)."""
        self._fh.flush()
        return {"rows": self.rows, "bytes": self.bytes}

    def finish(self) -> Path:
        """Close the file and rename it to its name; record its hash with the folder."""
        self._fh.close()
        os.replace(self.part, self.path)
        self.folder.note_hash(self.path, self._sha.hexdigest())
        return self.path
