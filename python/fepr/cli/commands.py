"""The ``fepr`` command line.

Commands::

    fepr run SCENE.toml [--steps N] [--out DIR] [--no-projection] [--export FORMATS] [--export-every K]
             [--checkpoint-every K] [--overwrite] [--strict] [--quiet]
    fepr run [SCENE.toml] --resume DIR [--steps N] [--quiet]
    fepr demo [--steps N] [--out DIR] [--frames F] [--size WxH] [--no-video] [--strict] [--quiet]
    fepr compare SCENE.toml --out DIR [--integrators A,B] [--steps N] [--frames F] [--size WxH] [--fps FPS]
                 [--no-video] [--strict] [--quiet]
    fepr view SCENE.toml | MESH [--host ADDR] [--port P] [--integrator NAME] [--dt S] [--paused]
    fepr mesh INPUT [-o OUTPUT] [--max-volume V | --edge-length L | --target-tets N] [--max-tets M]
              [--quality Q] [--mesher M] [--info]
    fepr bench [--quick] [--json PATH] [--scenes LIST] [--threads N] [--meshes DIR] [--quiet]
    fepr sweep SWEEP.toml [--out DIR] [--address ADDR] [--backend auto|ray|pool|serial] [--workers N] [--dataset]
               [--strict] [--quiet]
    fepr --version | --help

Exit status: 0 success; 1 an output file could not be written; 2 invalid command line, scene or mesh;
3 the simulation ran away (the state became non-finite; the diagnostics up to that step are still written), or,
with ``--strict``, the run has a problem (:meth:`fepr.report.metrics.RunMetrics.problems`: a runaway, inverted
tets at the end, unconverged projections, unresolved energy above 1e-3 of the energy scale; for ``compare`` and
``demo``, in a run with FEPR); 130 and 143 ``fepr run`` stopped by SIGINT or SIGTERM (its work kept).

Every command prints the same summary (:mod:`fepr.report.metrics`): energy error against the books, unresolved
energy, P and L drift against the momentum targets, min J, inverted tets, unconverged projections, substeps.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
import warnings
from pathlib import Path
from typing import Optional, Sequence

from ..errors import ConfigError, FeprError
from ..sweep.cli import add_sweep_parser as _add_sweep_parser
from ..sweep.cli import cmd_sweep

__all__ = ["EXIT_ERROR", "EXIT_INVALID", "EXIT_OK", "EXIT_RUNAWAY", "EXIT_STRICT", "build_parser", "main"]

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_INVALID = 2
EXIT_RUNAWAY = 3
#: ``--strict`` and the run has a problem (the same status as a runaway, which is one).
EXIT_STRICT = 3

_STRICT_HELP = (
    "exit with status 3 when the run has a problem: a runaway, inverted tets at the end, unconverged "
    "projections, or unresolved energy above 1e-3 of the energy scale (tets inverted only during the run are "
    "reported but do not fail)"
)
_STRICT_FEPR_HELP = (
    "exit with status 3 when a run with FEPR has a problem: a runaway, inverted tets at the end, unconverged "
    "projections, or unresolved energy above 1e-3 of the energy scale (the runs without FEPR are not checked)"
)


def _version() -> str:
    try:
        from .. import __version__  # type: ignore[attr-defined]

        return str(__version__)
    except ImportError:
        pass
    try:
        from importlib.metadata import PackageNotFoundError, version

        return version("fepr")
    except (ImportError, PackageNotFoundError):
        return "unknown"


def _whole_number(unit: str, name: str, minimum: int):
    """An argparse type: a whole number of ``unit`` of at least ``minimum``; errors name ``name``."""

    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number of {unit}, got {text!r}") from None
        if n < minimum:
            raise argparse.ArgumentTypeError(f"{name} must be >= {minimum}, got {n}")
        return n

    return parse


_steps = _whole_number("steps", "steps", 0)
_every = _whole_number("steps", "--export-every", 1)
_frames = _whole_number("frames", "frames", 1)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``fepr`` command (subcommands ``run`` and ``demo``)."""
    parser = argparse.ArgumentParser(
        prog="fepr",
        description="FEPR: tetrahedral FEM with energy- and momentum-conserving projection.",
        epilog="Exit status: 0 ok, 1 write error, 2 invalid input, 3 runaway simulation (or, with --strict, a run "
        "with inverted tets at the end, unconverged projections or unresolved energy above 1e-3), 130/143 a run "
        "stopped by SIGINT/SIGTERM (its work kept: fepr run --resume DIR continues).",
    )
    parser.add_argument("--version", action="version", version=f"fepr {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    run = sub.add_parser(
        "run",
        help="run a scene file and write diagnostics.csv and final_state.npz",
        description="Run a scene file (TOML). Writes DIR/diagnostics.csv (one row per step plus the initial "
        "state; the totals for a scene with [[bodies]], plus DIR/diagnostics_<body>.csv per body) and "
        "DIR/final_state.npz, and prints a one-line summary: energy error against the books (H0 plus the energy "
        "budget), unresolved energy, P and L drift against the momentum targets (P0, L0 plus the external "
        "impulses), min J, inverted tets, unconverged projections, substeps, and the run's problems. Exit "
        "status 3: the run ran away, or with --strict it has a problem.",
    )
    run.add_argument(
        "scene", metavar="SCENE.toml", nargs="?", default=None, help="scene file (with --resume: the run's own)"
    )
    run.add_argument(
        "--steps",
        type=_steps,
        default=None,
        metavar="N",
        help="number of steps (default: [run] steps)",
    )
    run.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR",
        help="output folder (default: ./fepr-out/<scene stem>)",
    )
    run.add_argument(
        "--no-projection",
        action="store_true",
        help="turn FEPR off (base integrator only), whatever the scene says",
    )
    run.add_argument(
        "--export",
        default=None,
        metavar="FORMATS",
        help="also write the animation to DIR/export/ in these comma-separated formats: vtu (+ .pvd, ParaView), "
        "obj, ply, glb (Blender), usd (needs usd-core) (default: [export] formats)",
    )
    run.add_argument(
        "--export-every",
        type=_every,
        default=None,
        metavar="K",
        help="export every K-th step (default: [export] every, or 1)",
    )
    run.add_argument(
        "--checkpoint-every",
        type=_every,
        default=None,
        metavar="K",
        help="write a checkpoint to DIR/checkpoint every K steps, so that a crash or a kill loses at most K steps "
        "(fepr run --resume DIR continues, bit-identical to an uninterrupted run)",
    )
    run.add_argument(
        "--resume",
        type=Path,
        default=None,
        metavar="DIR",
        help="continue the run in DIR from its last checkpoint (written by --checkpoint-every or when the run "
        "was interrupted), with the settings it was started with",
    )
    run.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the files of an earlier run in the output folder (those its run.json lists)",
    )
    run.add_argument("--strict", action="store_true", help=_STRICT_HELP)
    run.add_argument("--quiet", "-q", action="store_true", help="print only the final summary line")

    demo = sub.add_parser(
        "demo",
        help="the showcase: built-in scenes with and without FEPR, plots, videos and an HTML report",
        description="Run the built-in gallery (builtin meshes, no files needed), each scene with and without "
        "FEPR (backward Euler and Projective Dynamics too), write plots, side-by-side videos, summaries and "
        "report.html under DIR (default ./fepr-demo), and print a table of conservation errors, iterations and "
        "timings.",
    )
    demo.add_argument(
        "--steps",
        type=_steps,
        default=None,
        metavar="N",
        help="steps per run (default: each scene's own)",
    )
    demo.add_argument("--out", type=Path, default=None, metavar="DIR", help="output folder (default ./fepr-demo)")
    demo.add_argument("--quiet", "-q", action="store_true", help="print only the table")
    demo.add_argument("--frames", type=_frames, default=None, metavar="F", help="video frames per scene (default 30)")
    demo.add_argument("--size", default=None, metavar="WxH", help="video panel size in pixels (default 480x352)")
    demo.add_argument("--no-video", action="store_true", help="skip the videos (plots, summaries and report only)")
    demo.add_argument("--strict", action="store_true", help=_STRICT_FEPR_HELP)
    _add_mesh_parser(sub)
    _add_compare_parser(sub)
    _add_view_parser(sub)
    _add_sweep_parser(sub)
    # Imported here, not at the top: `python -m fepr.cli.bench` (the bench's worker subprocess) imports this
    # package first, and a bench module already imported would run twice (runpy warns).
    from .bench import add_bench_parser

    add_bench_parser(sub)
    return parser


def _add_compare_parser(sub) -> None:
    cmp = sub.add_parser(
        "compare",
        help="run a scene with and without FEPR (and several integrators): plots, video, summary, report",
        description="Run SCENE with and without the projection, for each listed integrator, and write to DIR: "
        "energy.png, momentum.png, side_by_side.mp4/.gif (off-screen, polyscope on EGL), summary.md, "
        "summary.json, report.html, and each run's diagnostics.csv. Needs the compare extra: "
        'pip install "fepr[compare]".',
    )
    cmp.add_argument("scene", metavar="SCENE.toml", help="scene file")
    cmp.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    cmp.add_argument(
        "--integrators",
        default=None,
        metavar="A,B",
        help="comma-separated base integrators to compare (default: the scene's own)",
    )
    cmp.add_argument("--steps", type=_steps, default=None, metavar="N", help="steps (default: [run] steps)")
    cmp.add_argument("--frames", type=_frames, default=48, metavar="F", help="video frames (default 48)")
    cmp.add_argument("--size", default="640x480", metavar="WxH", help="panel size in pixels (default 640x480)")
    cmp.add_argument("--fps", type=_positive_float, default=24.0, help="video frame rate (default 24)")
    cmp.add_argument("--no-video", action="store_true", help="skip the videos")
    cmp.add_argument("--strict", action="store_true", help=_STRICT_FEPR_HELP)
    cmp.add_argument("--quiet", "-q", action="store_true", help="no progress bars; print only the summary line")


def _add_view_parser(sub) -> None:
    view = sub.add_parser(
        "view",
        help="interactive viewer in the browser (viser)",
        description="Serve an interactive viewer of a scene file or a mesh (builtin meshes: ell, box, sphere, "
        "cylinder) on http://HOST:PORT and print its URL: play, pause, step, reset, projection on/off, "
        "integrator and dt, live energy and momentum plots, colour by J or energy density, drag a vertex. "
        'Needs the view extra: pip install "fepr[view]". Ctrl-C stops it.',
    )
    view.add_argument("target", metavar="SCENE.toml | MESH", help="scene file, mesh file or builtin mesh name")
    view.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1, this machine only)")
    view.add_argument("--port", type=int, default=8080, help="port (default 8080; 0 picks a free one)")
    view.add_argument("--integrator", default=None, help="base integrator at start (default: the scene's own)")
    view.add_argument("--dt", type=_positive_float, default=None, help="time step at start, s")
    view.add_argument("--paused", action="store_true", help="start paused")
    view.add_argument("--max-seconds", type=_positive_float, default=None, help=argparse.SUPPRESS)


def _positive_float(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (x > 0 and x < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return x


def _add_mesh_parser(sub) -> None:
    mesh = sub.add_parser(
        "mesh",
        help="tetrahedralize a surface, convert a tet mesh, or print a mesh report",
        description="Tetrahedralize a surface (.obj, .off, .stl, .ply) or convert a tet mesh, writing OUTPUT "
        "(.msh, .vtu, .vtk, .mesh, .meshb, .npz, .node/.ele); with --info print a report of INPUT (or of "
        'OUTPUT when -o is given). Tetrahedralizing needs the mesh extra: pip install "fepr[mesh]".',
    )
    mesh.add_argument("input", metavar="INPUT", help="surface or tet mesh file (a TetGen basename works too)")
    mesh.add_argument("-o", "--output", type=Path, default=None, metavar="OUTPUT", help="file to write")
    size = mesh.add_mutually_exclusive_group()
    size.add_argument(
        "--max-volume", type=_positive_float, default=None, metavar="V", help="largest tet volume (input units^3)"
    )
    size.add_argument(
        "--edge-length", type=_positive_float, default=None, metavar="L", help="target edge length (input units)"
    )
    size.add_argument(
        "--target-tets",
        type=_whole_number("tets", "--target-tets", 1),
        default=None,
        metavar="N",
        help="aim at about N tets (within 10%%): decimate the surface first (quadric, fast-simplification), then "
        "choose TetGen's volume bound by measuring",
    )
    mesh.add_argument(
        "--max-tets",
        type=_whole_number("tets", "--max-tets", 1),
        default=None,
        metavar="M",
        help="hard upper bound on the tet count: never written above it (with --target-tets the passes retry "
        "below it; without, a larger mesh is refused)",
    )
    mesh.add_argument(
        "--quality",
        type=_positive_float,
        default=None,
        metavar="Q",
        help="TetGen radius-edge ratio bound, > 1 (default 2.0; smaller: better shaped, more tets)",
    )
    mesh.add_argument(
        "--mesher", choices=("tetgen", "ftetwild"), default="tetgen", help="mesher for surfaces (default tetgen)"
    )
    mesh.add_argument("--info", action="store_true", help="print the mesh report (counts, volume, quality, ...)")


def _err(msg: str) -> None:
    print(f"fepr: {msg}", file=sys.stderr, flush=True)


def _cmd_run(args: argparse.Namespace) -> int:
    from ..report.metrics import RunProblemWarning
    from ..scene import StopRequest, load_scene, run_scene
    from .progress import progress_bar

    if args.resume is not None:
        if args.out is not None and Path(args.out).resolve() != Path(args.resume).resolve():
            raise ConfigError("--resume DIR continues the run in DIR: give no other --out")
        if args.overwrite:
            raise ConfigError("--resume continues a run, --overwrite replaces one: give one of them")
        out = Path(args.resume)
        scene = load_scene(args.scene if args.scene is not None else _resumed_scene_path(out))
    else:
        if args.scene is None:
            raise ConfigError("fepr run: give a scene file (or --resume DIR to continue a run)")
        scene = load_scene(args.scene)
        out = args.out if args.out is not None else Path("fepr-out") / Path(args.scene).stem
    projection = False if args.no_projection else None
    bars: list = []  # the progress bar, made with the header at the first call

    def progress(done: int, total: int, sim) -> None:
        if args.quiet:
            return
        if not bars:  # the first call, before the first step: the header, then the bar (steps, rate, ETA)
            proj = "off" if (args.no_projection or not scene.projection.enabled) else "on"
            bodies = f"{len(scene.bodies)} bodies, " if scene.is_multibody else ""
            what = f"resuming at step {done} of {total}" if args.resume is not None else f"{total} steps"
            print(
                f"fepr run {scene.name}: {bodies}{len(sim.rest_positions)} vertices, {len(sim.tets)} tets, "
                f"{scene.integrator.name} dt={scene.integrator.dt:.6g} s, FEPR {proj}, {what} -> {out}",
                flush=True,
            )
            bars.append(progress_bar(total, desc=scene.name, unit="step", leave=False))
            bars[0].update(done)
            return
        bar = bars[0]
        bar.set_postfix_str(f"t={float(sim.time):.4g} s", refresh=False)
        bar.update(done - bar.n)

    stop = StopRequest().install()
    try:
        with warnings.catch_warnings():
            # the end-of-run warning is in result.warnings, printed below with the others
            warnings.simplefilter("ignore", RunProblemWarning)
            result = run_scene(
                scene,
                steps=args.steps,
                out_dir=out,
                projection=projection,
                progress=progress,
                export=args.export,
                export_every=args.export_every,
                checkpoint_every=args.checkpoint_every,
                overwrite=args.overwrite,
                resume=args.resume is not None,
                stop=stop,
            )
    finally:
        stop.restore()
        for bar in bars:
            bar.close()
    if not args.quiet:
        for w in result.warnings:
            _err(f"warning: {w}")
    if result.runaway:
        _err(f"runaway at step {result.runaway_step}: {result.runaway_message}")
    print(result.summary(), flush=True)
    if result.interrupted is not None:
        sig = signal.Signals(result.interrupted)
        kept = [p.name for p in (result.diagnostics_path, result.state_path) if p is not None]
        if result.export_dir is not None:
            kept.append(f"{result.export_frames} exported frames")
        _err(
            f"{sig.name}: stopped at step {result.steps_completed + (result.resumed_from or 0)} "
            f"(t = {float(result.simulation.time):.6g} s); kept {', '.join(kept)} and a checkpoint in {out}: "
            f"fepr run --resume {out} continues"
        )
        return 128 + int(sig)
    if not args.quiet:
        print(f"wrote {result.diagnostics_path} and {result.state_path}", flush=True)
        if result.body_diagnostics_paths:
            names = ", ".join(p.name for p in result.body_diagnostics_paths.values())
            print(f"wrote per-body diagnostics {names}", flush=True)
        if result.export_dir is not None:
            print(
                f"exported {result.export_frames} frames ({', '.join(result.export_formats)}), "
                f"{result.export_fps:.6g} frames per simulated second, to {result.export_dir}",
                flush=True,
            )
    if result.runaway:
        return EXIT_RUNAWAY
    if args.strict and result.problems:
        _err(f"--strict: {'; '.join(result.problems)}")
        return EXIT_STRICT
    return EXIT_OK


def _resumed_scene_path(out: Path) -> Path:
    """The scene file of the run in ``out`` (from its manifest), unchanged since the run started."""
    import hashlib
    import json

    manifest = out / "run.json"
    try:
        entry = json.loads(manifest.read_text(encoding="utf-8")).get("scene", {})
    except (OSError, ValueError) as exc:
        raise ConfigError(f"--resume {out}: cannot read {manifest} ({exc})") from None
    path = entry.get("path")
    if not path:
        raise ConfigError(f"--resume {out}: the manifest names no scene file; give it: fepr run SCENE.toml --resume")
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"--resume {out}: the run's scene file {p} is gone; give it: fepr run SCENE.toml --resume")
    if entry.get("sha256") and hashlib.sha256(p.read_bytes()).hexdigest() != entry["sha256"]:
        raise ConfigError(f"--resume {out}: the scene file {p} changed since the run started")
    return p


def _cmd_mesh(args: argparse.Namespace) -> int:
    from ..errors import ConfigError
    from ..io import SURFACE_EXTENSIONS, load_mesh, write_mesh
    from ..mesh_report import mesh_info

    src = Path(args.input)
    surface = src.suffix.lower() in SURFACE_EXTENSIONS
    options = "--max-volume, --edge-length, --target-tets, --max-tets and --quality"
    sizing = any(
        x is not None for x in (args.max_volume, args.edge_length, args.target_tets, args.max_tets, args.quality)
    )
    if args.output is None:
        if not args.info:
            raise ConfigError("fepr mesh: give -o OUTPUT (a file to write) and/or --info (print a report)")
        if sizing:
            raise ConfigError(f"fepr mesh: {options} need -o OUTPUT")
        print(mesh_info(src), flush=True)
        return EXIT_OK
    # Before any reading or meshing (which can take a while on a dense scan): a wrong -o fails at once.
    _check_mesh_output(args.output)
    if args.target_tets is not None and args.max_tets is not None and args.max_tets < args.target_tets:
        raise ConfigError(f"fepr mesh: --max-tets ({args.max_tets}) must be >= --target-tets ({args.target_tets})")
    if args.target_tets is not None and args.mesher != "tetgen":
        raise ConfigError(f"fepr mesh: --target-tets works with --mesher tetgen only, not {args.mesher}")
    if surface:
        from ..mesher import tetrahedralize, tetrahedralize_to_size

        start = time.perf_counter()
        sized = None
        caught: list = []
        if args.target_tets is not None:
            with warnings.catch_warnings(record=True) as caught:  # printed as fepr's own warnings below
                warnings.simplefilter("always", UserWarning)
                sized = tetrahedralize_to_size(
                    src, target_tets=args.target_tets, max_tets=args.max_tets, quality=args.quality
                )
            mesh = sized.mesh
        else:
            mesh = tetrahedralize(
                src,
                max_volume=args.max_volume,
                edge_length=args.edge_length,
                quality=args.quality,
                mesher=args.mesher,
                max_tets=args.max_tets,
            )
        elapsed = time.perf_counter() - start
        print(f"{src}: {mesh.num_vertices} vertices, {mesh.num_tets} tets ({args.mesher}, {elapsed:.2f} s)", flush=True)
        if sized is not None:
            print(f"{src}: {sized}", flush=True)
        for w in caught:
            _err(f"warning: {w.message}")
    else:
        if sizing:
            raise ConfigError(
                f"fepr mesh: {src} is a tet mesh; {options} apply to surfaces ({', '.join(SURFACE_EXTENSIONS)})"
            )
        mesh = load_mesh(src)
    written = write_mesh(mesh, args.output)
    print("wrote " + ", ".join(str(w) for w in written), flush=True)
    if args.info:
        print(mesh_info(written[0]), flush=True)
    return EXIT_OK


def _check_mesh_output(out: Path) -> None:
    """Refuse an OUTPUT that :func:`fepr.io.write_mesh` could not write (extension, missing folder)."""
    from ..errors import ConfigError
    from ..io import WRITE_EXTENSIONS

    if out.suffix.lower() not in WRITE_EXTENSIONS:
        what = f"extension {out.suffix!r}" if out.suffix else "no extension"
        raise ConfigError(
            f"fepr mesh: cannot write {out}: {what} is not a tet mesh format; supported: {', '.join(WRITE_EXTENSIONS)}"
        )
    folder = out.parent
    if not folder.is_dir():
        raise ConfigError(f"fepr mesh: cannot write {out}: the folder {folder} does not exist")


def _cmd_demo(args: argparse.Namespace) -> int:
    from . import demo
    from .compare import parse_size

    size = demo.DEMO_SIZE if args.size is None else parse_size(args.size)
    frames = demo.DEMO_FRAMES if args.frames is None else args.frames
    return demo.main(
        steps=args.steps,
        out_dir=args.out,
        quiet=args.quiet,
        frames=frames,
        size=size,
        video=not args.no_video,
        strict=args.strict,
    )


def _cmd_compare(args: argparse.Namespace) -> int:
    from ..errors import ConfigError
    from ..report.runs import parse_integrators
    from ..scene import load_scene
    from .compare import compare, parse_size

    size = parse_size(args.size)
    if not Path(args.scene).is_file():
        raise ConfigError(f"scene file not found: {args.scene}")
    scene = load_scene(args.scene)
    integrators = parse_integrators(args.integrators, scene.integrator.name)
    result = compare(
        scene,
        args.out,
        integrators=integrators,
        steps=args.steps,
        frames=args.frames,
        size=size,
        fps=args.fps,
        video=not args.no_video,
        quiet=args.quiet,
    )
    for note in (result.video_error, result.plot_error):
        if note:
            _err(f"note: {note}")
    if not args.quiet:
        for line in result.run_lines():
            print(f"  {line}", flush=True)
    print(f"fepr compare {result.summary_line()}", flush=True)
    problems = result.problems()
    if args.strict and problems:
        _err(f"--strict: {'; '.join(problems)}")
        return EXIT_STRICT
    return EXIT_OK


def _cmd_view(args: argparse.Namespace) -> int:
    from ..viewer import serve_target

    return serve_target(
        args.target,
        host=args.host,
        port=args.port,
        integrator=args.integrator,
        dt=args.dt,
        paused=args.paused,
        max_seconds=args.max_seconds,
    )


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the ``fepr`` command with ``argv`` (default: ``sys.argv[1:]``); returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(None if argv is None else list(argv))
    except SystemExit as exc:  # --help, --version, usage errors
        code = exc.code
        return code if isinstance(code, int) else (EXIT_OK if code is None else EXIT_INVALID)
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_INVALID
    try:
        if args.command == "run":
            return _cmd_run(args)
        if args.command == "mesh":
            return _cmd_mesh(args)
        if args.command == "compare":
            return _cmd_compare(args)
        if args.command == "view":
            return _cmd_view(args)
        if args.command == "sweep":
            return cmd_sweep(args)
        if args.command == "bench":
            from .bench import cmd_bench

            return cmd_bench(args)
        return _cmd_demo(args)
    except FeprError as exc:
        _err(f"error: {exc}")
        return EXIT_INVALID
    except OSError as exc:
        _err(f"error: {exc}")
        return EXIT_ERROR
    except KeyboardInterrupt:
        _err("interrupted")
        return 130
