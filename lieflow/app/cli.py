"""The ``lieflow`` command line.

Subcommands::

    lieflow list                      systems, schemes and solvers (plugins included)
    lieflow run CONFIG.toml           integrate a TOML configuration into an HDF5 file
            [--resume] [--out FILE] [--force] [--no-progress]
    lieflow salvage FILE.h5           rebuild a damaged trajectory file from every row
                                      that reads back (then run --resume)
    lieflow reproduce [STUDY]         the paper's experiments (default) or a published study
            [--out DIR] [--quick] [--seed N]  (modin-viviani-2020): figures, report.md,
            [--executor ...] [--workers N]    results.csv
            [--device DEV] [--smoke]
    lieflow plot FILE.h5 [--out DIR]  energy error, Casimir drift and iterations per step,
            [--movie OUT.mp4|OUT.gif] plus the figures a plugin registered for the system
                                      (and its movie of the saved states)
    lieflow sweep GRID.toml           every run of a grid (a product of parameter lists),
            [--executor local|dask] [--scheduler ADDRESS] [--workers N] [--out DIR]
            [--dry-run] [--no-progress]

:func:`main` returns the exit code: 0 on success, 2 for any lieflow error (the message, one
paragraph naming the problem and the fix, goes to stderr; no traceback), 130 when a run was
interrupted with Ctrl-C and 143 when it was stopped with SIGTERM (either way its file is
marked "interrupted" and can be continued with ``--resume``). ``python -m lieflow`` is the
same command.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shlex
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import FrameType
from typing import TextIO

from .. import __version__
from ..errors import InputError, LieflowError, shorten
from ..progress import ProgressBar, start_live, stop_live

__all__ = ["main"]

EXIT_OK = 0
EXIT_ERROR = 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143  # 128 + SIGTERM, what a shell reports for a process SIGTERM stopped
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE: what `cmd | head` gives for a Unix tool


class _Terminated:
    """Whether SIGTERM arrived while :func:`_sigterm_as_interrupt` was active."""

    received = False


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """Treat SIGTERM like Ctrl-C while the block runs: the SIGINT handler in force when the
    signal arrives (Python's, which raises KeyboardInterrupt, or one a run installed to
    stop at a safe point) is called, so the file is checkpointed and marked "interrupted"
    instead of the process dying with its file marked "running"."""
    if not hasattr(signal, "SIGTERM"):  # pragma: no cover
        yield
        return

    def on_term(signum: int, frame: FrameType | None) -> None:
        _Terminated.received = True
        handler = signal.getsignal(signal.SIGINT)
        if callable(handler):
            handler(signal.SIGINT, frame)
        else:
            raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, on_term)
    except ValueError:  # not the main thread: leave SIGTERM alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _cmd_list(args: argparse.Namespace) -> int:
    from ..plugins import KINDS, default_registry

    registry = default_registry()
    out: TextIO = sys.stdout
    kinds = KINDS if args.kind is None else (args.kind,)
    for i, kind in enumerate(kinds):
        table = registry.table(kind)
        if i:
            print(file=out)
        print(f"{kind}s:", file=out)
        width = max((len(name) for name in table), default=0)
        for name in sorted(table):
            entry = table[name]
            line = f"  {name:<{width}}  {entry.description}"
            if args.verbose:
                line += f"  [{entry.source}]"
            print(line.rstrip(), file=out)
    return EXIT_OK


def _show_progress(args: argparse.Namespace) -> bool:
    return not args.no_progress and sys.stderr.isatty()


def _cmd_run(args: argparse.Namespace) -> int:
    try:
        return _run_command(args)
    except KeyboardInterrupt:  # before the run had its file (once it has, run returns)
        how = "terminated (SIGTERM)" if _Terminated.received else "interrupted"
        print(
            f"lieflow: {how} before the run started: nothing was written"
            + (f"; continue with: {_resume_command(args)}" if args.resume else ""),
            file=sys.stderr,
        )
        return EXIT_TERMINATED if _Terminated.received else EXIT_INTERRUPTED


def _run_command(args: argparse.Namespace) -> int:
    from .config import ConfigError, build, load_config
    from .io import run

    config = load_config(args.config)
    setup = build(config, output=args.out, replace=args.force)
    if setup.output.exists() and not (args.resume or args.force):
        key = "--out" if args.out is not None else "[run] output"
        raise ConfigError(
            f"{config.source}: {key}: {str(setup.output)!r} already exists. To fix: pass "
            "--resume to continue it, --force to replace it, or choose another output.",
            key,
        )
    if args.resume and not setup.output.exists():  # --resume means "resume if present"
        print(f"lieflow: --resume: {str(setup.output)!r} does not exist yet; starting a new run",
              file=sys.stderr)  # fmt: skip
    summary = run(
        setup,
        resume=args.resume,
        monitor=ProgressBar() if _show_progress(args) else None,
    )
    rate = summary.new_steps / summary.wall_time if summary.wall_time > 0 else 0.0
    # with [splitting] flows (dissipation, forcing) the energy changes by design: its
    # relative change is the run's energy budget, not an error of the scheme
    energy = "energy change (not conserved: [splitting])" if setup.flows else "energy error"
    print(
        f"{summary.status}: {summary.completed_steps}/{summary.requested_steps} steps "
        f"({summary.new_steps} new, {summary.wall_time:.2f} s, {rate:,.0f} steps/s), "
        f"max {energy} {summary.max_energy_error:.3e} -> {summary.path}"
    )
    if summary.status == "interrupted":
        how = "terminated (SIGTERM)" if _Terminated.received else "interrupted"
        print(f"lieflow: {how}; continue with: {_resume_command(args)}", file=sys.stderr)
        return EXIT_TERMINATED if _Terminated.received else EXIT_INTERRUPTED
    return EXIT_OK


def _resume_command(args: argparse.Namespace) -> str:
    """The command that was run, as it continues the run: with ``--resume``, without
    ``--force`` (which would replace the file)."""
    argv = [a for a in args.argv if a != "--force"]
    if "--resume" not in argv:
        argv.append("--resume")
    return shlex.join(["lieflow", *argv])


def _cmd_salvage(args: argparse.Namespace) -> int:
    from .salvage import salvage

    print(salvage(args.file).describe())
    return EXIT_OK


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from .reproduce import reproduce_study

    def log(message: str) -> None:
        if not args.quiet:
            print(message, file=sys.stderr, flush=True)

    files = reproduce_study(args.study, args.out, quick=args.quick, smoke=args.smoke,
                            seed=args.seed, executor=args.executor, workers=args.workers,
                            scheduler=args.scheduler, device=args.device,
                            log=None if args.quiet else log)  # fmt: skip
    for path in files:
        print(path)
    return EXIT_OK


def _check_out_dir(out: Path | None, what: str) -> None:
    """Refuse an ``--out`` directory that is an existing file (or under one)."""
    if out is None:
        return
    for parent in (out, *out.parents):
        if parent.exists():
            if not parent.is_dir():
                raise InputError(
                    f"{what} --out {str(out)!r}: {str(parent)!r} is a file, not a directory. "
                    "To fix: give a directory (it is created if missing)."
                )
            return


def _cmd_plot(args: argparse.Namespace) -> int:
    from .plotting import plot_sweep, plot_trajectory

    _check_out_dir(args.out, "lieflow plot")
    sweep = args.file.is_dir() or args.file.name == "manifest.json"
    if sweep and args.movie is not None:
        raise InputError("lieflow plot: --movie needs a trajectory file, not a sweep directory")
    try:
        if sweep:
            written = plot_sweep(args.file if args.file.is_dir() else args.file.parent, args.out)
        else:
            written = plot_trajectory(args.file, args.out)
    except OSError as exc:  # reading errors are LieflowErrors already: this is writing
        where = args.out if args.out is not None else args.file.parent
        raise InputError(
            f"lieflow plot: cannot write the figures to {str(where)!r}: "
            f"{exc.strerror or exc}. To fix: give --out a directory you can write to."
        ) from None
    for path in written:
        print(path)
    if args.movie is not None:
        print(_plot_movie(args.file, args.movie, sys.stderr.isatty()))
    return EXIT_OK


def _plot_movie(file: Path, out: Path, live: bool) -> Path:
    """``lieflow plot FILE --movie OUT``: the ``movie(trajectory, path, progress)`` attribute
    of the plotter a plugin registered for the file's system, with a progress bar."""
    from ..plugins import default_registry
    from .io import read_trajectory

    traj = read_trajectory(file)
    system = str(traj.meta["system"])
    plotter = default_registry().plotters.get(system)
    movie = getattr(plotter.function, "movie", None) if plotter is not None else None
    if movie is None:
        raise InputError(
            f"lieflow plot --movie: no plugin draws movies of {system!r} runs ({str(file)!r}); "
            "movies come from a plotter with a 'movie' function (euler_zeitlin's: pip install "
            "lieflow-zeitlin[movie]). To fix: drop --movie."
        )
    if not live:
        return Path(movie(traj, out))
    from rich.console import Console
    from rich.progress import Progress

    bar = Progress(console=Console(stderr=True))
    task = bar.add_task("movie frames", total=None)
    start_live(bar)
    try:
        return Path(movie(traj, out, lambda done, total: bar.update(task, completed=done,
                                                                    total=total)))  # fmt: skip
    finally:
        stop_live(bar)


EXIT_RUNS_FAILED = 1  # lieflow sweep: it finished, but some runs failed (see the manifest)


def _cmd_sweep(args: argparse.Namespace) -> int:
    from .sweeps import SweepProgress, load_sweep, sweep

    if args.scheduler is not None and args.executor != "dask":
        raise InputError("--scheduler is the address of a Dask scheduler: add --executor dask")
    _check_out_dir(args.out, "lieflow sweep")
    grid = load_sweep(args.grid, directory=args.out)
    if args.dry_run:
        from .config import build
        from .sweeps import file_status

        for spec in grid.runs:
            build(spec.config, output=spec.output)
            shown = ", ".join(f"{k} = {v!r}" for k, v in spec.params.items())
            print(f"{file_status(spec):<18} {spec.id}  {shown}")
        print(f"{len(grid.runs)} runs ({' x '.join(map(str, grid.shape)) or '1'}) -> "
              f"{grid.directory}")  # fmt: skip
        return EXIT_OK
    result = sweep(grid, args.executor, workers=args.workers, scheduler=args.scheduler,
                   monitor=SweepProgress(live=_show_progress(args)),
                   store=args.store)  # fmt: skip
    c = result.counts
    print(
        f"sweep {grid.source}: {len(result.runs)} runs: {c['complete']} complete "
        f"({result.skipped} already), {c['failed']} failed"
        + (f", {c['interrupted'] + c['pending']} not finished" if result.interrupted else "")
        + f" in {result.wall_time:.1f} s -> {result.manifest}"
    )
    for rec in result.failed:
        error = str(rec.get("error", "")).strip().splitlines()
        print(f"  failed: {rec['output']}: {error[0] if error else ''}", file=sys.stderr)
    if result.interrupted:
        print(f"lieflow: sweep interrupted; run the same command again to continue: "
              f"{shlex.join(['lieflow', *args.argv])}", file=sys.stderr)  # fmt: skip
        return EXIT_TERMINATED if _Terminated.received else EXIT_INTERRUPTED
    return EXIT_OK if result.ok else EXIT_RUNS_FAILED


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lieflow",
        description="Structure-preserving integration of isospectral Lie-Poisson systems.",
    )
    parser.add_argument("--version", action="version", version=f"lieflow {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("list", help="list systems, schemes and solvers (plugins included)")
    p.add_argument("--kind", choices=("system", "scheme", "solver", "flow"), help="only this kind")
    p.add_argument("-v", "--verbose", action="store_true", help="show who registered each")
    p.set_defaults(func=_cmd_list)

    p = sub.add_parser(
        "run",
        help="integrate a TOML configuration, writing an HDF5 trajectory as it goes",
        description=(
            "Integrate the run described by CONFIG (TOML with [system], [initial], [scheme], "
            "optional [solver], and [run] tables; see examples/*.toml). The trajectory, "
            "diagnostics and a checkpoint are written to HDF5 at every save, so an "
            "interrupted run can be continued bit-for-bit with --resume. Paths inside CONFIG "
            "are relative to its directory; --out is relative to the current directory. "
            "A damaged output (a process killed while it wrote, a truncated copy, flipped "
            "bits) is refused by --resume; `lieflow salvage FILE` rebuilds it from every "
            "row that reads back, and --resume then continues it."
        ),
    )
    p.add_argument("config", type=Path, metavar="CONFIG.toml")
    p.add_argument("--resume", action="store_true",
                   help="continue the output file from its last checkpoint (a missing file is "
                        "started afresh, and said so)")  # fmt: skip
    p.add_argument("--out", type=Path, metavar="FILE", help="output file (overrides [run])")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser(
        "salvage",
        help="rebuild a damaged trajectory file from every row that reads back",
        description=(
            "Make a damaged trajectory file (refused by `lieflow run --resume` and the "
            "readers) resumable again: keep every row that reads back with verified "
            "checksums (a damaged chunk costs its own rows, at most 128 steps, left as NaN), "
            "repair what has a copy (initial/W0, header attributes, steps of saved states), "
            "restart from the latest verified checkpoint (resumed bit for bit) or saved "
            "state (resumed with a cold solver start), and mark the file interrupted; it "
            "prints what was lost and repaired. The damaged original is kept as "
            "FILE.damaged. Then continue it with `lieflow run CONFIG --resume`."
        ),
    )
    p.add_argument("file", type=Path, metavar="FILE.h5")
    p.set_defaults(func=_cmd_salvage)

    p = sub.add_parser(
        "reproduce",
        help="rerun the paper's experiments or a published study (figures, report.md, ...)",
        description=(
            "Rerun the paper's numerical experiments (STUDY = paper, the default: rigid body, "
            "Toda lattice, generalized rigid body with midpoint, sydirk7, gauss2, gauss3; "
            "energy-error figures, report.md with Tables 1-6 next to the published numbers, "
            "results.csv), or a published study: modin-viviani-2020 (2, 3 or 4 coherent "
            "vortices of 2D Euler on the sphere against gamma; an ensemble run as a sweep, "
            "written to DIR/modin-viviani-2020[-quick]/; resumable: run the same command "
            "again)."
        ),
    )
    p.add_argument("study", nargs="?", default="paper", metavar="STUDY",
                   help="paper (default) or modin-viviani-2020")  # fmt: skip
    p.add_argument("--out", type=Path, default=Path("lieflow-out"), metavar="DIR")
    p.add_argument("--quick", action="store_true",
                   help="paper: 10x fewer steps, GRB n = 10 only; modin-viviani-2020: the "
                        "laptop variant (N = 32, 32 runs, minutes on 2 cores)")  # fmt: skip
    p.add_argument("--smoke", action="store_true",
                   help="a study at toy size (seconds): checks the setup only")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="seed of the random data (default 0)")
    _executor_arguments(p, "a study's runs: ")
    p.add_argument("--device", default="cpu", metavar="DEV",
                   help="a study's [run] device: cpu (default), cupy, torch:cuda:0")  # fmt: skip
    p.add_argument("-q", "--quiet", action="store_true", help="no per-run log lines")
    p.set_defaults(func=_cmd_reproduce)

    p = sub.add_parser(
        "plot",
        help="plot the diagnostics of a trajectory file, or a sweep's convergence",
        description=(
            "Write PNGs of a trajectory file's energy error, Casimir drift and solver updates "
            "per step, then the figures a plugin registered for its system (for example "
            "vorticity snapshots of euler_zeitlin runs), and print their paths. Given a sweep "
            "directory (lieflow sweep), write its convergence (energy error against h, with "
            "the observed order) and work-precision figures."
        ),
    )
    p.add_argument("file", type=Path, metavar="FILE.h5|SWEEP_DIR")
    p.add_argument("--out", type=Path, metavar="DIR", help="output directory (default: FILE's)")
    p.add_argument(
        "--movie",
        type=Path,
        metavar="OUT.mp4|OUT.gif",
        help="also render the saved states as a movie (systems whose plugin draws movies)",
    )
    p.set_defaults(func=_cmd_plot)

    p = sub.add_parser(
        "sweep",
        help="run every run of a grid (a product of parameter lists) in parallel",
        description=(
            "Run the grid GRID: a run configuration plus a [sweep] table of lists over "
            'dotted keys ("run.h" = [0.1, 0.05]) and optional [[sweep.zip]] groups; their '
            "product defines the runs (docs: sweeps.md). Each run writes DIR/runs/<id>.h5, "
            "DIR/manifest.json lists them all. Running the same command again skips complete "
            "runs and resumes the others. Exit status: 0 when every run is complete, 1 when "
            "some failed (the others still ran), 2 on an error, 130/143 when interrupted."
        ),
    )
    p.add_argument("grid", type=Path, metavar="GRID.toml")
    _executor_arguments(p)
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="sweep directory (overrides [sweep] directory)")  # fmt: skip
    p.add_argument("--store", choices=("zarr",), default=None,
                   help="also write every run's results into one Zarr store, DIR/runs.zarr "
                        "(each worker its own runs), which lieflow.open_sweep reads")  # fmt: skip
    p.add_argument("--dry-run", action="store_true", help="check and list the runs only")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_sweep)
    return parser


def _executor_arguments(p: argparse.ArgumentParser, whose: str = "") -> None:
    """``--executor``, ``--scheduler``, ``--workers``: where the runs of a sweep go."""
    p.add_argument("--executor", choices=("local", "dask"), default="local",
                   help=f"{whose}local process pool (default) or Dask distributed")  # fmt: skip
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="address of a running Dask scheduler (with --executor dask)")  # fmt: skip
    p.add_argument("--workers", type=_positive_int, metavar="N",
                   help="processes of the local pool or LocalCluster (default: cores)")  # fmt: skip


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``lieflow`` command line with ``argv`` (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        0 on success, 2 on a lieflow error or bad usage, 130 after Ctrl-C, 143 after
        SIGTERM.
    """
    parser = _parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, usage errors
        return exc.code if isinstance(exc.code, int) else EXIT_ERROR
    func: Callable[[argparse.Namespace], int] = args.func
    args.argv = list(sys.argv[1:] if argv is None else argv)
    _Terminated.received = False
    try:
        with _sigterm_as_interrupt():  # for the whole command, before anything is created
            return func(args)
    except LieflowError as exc:
        print(f"lieflow: error: {shorten(exc, 4000)}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("lieflow: interrupted", file=sys.stderr)
        return EXIT_TERMINATED if _Terminated.received else EXIT_INTERRUPTED
    except (
        BrokenPipeError
    ):  # `lieflow list | head`: the reader left; stop quietly, as Unix tools do
        with contextlib.suppress(OSError):  # no second error when Python flushes stdout at exit
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except OSError as exc:  # a file system error no check foresaw (disk full, I/O error)
        print(
            f"lieflow: error: {exc}. To fix: check the disk and the paths given, then run "
            "again (an interrupted run continues with --resume).",
            file=sys.stderr,
        )
        return EXIT_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
