"""Where a sweep's runs execute: Ray tasks, a local process pool, or one after another in this process.

Every executor runs :func:`fepr.sweep.runner.run_one` on each :class:`~fepr.sweep.runner.RunTask` and calls
``on_done(task, record, error)`` in the driver as each run ends (``record`` the run's ``status.json``, or
``None`` and ``error`` a message when the run failed after its retries). The outputs are the same whichever runs
them: a run's results do not depend on the process, the machine or the thread count.

- :class:`RayExecutor`: each run is a Ray task with ``num_cpus = cpus_per_run`` (its simulation gets as many
  threads), ``max_retries = retries`` (a worker process or node that dies) and ``retry_exceptions`` (a run that
  raised); a retried run continues from its last checkpoint. Without an address it starts a local Ray instance
  with the machine's cores and stops it at the end (an instance this process already started is used and left
  running); ``address="auto"`` or ``"ray://host:port"`` joins an existing cluster.
- :class:`PoolExecutor`: ``concurrent.futures.ProcessPoolExecutor`` (spawned processes, so no state of the driver
  leaks in), ``cores // cpus_per_run`` processes. A run that raised, or whose process died (the pool is then
  started again), is submitted again up to ``retries`` times; what counts is the attempts the run itself recorded
  in ``status.json``, so runs that only waited in the queue are not charged.
- :class:`SerialExecutor`: in this process, one run at a time (debugging; the reference for the others).
"""

from __future__ import annotations

import os
import socket
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

from ..errors import ConfigError, MissingDependencyError
from .runner import RunTask, read_status, run_one

__all__ = ["BACKENDS", "PoolExecutor", "RayExecutor", "SerialExecutor", "available_cores", "make_executor"]

BACKENDS = ("auto", "ray", "pool", "serial")

OnDone = Callable[[RunTask, Optional[dict], Optional[str]], None]


def available_cores() -> int:
    """CPUs this process may use (its affinity mask, which container limits set), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _disk_attempts(task: RunTask) -> int:
    st = read_status(Path(task.run_dir)) or {}
    return int(st.get("attempts", 0)) if st.get("run_id") == task.run_id else 0


def _error_text(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".strip()


class SerialExecutor:
    """Runs in this process, one after another, each retried up to ``retries`` times."""

    name = "serial"

    def __init__(self, retries: int, cpus_per_run: int):
        self.retries, self.cpus_per_run, self.slots = retries, cpus_per_run, 1

    def run(self, tasks: Sequence[RunTask], on_done: OnDone) -> None:
        for task in tasks:
            for attempt in range(self.retries + 1):
                try:
                    on_done(task, run_one(task), None)
                    break
                except Exception as exc:
                    if attempt == self.retries:
                        on_done(task, None, f"{_error_text(exc)} (after {attempt + 1} attempts)")

    def close(self) -> None:
        pass


def _pool_worker_init() -> None:
    # The simulation's threads come from the task; keep libraries that read these from starting more.
    os.environ.setdefault("OMP_NUM_THREADS", "1")


class PoolExecutor:
    """A local process pool of ``workers`` processes (default ``cores // cpus_per_run``)."""

    name = "pool"

    def __init__(self, retries: int, cpus_per_run: int, workers: Optional[int] = None):
        self.retries, self.cpus_per_run = retries, cpus_per_run
        self.slots = workers if workers is not None else max(1, available_cores() // cpus_per_run)
        self._pool: Optional[ProcessPoolExecutor] = None

    def _new_pool(self) -> ProcessPoolExecutor:
        import multiprocessing

        return ProcessPoolExecutor(
            max_workers=self.slots, mp_context=multiprocessing.get_context("spawn"), initializer=_pool_worker_init
        )

    def run(self, tasks: Sequence[RunTask], on_done: OnDone) -> None:
        base = {t.run_id: _disk_attempts(t) for t in tasks}
        submitted = {t.run_id: 0 for t in tasks}
        queue: List[RunTask] = list(tasks)
        running: Dict = {}

        def retry_or_fail(task: RunTask, error: str, broken: bool) -> None:
            # The attempts the run recorded itself; a run that raised before recording counts its submissions,
            # and a run that only waited in a pool that broke is not charged (up to a bound on resubmissions).
            tried = _disk_attempts(task) - base[task.run_id]
            if not broken:
                tried = max(tried, submitted[task.run_id])
            if tried > self.retries or submitted[task.run_id] > 3 * (self.retries + 1):
                on_done(task, None, f"{error} (after {max(tried, 1)} attempts)")
            else:
                queue.insert(0, task)

        self._pool = self._new_pool()
        breaks, progress = 0, False
        try:
            while queue or running:
                while queue and len(running) < 2 * self.slots:  # a short queue: a broken pool loses little
                    task = queue.pop(0)
                    submitted[task.run_id] += 1
                    running[self._pool.submit(run_one, task)] = task
                finished, _ = wait(list(running), timeout=1.0, return_when=FIRST_COMPLETED)
                broken = False
                for fut in finished:
                    task = running.pop(fut)
                    try:
                        record = fut.result()
                    except BrokenProcessPool:
                        broken = True
                        retry_or_fail(task, "its worker process died", True)
                    except Exception as exc:
                        retry_or_fail(task, _error_text(exc), False)
                    else:
                        progress = True
                        on_done(task, record, None)
                if broken:
                    breaks += 1
                    progress = progress or any(_disk_attempts(t) > base[t.run_id] for t in tasks)
                    if breaks >= 2 and not progress:
                        raise RuntimeError(
                            "the local pool's worker processes die before they run anything; if fepr.sweep is "
                            'called from a script, put the call under `if __name__ == "__main__":` (the pool '
                            "starts its processes by importing the script, as multiprocessing does)"
                        )
                    # Every run of a broken pool fails with it: the rest go back into the queue of a new pool.
                    for fut, task in list(running.items()):
                        running.pop(fut)
                        retry_or_fail(task, "its worker process died", True)
                    self._pool.shutdown(wait=False, cancel_futures=True)
                    self._pool = self._new_pool()
        finally:
            self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None


class RayExecutor:
    """Ray tasks on a local instance (started here, stopped at the end) or an existing cluster (``address``)."""

    name = "ray"

    def __init__(self, retries: int, cpus_per_run: int, address: Optional[str] = None):
        try:
            import ray
        except ImportError:
            raise MissingDependencyError(
                'fepr sweep on Ray needs the sweep extra: pip install "fepr[sweep]" (or use the local pool: '
                "--backend pool)"
            ) from None
        self.ray = ray
        self.retries, self.cpus_per_run, self.address = retries, cpus_per_run, address
        self.started_here = False
        self.connected_here = False
        self.startup_s = 0.0
        t0 = time.perf_counter()
        if ray.is_initialized():
            pass  # an instance this process joined already: use it, leave it running
        elif address is None:
            import logging

            ray.init(
                address="local",  # a new instance, even when this machine has a cluster (or a stale record of one)
                num_cpus=available_cores(),
                include_dashboard=False,
                logging_level=logging.ERROR,
                log_to_driver=False,
            )
            self.started_here = True
        else:
            import logging

            _check_reachable(address)
            try:
                ray.init(address=address, logging_level=logging.ERROR, log_to_driver=False)
            except ConnectionError as exc:
                raise ConfigError(f"--address {address}: cannot join the Ray cluster ({exc})") from None
            self.connected_here = True
        self.startup_s = time.perf_counter() - t0
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self.slots = max(1, cpus // cpus_per_run)
        self.cluster_cpus = cpus

    def run(self, tasks: Sequence[RunTask], on_done: OnDone) -> None:
        ray = self.ray
        remote = ray.remote(run_one)
        opts = {"num_cpus": self.cpus_per_run, "max_retries": self.retries, "retry_exceptions": True}
        refs = {remote.options(name=f"fepr-sweep-{t.run_id}", **opts).remote(t): t for t in tasks}
        pending = list(refs)
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1, timeout=1.0)
                for ref in ready:
                    task = refs.pop(ref)
                    try:
                        on_done(task, ray.get(ref), None)
                    except ray.exceptions.RayTaskError as exc:
                        cause = getattr(exc, "cause", None) or exc
                        on_done(task, None, f"{_error_text(cause)} (after {self.retries + 1} attempts)")
                    except ray.exceptions.RayError as exc:
                        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                        on_done(task, None, f"{type(exc).__name__}: {first} (after {self.retries + 1} attempts)")
        except BaseException:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise

    def close(self) -> None:
        if self.started_here or self.connected_here:
            self.ray.shutdown()
            self.started_here = self.connected_here = False


def _check_reachable(address: str) -> None:
    """Fail at once, naming the address, when nothing answers there (Ray itself would retry for minutes)."""
    if address == "auto":
        return  # Ray finds the cluster this machine belongs to, or says there is none
    host, _, port = address.split("://", 1)[-1].rpartition(":")
    if not port.isdigit() or not host:
        raise ConfigError(f"--address {address}: expected auto, HOST:PORT (the head's GCS) or ray://HOST:PORT")
    try:
        socket.create_connection((host, int(port)), timeout=5.0).close()
    except OSError as exc:
        raise ConfigError(
            f"--address {address}: nothing answers at {host}:{port} ({exc.strerror or exc}); start the cluster's "
            "head with `ray start --head` (docs/sweeps.md)"
        ) from None


def make_executor(backend: str, *, retries: int, cpus_per_run: int, address: Optional[str], workers: Optional[int]):
    """The executor for ``backend`` (``auto``: Ray if it is installed, else the local pool; an ``address`` needs
    Ray)."""
    if backend not in BACKENDS:
        raise ConfigError(f"backend must be one of {', '.join(BACKENDS)}; got {backend!r}")
    if address is not None and backend in ("pool", "serial"):
        raise ConfigError(f"--address joins a Ray cluster; it does not go with backend {backend!r}")
    if backend == "auto":
        try:
            import ray  # noqa: F401
        except ImportError:
            if address is not None:
                raise MissingDependencyError(f'--address {address} needs Ray: pip install "fepr[sweep]"') from None
            backend = "pool"
        else:
            backend = "ray"
    if backend == "ray":
        if workers is not None:
            raise ConfigError("--workers sizes the local pool; Ray runs as many runs as the cluster has CPUs for")
        return RayExecutor(retries, cpus_per_run, address)
    if backend == "pool":
        return PoolExecutor(retries, cpus_per_run, workers)
    return SerialExecutor(retries, cpus_per_run)
