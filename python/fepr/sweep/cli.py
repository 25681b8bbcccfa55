"""``fepr sweep``: the command-line face of :func:`fepr.sweep.run_sweep`.

::

    fepr sweep SWEEP.toml [--out DIR] [--address auto|HOST:PORT|ray://HOST:PORT] [--backend auto|ray|pool|serial]
               [--workers N] [--dataset] [--strict] [--quiet]

Exit status: 0 every run finished (complete, or ran away: a result of the parameters); 3 some runs failed after
their retries (the index says why), or with ``--strict`` some ran away or have a problem
(:meth:`fepr.report.metrics.RunMetrics.problems`); 2 an invalid sweep file; 130 stopped by Ctrl-C (what finished
is kept, and running the same command again continues).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["add_sweep_parser", "cmd_sweep"]


def _positive(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {n}")
    return n


def add_sweep_parser(sub) -> None:
    """Add the ``sweep`` subcommand to the ``fepr`` parser's subparsers."""
    p = sub.add_parser(
        "sweep",
        help="many runs of a scene: a parameter grid and random samples, on Ray or a local process pool",
        description="Run every run of a sweep file (a base scene, parameters on a grid and/or seeded random "
        "samples) into DIR/runs/<id>/ (scene.toml, diagnostics.csv, final_state.npz, frames as .npy), and write "
        "DIR/index.parquet (one row per run: parameters, status, summary metrics) and DIR/sweep.json. Runs that "
        "finished before are skipped; unfinished ones continue from their checkpoints. With Ray installed "
        '(pip install "fepr[sweep]") runs are Ray tasks on a local instance, or on a cluster with --address; '
        "without it, a local process pool. See docs/sweeps.md.",
    )
    p.add_argument("sweep", metavar="SWEEP.toml", help="sweep file")
    p.add_argument("--out", type=Path, default=None, metavar="DIR", help="sweep folder (default ./fepr-sweep/<stem>)")
    p.add_argument(
        "--address",
        default=None,
        metavar="ADDR",
        help="join a running Ray cluster: 'auto' (this machine is a node of it), HOST:PORT (the head) or "
        "ray://HOST:PORT (Ray Client); default: a new local Ray instance with this machine's cores, stopped at the end",
    )
    p.add_argument(
        "--backend",
        choices=("auto", "ray", "pool", "serial"),
        default="auto",
        help="where the runs execute (default auto: Ray if installed, else a local process pool)",
    )
    p.add_argument("--workers", type=_positive, default=None, metavar="N", help="processes of the local pool")
    p.add_argument(
        "--dataset",
        action="store_true",
        help="also write DIR/dataset: one (frames, m, 3) .npy per trajectory, the meshes, metadata.csv and a "
        "train/validation/test split ([dataset] in the sweep file); needs [sweep] frames_every",
    )
    p.add_argument("--strict", action="store_true", help="exit with status 3 when a run ran away or has a problem, too")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar; print only the summary line")


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run ``fepr sweep`` with parsed arguments; returns the exit status."""
    from .driver import run_sweep, summary_line

    out = args.out if args.out is not None else Path("fepr-sweep") / Path(args.sweep).stem
    try:
        df = run_sweep(
            args.sweep,
            out,
            backend=args.backend,
            address=args.address,
            workers=args.workers,
            dataset=args.dataset,
            progress=not args.quiet,
        )
    except KeyboardInterrupt:
        print(
            f"fepr: interrupted; what finished is in {out}/index.parquet, and `fepr sweep {args.sweep} --out {out}` "
            "continues",
            file=sys.stderr,
            flush=True,
        )
        return 130
    info = df.attrs["sweep"]
    print(summary_line(info), flush=True)
    failed = df[df["status"] == "failed"]
    for r in failed.head(5).itertuples():
        print(f"fepr: run {r.run_id} failed: {r.error}", file=sys.stderr, flush=True)
    if len(failed) > 5:
        print(f"fepr: ... and {len(failed) - 5} more failed runs (see the index)", file=sys.stderr, flush=True)
    if info.get("dataset") and not args.quiet:
        print(f"wrote the dataset to {info['dataset']}", flush=True)
    if len(failed):
        return 3
    if args.strict:
        bad = df[(df["status"] != "complete") | (df["problems"] != "")]
        if len(bad):
            print(f"fepr: --strict: {len(bad)} runs ran away or have problems (see the index)", file=sys.stderr)
            return 3
    return 0
