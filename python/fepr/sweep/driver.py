"""Running a sweep (what ``fepr sweep`` does): plan the runs, skip the finished ones, run the rest, write the index.

:func:`run_sweep` reads the sweep (:mod:`fepr.sweep.spec`), expands it into runs (:mod:`fepr.sweep.plan`),
writes ``DIR/sweep.json`` (the manifest: the sweep, its runs and their parameters, how it was run, its status),
skips every run whose ``status.json`` says it finished and whose files still have their recorded SHA-256, runs
the others on an executor (:mod:`fepr.sweep.backends`) with one progress bar over all runs, and writes
``DIR/index.parquet`` (:mod:`fepr.sweep.index`) and, with ``dataset=True``, ``DIR/dataset``
(:mod:`fepr.sweep.dataset`).

Stopping a sweep (Ctrl-C) writes the index and the manifest of what finished (the rest ``pending``) and leaves
each unfinished run's last checkpoint: running the same sweep again continues where it stopped.
"""

from __future__ import annotations

import json
import socket
import sys
import time
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Union

from ..errors import ConfigError
from ..io.atomic import atomic_path
from .backends import make_executor
from .index import build_index, require_pandas, write_index
from .plan import RunPlan, plan_runs
from .runner import FINISHED, STATUS, RunTask, read_status, verify_files
from .spec import SweepSpec, load_sweep, sweep_from_dict

__all__ = ["MANIFEST", "run_sweep", "summary_line"]

MANIFEST = "sweep.json"


def summary_line(info: Mapping[str, Any]) -> str:
    """One line of what a sweep did, from ``df.attrs["sweep"]`` of :func:`run_sweep`'s index."""
    c = info["counts"]
    parts = [f"{c.get(k, 0)} {k}" for k in ("complete", "runaway", "failed", "pending") if c.get(k)]
    return (
        f"fepr sweep {info['name']}: {c.get('runs', 0)} runs: {', '.join(parts) or 'none'} "
        f"({c.get('skipped', 0)} already finished, skipped); {info['wall_s']:.1f} s on {info['backend']} "
        f"({info['slots']} at a time); index {info['index']}"
    )


def _spec_of(sweep: Union[str, Path, Mapping[str, Any], SweepSpec], base_dir) -> SweepSpec:
    if isinstance(sweep, SweepSpec):
        return sweep
    if isinstance(sweep, Mapping):
        return sweep_from_dict(sweep, "." if base_dir is None else base_dir)
    return load_sweep(sweep)


def _write_manifest(out: Path, manifest: Dict[str, Any]) -> None:
    manifest["updated"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    with atomic_path(out / MANIFEST) as tmp:
        Path(tmp).write_text(json.dumps(manifest, indent=1, allow_nan=True) + "\n", encoding="utf-8")


def _finished_record(out: Path, plan: RunPlan) -> Optional[Dict[str, Any]]:
    """The record of a run that finished before (status, parameters and file hashes agree), or None. A run whose
    files changed since is cleared, to run again."""
    folder = out / "runs" / plan.run_id
    status = read_status(folder)
    if status is None or status.get("run_id") != plan.run_id or status.get("status") not in FINISHED:
        return None
    if json.dumps(status.get("params"), sort_keys=True) == json.dumps(plan.params, sort_keys=True) and verify_files(
        folder, status
    ):
        return status
    for f in status.get("files", []):  # damaged or edited since: run again from scratch
        (folder / f["path"]).unlink(missing_ok=True)
    (folder / STATUS).unlink(missing_ok=True)
    return None


def run_sweep(
    sweep: Union[str, Path, Mapping[str, Any], SweepSpec],
    out_dir: Union[str, Path],
    *,
    backend: str = "auto",
    address: Optional[str] = None,
    workers: Optional[int] = None,
    dataset: bool = False,
    progress: bool = True,
    base_dir: Union[str, Path, None] = None,
):
    """Run a sweep: every run of ``sweep`` into ``out_dir/runs/<id>``, and its index.

    Parameters
    ----------
    sweep : str, Path, dict or SweepSpec
        A sweep file (TOML, :mod:`fepr.sweep.spec`), the same as a dict of sections (relative paths against
        ``base_dir``, default the working folder), or a :class:`~fepr.sweep.spec.SweepSpec`.
    out_dir : str or Path
        The sweep's folder: ``sweep.json``, ``index.parquet``, ``runs/<id>/``, ``meshes/`` (and ``dataset/``).
        Runs that finished there before (same id, files intact) are skipped; unfinished ones continue from their
        checkpoints. On a cluster it must be on storage every node mounts at the same path.
    backend : str
        ``"auto"`` (Ray if installed, else the local pool), ``"ray"``, ``"pool"`` (local processes) or
        ``"serial"`` (this process). The results are bit-identical whichever runs them.
    address : str, optional
        A Ray cluster to join (``"auto"``, ``"ray://host:10001"``); default: a local Ray instance with the machine's
        cores, stopped at the end.
    workers : int, optional
        Processes of the local pool (default: cores // ``cpus_per_run``).
    dataset : bool
        Also write the dataset for a learned simulator (:mod:`fepr.sweep.dataset`); needs ``frames_every``.
    progress : bool
        One progress bar over all runs, with an ETA (on stderr).

    Returns
    -------
    pandas.DataFrame
        The index (:mod:`fepr.sweep.index`): one row per run, in the sweep's order. ``df.attrs["sweep"]`` says
        what this call did (plain data): ``name``, ``counts`` (runs, skipped, and per status), ``wall_s``,
        ``backend``, ``slots`` (runs at a time), ``startup_s`` (starting Ray), ``index`` and ``dataset`` (paths).

    Raises
    ------
    ConfigError
        For an invalid sweep file (naming the key), an invalid run (naming its parameters), or options that do not
        go together.
    MissingDependencyError
        Without pandas and pyarrow (the index), or Ray for ``backend="ray"`` or an ``address``.
    KeyboardInterrupt
        After writing the index and manifest of what finished, when the sweep is stopped.
    """
    require_pandas()
    spec = _spec_of(sweep, base_dir)
    if dataset and not spec.frames_every:
        raise ConfigError(f"{spec.source or 'the sweep'}: --dataset needs frames: set [sweep] frames_every = K")
    plans = plan_runs(spec)
    out = Path(out_dir).resolve()
    try:
        (out / "runs").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"cannot create the sweep folder {out}: {exc.strerror or exc}") from None
    from .. import __version__

    records: Dict[str, Dict[str, Any]] = {}
    for plan in plans:
        rec = _finished_record(out, plan)
        if rec is not None:
            records[plan.run_id] = dict(rec, skipped=True)
    todo = [p for p in plans if p.run_id not in records]

    t0 = time.perf_counter()
    executor = (
        make_executor(backend, retries=spec.retries, cpus_per_run=spec.cpus_per_run, address=address, workers=workers)
        if todo
        else None
    )
    name = executor.name if executor is not None else "none (every run had finished)"
    info: Dict[str, Any] = {
        "name": spec.name,
        "backend": name,
        "slots": executor.slots if executor is not None else 0,
        "startup_s": getattr(executor, "startup_s", 0.0),
        "dataset": None,
    }
    manifest: Dict[str, Any] = {
        "format": "fepr-sweep",
        "version": 1,
        "fepr": __version__,
        "status": "running",
        "sweep": spec.describe(),
        "backend": name,
        "address": address,
        "driver_host": socket.gethostname(),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "runs": [{"run_id": p.run_id, "params": p.params, "sample": p.sample} for p in plans],
    }
    _write_manifest(out, manifest)  # before any task: workers check that they see it (shared storage)
    tasks = [
        RunTask(
            run_id=p.run_id,
            run_dir=str(out / "runs" / p.run_id),
            sweep_dir=str(out),
            scene_text=p.scene_text(spec.name),
            params=p.params,
            steps=p.steps,
            frames_every=spec.frames_every,
            frame_velocities=spec.frame_velocities,
            checkpoint_every=spec.checkpoint_every,
            checkpoint_seconds=spec.checkpoint_seconds,
            threads=spec.cpus_per_run,
            fepr_version=__version__,
        )
        for p in todo
    ]
    bar = _progress_bar(len(plans), len(plans) - len(todo), spec.name, quiet=not progress)
    counts = {"failed": 0, "runaway": 0}

    def on_done(task: RunTask, record: Optional[dict], error: Optional[str]) -> None:
        if record is None:
            record = dict(read_status(Path(task.run_dir)) or {}, status="failed", error=error)
        records[task.run_id] = record
        if record.get("status") in counts:
            counts[record["status"]] += 1
        bar.set_postfix_str(", ".join(f"{v} {k}" for k, v in counts.items() if v), refresh=False)
        bar.update(1)

    stopped = False
    try:
        if executor is not None:
            executor.run(tasks, on_done)
    except KeyboardInterrupt:
        stopped = True
        raise
    finally:
        bar.close()
        if executor is not None:
            executor.close()
        info["wall_s"] = time.perf_counter() - t0
        df = build_index(plans, records, out)
        info["index"] = str(write_index(df, out))
        info["counts"] = {"runs": len(plans), "skipped": len(plans) - len(todo)}
        info["counts"].update({str(k): int(v) for k, v in df["status"].value_counts().items()})
        manifest.update(
            status="interrupted" if stopped else "complete",
            finished=time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            wall_s=info["wall_s"],
            counts=info["counts"],
            slots=info["slots"],
        )
        _write_manifest(out, manifest)
    if dataset:
        from .dataset import write_dataset

        seed = spec.seed if spec.split_seed is None else spec.split_seed
        info["dataset"] = str(write_dataset(out, split=spec.split, seed=seed))
    df.attrs["sweep"] = info
    return df


def _progress_bar(total: int, initial: int, name: str, quiet: bool):
    """One bar over all runs, with the rate and the ETA (tqdm, on stderr; the finished runs counted from the
    start, so the ETA is of the runs left)."""
    try:
        from tqdm.auto import tqdm
    except ImportError:  # tqdm is a dependency of fepr; without it, no bar
        return _NoBar()
    from ..cli.progress import DELAY_S

    return tqdm(
        total=total,
        initial=initial,
        desc=f"sweep {name}",
        unit="run",
        file=sys.stderr,
        dynamic_ncols=True,
        disable=quiet,
        smoothing=0.1,
        delay=DELAY_S,  # as every fepr bar: a sweep of a few seconds prints nothing
    )


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def set_postfix_str(self, s: str, refresh: bool = True) -> None:
        pass

    def close(self) -> None:
        pass
