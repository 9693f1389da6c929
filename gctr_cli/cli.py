"""The ``gctr`` command line: register one pair, run a batch, build a manifest, show/check configs.

Heavy modules (numpy, Open3D, the engine, pydantic) are imported inside the commands, so
``gctr --help`` is instant and never loads Open3D.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import click

from gctr_cli import __version__
from gctr_cli.fsutil import THREAD_ENV_VARS

if TYPE_CHECKING:  # imported inside the commands at run time (a fast start)
    from gctr_cli.manifest import PairSpec

logger = logging.getLogger("gctr_cli")

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_BELOW_MIN_SUCCESS = 3

EXIT_CODES_HELP = """\b
Exit codes:
  0  every pair registered (status ok)
  1  at least one pair failed (see the message column of transforms.csv)
  2  usage, manifest, config or output-folder error: nothing was run;
     or the batch had to stop (the finished pairs are saved: --resume)
  3  --min-success given and the success rate over pairs with ground
     truth is below it (takes precedence over 1)
  130/143  stopped by Ctrl-C / SIGTERM (129: SIGHUP; finished pairs saved: --resume)"""


# ----------------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------------


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at emit time (works under click's test runner too)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):  # noqa: D401
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def _setup_logging(verbose: int) -> None:
    level = logging.WARNING if verbose <= 0 else logging.INFO if verbose == 1 else logging.DEBUG
    if not any(isinstance(h, _StderrHandler) for h in logger.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("gctr: %(levelname)s: %(message)s"))
        logger.addHandler(handler)
        logger.propagate = False
    logger.setLevel(level)


VERBOSITY = "gctr.verbose"  # key of the -v count in click's context meta (shared by all contexts)


def _more_verbose(ctx: click.Context, param: click.Parameter, verbose: int) -> None:
    """``-v`` given after a command's name (``gctr batch ... -v``, ``gctr config -v show``): counts
    with the ones before it (``gctr -v register ... -v`` is ``-vv``)."""
    if verbose > 0:
        ctx.meta[VERBOSITY] = ctx.meta.get(VERBOSITY, 0) + verbose
        _setup_logging(ctx.meta[VERBOSITY])


class _Path(click.Path):
    """A path argument or option that refuses an empty value: ``-o "$out"`` with ``out`` unset would
    otherwise mean the current folder (a batch's files written wherever the job happens to run)."""

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, str) and not value.strip():
            hint = "; '.' is the current folder" if self.dir_okay and not self.file_okay else ""
            self.fail(f"is empty (an unset shell variable?){hint}", param, ctx)
        return super().convert(value, param, ctx)


def verbose_option(command):
    """The group's ``-v``/``-vv``, also accepted after a command's name."""
    option = click.option("-v", "--verbose", count=True, expose_value=False, callback=_more_verbose,
                          help="More log output on stderr (-v info, -vv debug); counts with -v before the command.")
    return option(command)


def _die(message: str, code: int = EXIT_USAGE) -> NoReturn:
    click.echo(f"gctr: error: {message}", err=True)
    sys.exit(code)


def _load_config(path: str | None, runs_here: bool = True):
    """The config at ``path`` (defaults for ``None``), or exit 2 naming the problem. With ``runs_here``
    the method it selects must also be installed on this machine (not checked for a batch on a Dask
    cluster, whose workers may have packages this machine lacks)."""
    from gctr_cli.config import ConfigError, load_config
    from gctr_cli.methods import REGISTRY, is_available

    try:
        config = load_config(path)
    except ConfigError as exc:
        _die(str(exc))
    if runs_here and not is_available(config.method):
        _die(f"{path or 'the default config'}: method {config.method!r} needs the optional package "
             f"{REGISTRY[config.method].requires!r}, which is not installed here")
    return config


def _single_threaded_native_libs() -> None:
    """Run the engine like a batch worker does: one BLAS/OpenMP thread (unless the user set them).

    Must run before numpy is imported. Same numerics as a batch row (``--seed`` reproduces it) and,
    on small matrices, much faster than oversubscribed BLAS threads.
    """
    for var in THREAD_ENV_VARS:
        os.environ.setdefault(var, "1")


def _fmt_num(x: float | None, spec: str = ".6g") -> str:
    """``x``; "n/a" when there is none (no answer to measure, or no inliers: NaN)."""
    return "n/a" if x is None or x != x else format(x, spec)


def _fmt_confidence(x: float | None) -> str:
    """The engine's confidence; "n/a" when the method does not compute one (NaN)."""
    return "n/a" if x is None or x != x else format(x, ".6g")


class _Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, handled like Ctrl-C; ``signum`` says which (the exit code is 128 + it)."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__()
        self.signum = signum


def _stop_signal(exc: BaseException) -> int:
    """The signal that stopped the command: SIGTERM/SIGHUP for :class:`_Terminated`, else SIGINT."""
    for e in (exc, exc.__cause__):
        if isinstance(e, _Terminated):
            return e.signum
    return signal.SIGINT


def _say_stopped(line: str) -> None:
    """Say on stderr why the command stopped, if stderr can still be written: after a SIGHUP from a
    closed terminal it cannot (EIO), and the exit code must still say what stopped it, not 1."""
    try:
        click.echo(line, err=True)
    except (OSError, ValueError):
        pass


@contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM (e.g. from a job scheduler) and SIGHUP (a closed ssh session or terminal) stop the batch like
    Ctrl-C: workers killed, lock released, a report written. A SIGHUP that is ignored (``nohup``) stays
    ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001
        raise _Terminated(signum)

    signals = [signal.SIGTERM]
    hup = getattr(signal, "SIGHUP", None)
    if hup is not None and signal.getsignal(hup) is not signal.SIG_IGN:
        signals.append(hup)
    previous = {s: signal.signal(s, handler) for s in signals}
    try:
        yield
    finally:
        for s, before in previous.items():
            signal.signal(s, before)


# ----------------------------------------------------------------------------------------------------
# the group
# ----------------------------------------------------------------------------------------------------


#: set by the one-shot commands (register, apply): everything they write is closed when they return
_ONE_SHOT = False


def _mark_one_shot() -> None:
    global _ONE_SHOT
    _ONE_SHOT = True


def run() -> None:
    """Console-script entry point (``gctr``, ``python -m gctr_cli``): :func:`main`, then, after the
    one-shot commands, a fast process exit.

    Tearing the interpreter down (freeing numpy's and scipy's module state) takes 0.2-0.3 s, more than
    reading and writing a pair's files; ``register`` and ``apply`` have written, flushed and closed
    their outputs when they return, so the process ends with ``os._exit`` after flushing the streams.
    """
    code: int | str | None = 0
    try:
        with _sigterm_as_interrupt():  # every command stops on SIGTERM as on Ctrl-C, with a message
            returned = main(prog_name="gctr", standalone_mode=False)
        code = returned if isinstance(returned, int) else 0  # --help / --version exit through here
    except click.UsageError as exc:  # bad option or argument: one line like every other error
        no_args = getattr(click.exceptions, "NoArgsIsHelpError", ())
        if isinstance(exc, no_args):  # `gctr` or `gctr config` alone: the help, as click prints it
            exc.show()
        else:
            hint = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
            click.echo(f"gctr: error: {exc.format_message()}{hint}", err=True)
        code = exc.exit_code
    except click.ClickException as exc:
        click.echo(f"gctr: error: {exc.format_message()}", err=True)
        code = exc.exit_code
    except (click.exceptions.Abort, KeyboardInterrupt) as exc:  # Ctrl-C / SIGTERM outside a batch (it has its own)
        stopped_by = _stop_signal(exc)
        _say_stopped(f"gctr: {'interrupted' if stopped_by == signal.SIGINT else 'terminated'}")
        code = 128 + stopped_by
    except SystemExit as exc:
        code = exc.code
    except OSError as exc:  # --help or --version (printed by click while it parses) to a stdout that fails
        if not {"-h", "--help", "--version"} & set(sys.argv[1:]):  # the commands' own prints handle it
            raise
        _stdout_to_devnull()
        code = 0
        if not isinstance(exc, BrokenPipeError):  # `gctr --help | head -1`: the reader just quit
            click.echo(f"gctr: error: cannot print to standard output ({exc.strerror or exc})", err=True)
            code = EXIT_USAGE
    if not _ONE_SHOT:
        sys.exit(code)
    if isinstance(code, str):  # sys.exit("message"): print it like the interpreter would
        print(code, file=sys.stderr)
        code = 1
    logging.shutdown()
    try:
        if sys.stdout is not None:
            sys.stdout.flush()
    except OSError:
        _stdout_to_devnull()
    sys.stderr.flush()
    os._exit(code or 0)


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="gctr")
@click.option("-v", "--verbose", count=True, help="More log output on stderr (-v info, -vv debug).")
def main(verbose: int) -> None:
    """gctr: register pairs of 3D point clouds from different sensors with a similarity transform
    (rotation, translation and scale), using GCTR (geometric constraint tensor-based registration).

    \b
    Examples:
      gctr register scan_a.ply scan_b.pcd -o a_to_b.txt
      gctr register scan_a.laz map.e57 -o a_to_map.txt --aligned scan_a_aligned.laz
      gctr apply a_to_b.txt scan_a.ply -o scan_a_on_b.ply
      gctr manifest lidar/ photogrammetry/ --gt-dir gt/ -o pairs.csv
      gctr batch pairs.csv -c configs/default.yaml -o results/
      gctr batch pairs.csv -o results/ --executor dask --scheduler tcp://HOST:8786
      gctr show scan_a.ply scan_b.pcd --matrix a_to_b.txt -o view.png
      gctr config show > my.yaml && gctr config check my.yaml

    Every matrix is a 4x4 [[s*R, t], [0 0 0 1]] mapping the SOURCE cloud onto the TARGET.

    \b
    Exit codes:
      0  success
      1  registration failed (register) / at least one pair failed (batch)
      2  usage, file, manifest or config error: nothing was run; or a
         batch had to stop (finished pairs saved: --resume); or register
         without -o could not print its matrix
      3  batch --min-success: success rate below the threshold
      130/143  stopped by Ctrl-C / SIGTERM (129: SIGHUP)

    \b
    -v / -vv go before or after the command:
      gctr -v batch ...   or   gctr batch ... -v
    """
    click.get_current_context().meta[VERBOSITY] = verbose
    _setup_logging(verbose)


# ----------------------------------------------------------------------------------------------------
# register
# ----------------------------------------------------------------------------------------------------


@main.command()
@click.argument("source", type=_Path(path_type=Path))
@click.argument("target", type=_Path(path_type=Path))
@click.option("-c", "--config", "config_path", type=_Path(dir_okay=False),
              help="YAML config (default: built-in defaults).")
@click.option("-o", "--output", type=_Path(dir_okay=False, path_type=Path),
              help="Write the 4x4 matrix to this file (missing folders are created).")
@click.option("--gt", type=_Path(path_type=Path),
              help="Ground-truth matrix: also print the errors.")
@click.option("--seed", type=click.IntRange(min=0), help="Engine seed (default: the config seed). To reproduce a "
              "batch row, pass its seed column.")
@click.option("--aligned", type=_Path(dir_okay=False, path_type=Path),
              help="Also write SOURCE moved onto TARGET to this file (.ply, .pcd, .las, .laz, .xyz, .pts, .txt, .csv; "
                   "attributes kept where the format allows).")
@verbose_option
def register(source: Path, target: Path, config_path: str | None, output: Path | None, gt: Path | None,
             seed: int | None, aligned: Path | None) -> None:
    """Register SOURCE onto TARGET and print the similarity transform.

    Prints the 4x4 matrix (full precision, same format as the matrix files), the scale, fitness
    (fraction of source points with a target point within the inlier distance), the engine's
    confidence (n/a for methods without one), inlier RMSE, status and runtime; with --gt also the
    rotation/translation/scale/TM errors and success. BLAS/OpenMP run single-threaded as in batch
    workers (set OMP_NUM_THREADS etc. to override).

    \b
    Examples:
      gctr register scan.ply model.pcd -o scan_to_model.txt
      gctr register scan.laz map.e57 -c my.yaml --aligned scan_in_map.laz
      gctr register src.ply tgt.ply --gt gt.txt   # also prints the errors against gt.txt

    \b
    Exit codes:
      0  registered (status ok)
      1  registration failed (the message says why)
      2  usage, config or file error (unreadable cloud, bad ground truth;
         without -o, a stdout that cannot take the matrix)
      130/143  stopped by Ctrl-C / SIGTERM (129: SIGHUP)
    """
    _mark_one_shot()
    _single_threaded_native_libs()
    from gctr_cli.allocator import keep_freed_memory

    keep_freed_memory()  # about 13% off a fresh process's engine time (see gctr_cli.allocator)
    _check_writable(output)
    clouds = {"the SOURCE cloud": source, "the TARGET cloud": target, "the --gt matrix": gt}
    _check_not_an_input(output, clouds)
    _check_not_an_input(aligned, {**clouds, "the -o matrix": output})
    if output is not None and aligned is not None and os.path.abspath(output) == os.path.abspath(aligned):
        _die(f"{output}: given as both -o and --aligned: choose two files")
    if output is None and sys.stdout is None:  # closed (>&-): the printed matrix would be lost; say so first
        _die_unprinted("the result", "stdout is closed")
    if aligned is not None:
        _check_output_cloud(aligned)
    config = _load_config(config_path)
    from gctr_cli.io import MatrixError, format_matrix, write_matrix
    from gctr_cli.manifest import PairSpec
    from gctr_cli.pair import run_pair  # the single-pair path only: no batch machinery

    spec = PairSpec(pair_id=source.stem, source=source, target=target, gt=gt)
    outcome = run_pair(spec, config, seed=config.seed if seed is None else seed)
    if outcome.failure in ("input", "ground_truth"):
        _die(outcome.message)

    # The files first: a reader that stops early (`gctr register … | head`) must not cost them.
    transform = outcome.transform if outcome.ok else None  # an ok outcome always carries its transform
    if transform is not None and output is not None:
        try:
            write_matrix(output, transform)
        except MatrixError as exc:
            _die(str(exc))
        logger.info("wrote %s", output)
    if transform is not None and aligned is not None:
        from gctr_cli.io import PointCloudError, write_aligned

        try:
            write_aligned(source, transform, aligned, reread=True)
        except (PointCloudError, MatrixError) as exc:
            _die(str(exc))

    lines = [f"status: {outcome.status}"]
    if outcome.message:
        lines.append(f"message: {outcome.message}")
    if outcome.transform is not None:
        lines += ["matrix (source -> target):", format_matrix(outcome.transform).rstrip("\n"),
                  f"scale: {outcome.scale!r}"]
    lines += [f"fitness: {_fmt_num(outcome.fitness)}", f"confidence: {_fmt_confidence(outcome.confidence)}",
              f"inlier_rmse: {_fmt_num(outcome.inlier_rmse)}", f"runtime_s: {outcome.runtime_s:.3f}",
              f"seed: {outcome.seed}"]
    if outcome.errors is not None:
        e = outcome.errors
        lines += [f"rot_err_deg: {e.rot_err_deg:.6g}", f"trans_err: {e.trans_err:.6g}",
                  f"trans_err_rel: {e.trans_err_rel:.6g}", f"scale_err: {e.scale_err:.6g}",
                  f"tm_err: {e.tm_err:.6g}", f"success: {'true' if outcome.success else 'false'}"]
    if transform is not None and output is not None:
        lines.append(f"matrix_file: {output}")
    if transform is not None and aligned is not None:
        lines.append(f"aligned: {aligned}")
    _print_report("\n".join(lines) + "\n", only_copy=transform is not None and output is None)
    if transform is None:
        for path, what in ((output, "matrix"), (aligned, "aligned cloud")):
            if path is not None:
                # a script that ignores the exit code must not mistake an earlier run's file for this one's
                older = f"; the {path} there is an older file, left as it was" if path.exists() else ""
                click.echo(f"gctr: no {what} written to {path} (registration failed{older})", err=True)
        sys.exit(EXIT_FAILED)


def _print_report(text: str, only_copy: bool = False) -> None:
    """``text`` on stdout, after the command's files are written (:func:`_stdout_may_fail`; ``only_copy``:
    the text holds a matrix written nowhere else)."""
    with _stdout_may_fail("the result", only_copy=only_copy):
        click.echo(text, nl=False)


@contextmanager
def _stdout_may_fail(what: str, results: Path | None = None, only_copy: bool = False,
                     advice: str | None = None) -> Iterator[None]:
    """Printing ``what`` in the block: a stdout that is closed, full or read by a reader that stopped
    early (``gctr register … | head -1``) is not an error of the command, whose files are written: the
    rest is dropped (with a warning unless the reader just quit) and the exit code stays the command's.
    Unless ``only_copy`` (``register`` without ``-o``: the printed matrix is the result): a stdout that
    cannot be written (full, an I/O error) then exits 2, or a script would take the lost matrix for a success
    (``advice``: the end of that message when it is not ``register``'s, e.g. for ``config show``)."""
    try:
        yield
        if sys.stdout is not None:  # None: closed (>&-); click.echo then prints nothing
            sys.stdout.flush()
    except OSError as exc:
        _stdout_to_devnull()
        if isinstance(exc, BrokenPipeError):
            return
        if only_copy:
            if advice is None:
                _die_unprinted(what, str(exc.strerror or exc))
            _die(f"cannot print {what} ({exc.strerror or exc}){advice}")
        where = f"; the results are in {results}" if results is not None else ""
        logger.warning("cannot print %s (%s)%s", what, exc.strerror or exc, where)


def _die_unprinted(what: str, problem: str) -> NoReturn:
    """Exit 2: ``register`` without ``-o`` could not print ``what``, the only copy of its matrix."""
    _die(f"cannot print {what} ({problem}), and without -o FILE the printed matrix is its only copy: pass -o FILE "
         "to write it to a file")


def _stdout_to_devnull() -> None:
    """Point stdout at /dev/null so that later writes and the final flush do not fail again."""
    if sys.stdout is None:
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


class _Rate(click.FloatRange):
    """A number in a range, and not NaN: click's range check lets ``nan`` through (every comparison with
    it is false), and ``--min-success nan`` then passed every batch, however many pairs failed."""

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        rate = super().convert(value, param, ctx)
        if rate != rate:  # NaN
            self.fail(f"{value!r} is not a number in the range {self.min}<=x<={self.max}.", param, ctx)
        return rate


def _check_output_cloud(path: Path) -> None:
    """Exit 2 before any work when ``path`` has no extension gctr can write a cloud to, or cannot be
    written (:func:`_check_writable`)."""
    from gctr_cli.io.registry import WRITE_EXTENSIONS, format_of

    fmt = format_of(path)
    if fmt is None or fmt.write is None:
        _die(f"{path}: cannot write a point cloud with extension '{path.suffix}' "
             f"(supported: {', '.join(WRITE_EXTENSIONS)})")
    _check_writable(path)


def _check_not_an_input(output: Path | None, inputs: dict[str, Path | None]) -> None:
    """Exit 2 before any work when ``output`` is one of the command's input files (``inputs``: role ->
    path; the same file by another name or a hard link included): ``apply m.txt scan.pcd -o scan.pcd``
    replaced the scan with the moved cloud without a word."""
    if output is None or not output.exists():
        return
    for role, path in inputs.items():
        if path is not None and path.exists() and os.path.samefile(output, path):
            _die(f"{output}: is also {role}; writing there would replace it: choose another output file")


def _check_writable(path: Path | None) -> None:
    """Exit 2 before any work when a file cannot be written at ``path`` (a file where a folder should
    be, a read-only folder, ...): better than finding out after the registration."""
    from gctr_cli.fsutil import output_problem

    if path is not None and (problem := output_problem(path)) is not None:
        _die(f"{path}: cannot write file ({problem})")


# ----------------------------------------------------------------------------------------------------
# apply
# ----------------------------------------------------------------------------------------------------


@main.command()
@click.argument("matrix", type=_Path(path_type=Path))
@click.argument("input", type=_Path(path_type=Path))
@click.option("-o", "--output", required=True, type=_Path(dir_okay=False, path_type=Path),
              help="Cloud to write: .ply, .pcd, .las, .laz, .xyz, .pts, .txt or .csv (missing folders are created).")
@verbose_option
def apply(matrix: Path, input: Path, output: Path) -> None:  # noqa: A002 - the argument's name in --help
    """Move the cloud INPUT by the 4x4 MATRIX and write it to OUTPUT.

    MATRIX is a source->target matrix file as written by register -o or batch (matrices/<pair_id>.txt).
    INPUT may be any format gctr reads (.ply .pcd .xyz .pts .txt .csv .las .laz .e57); OUTPUT's extension
    chooses its format. Coordinates stay float64 (LAS/LAZ: a scale fine enough for the extent);
    attributes (colours, intensity, classification ...) are kept where OUTPUT's format allows, and
    normals are turned with the surface (for a matrix that is not a similarity, by its inverse
    transpose, so they stay perpendicular to it).

    \b
    Example:
      gctr register scan.laz map.e57 -o scan_to_map.txt
      gctr apply scan_to_map.txt scan.laz -o scan_in_map.laz

    \b
    Exit codes:
      0  written
      2  unreadable matrix or cloud, unsupported extension, or OUTPUT cannot be written
    """
    _mark_one_shot()
    _check_output_cloud(output)
    _check_not_an_input(output, {"the INPUT cloud": input, "the MATRIX": matrix})
    from gctr_cli.io import MatrixError, PointCloudError, read_matrix, write_aligned
    from gctr_cli.metrics import is_similarity

    try:
        T = read_matrix(matrix)
    except MatrixError as exc:  # named as the matrix: swapped arguments are the usual cause
        _die(f"matrix {exc}")
    try:
        similarity, reason = is_similarity(T)
        if not similarity:  # a general affine map is applied as given, but rarely meant
            logger.warning("%s is not a similarity transform (%s); applying it anyway", matrix, reason)
        moved = write_aligned(input, T, output)
    except (PointCloudError, MatrixError) as exc:
        _die(str(exc))
    _print_report(f"wrote {output} ({len(moved)} points)\n")


# ----------------------------------------------------------------------------------------------------
# batch
# ----------------------------------------------------------------------------------------------------


def _has_rows(path: Path) -> bool:
    """Whether the CSV file ``path`` exists and has a line after its header."""
    try:
        with open(path, "rb") as fh:
            return len(fh.readline()) > 0 and len(fh.readline()) > 0
    except OSError:
        return False


def _miss_text(rot: float, trans: float, scale: float, th: Any) -> str:
    """What puts an ``ok`` answer outside the success limits ``th``: the errors over their limits."""
    over = [f"{what} {value:.4g}{unit} (limit {limit:g}{unit})" if float(f"{value:.4g}") != limit
            else f"{what} {value:.8g}{unit} (limit {limit:g}{unit})"
            for what, value, limit, unit in (("rotation", rot, th.rotation_deg, " deg"),
                                             ("translation", trans, th.translation_rel, " x target diagonal"),
                                             ("scale error", scale, th.scale, ""))
            if not value < limit]
    return ", ".join(over) or "no success"


def _print_summary(summary: Any, config: Any) -> None:
    s = summary
    echo = click.echo
    th = config.success
    resumed = f" ({s.n_resumed} done by an earlier run)" if s.n_resumed else ""
    echo(f"pairs: {s.n_pairs} ({s.n_ok} ok, {s.n_failed} failed){resumed}")
    if s.success_rate is not None:
        echo(
            f"success: {s.n_success}/{s.n_gt} pairs with ground truth ({100 * s.success_rate:.1f}%)"
            f"  [rotation < {th.rotation_deg:g} deg, translation < {th.translation_rel:g} x target diagonal,"
            f" scale error < {th.scale:g}]"
        )
    else:
        echo("success: n/a (no pair has ground truth)")
    if s.median_rot_err_deg is not None:
        echo(
            f"median errors: rotation {s.median_rot_err_deg:.4g} deg, translation {s.median_trans_err:.4g}"
            f" ({s.median_trans_err_rel:.4g} x target diagonal), scale {s.median_scale_err:.4g},"
            f" TM {s.median_tm_err:.4g}"
        )
    echo(f"wall time: {s.wall_time_s:.1f} s ({s.n_run} pair{'' if s.n_run == 1 else 's'} run)")
    if s.failures:
        echo("failed pairs:")
        for pid, msg in s.failures[:50]:
            echo(f"  {pid}: {msg}")
        if len(s.failures) > 50:
            echo(f"  ... and {len(s.failures) - 50} more (see transforms.csv)")
    if s.misses:
        echo("ok but wrong by their ground truth:")
        for pid, rot, trans, scale in s.misses[:50]:
            echo(f"  {pid}: {_miss_text(rot, trans, scale, th)}")
        if len(s.misses) > 50:
            echo(f"  ... and {len(s.misses) - 50} more (see tm_errors.csv)")
    extras = "".join(f", {name}/" for name in ("snapshots", "aligned") if (Path(s.outdir) / name).is_dir())
    from gctr_cli.io.errors import escaped

    shown = escaped(s.outdir)  # a Latin-1 name as \xe9: no crash under a strict UTF-8 stdout
    echo(f"outputs: {shown}/transforms.csv, tm_errors.csv, matrices/, config.yaml{extras}")
    if s.report_written:
        echo(f"report: {shown}/report.html")


@main.command(epilog=EXIT_CODES_HELP)
@click.argument("manifest", type=_Path(path_type=Path))
@click.option("-c", "--config", "config_path", type=_Path(dir_okay=False),
              help="YAML config (default: built-in defaults).")
@click.option("-o", "--outdir", required=True, type=_Path(file_okay=False, path_type=Path),
              help="Output folder (created if needed).")
@click.option("-j", "--workers", type=click.IntRange(min=0),
              help="Worker processes (default: config batch.workers; 0 = one per core).")
@click.option("--resume", is_flag=True,
              help="Continue an interrupted run: skip pairs already in OUTDIR/transforms.csv (pairs whose "
                   "input files changed since, as paths or on disk, run again).")
@click.option("--retry-failed", is_flag=True,
              help="With --resume: also run again the pairs whose earlier row is failed (timeouts, killed "
                   "workers, files fixed since).")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar.")
@click.option("--min-success", type=_Rate(0.0, 1.0), metavar="RATE",
              help="Exit 3 if the success rate over pairs with ground truth is below RATE (0..1).")
@click.option("--executor", type=click.Choice(["local", "dask"]), default=None,
              help="Where pairs run: 'local' process pool (default) or a dask.distributed cluster "
                   "(make setup installs it; elsewhere pip install '.[dask]' in gctr's checkout).")
@click.option("--scheduler", metavar="ADDRESS",
              help="Dask scheduler address, e.g. tcp://HOST:8786 (implies --executor dask). Without it "
                   "--executor dask starts a local cluster of -j worker processes.")
@click.option("--snapshots", is_flag=True,
              help="Also write OUTDIR/snapshots/<pair_id>.png: both clouds before and after registration.")
@click.option("--write-aligned", is_flag=True,
              help="Also write OUTDIR/aligned/<pair_id>.<ext>: each registered source moved onto its target "
                   "(the source's format when writable, else PLY; attributes kept where the format allows).")
@verbose_option
def batch(manifest: Path, config_path: str | None, outdir: Path, workers: int | None, resume: bool,
          retry_failed: bool, quiet: bool, min_success: float | None, executor: str | None, scheduler: str | None,
          snapshots: bool, write_aligned: bool) -> None:
    """Register every pair of MANIFEST in a pool of worker processes (or on a dask cluster).

    MANIFEST is a CSV with header pair_id,source,target[,gt] (relative paths are relative to the
    manifest's folder). Results are written to OUTDIR as pairs finish: transforms.csv (one row per
    pair, ok or failed with a message), tm_errors.csv (pairs with ground truth), matrices/<pair_id>.txt
    and config.yaml (the resolved config); at the end report.html, a self-contained page with the
    summary, a sortable table of the pairs and the error distribution. A crashed or timed-out pair
    gets a failed row and the batch goes on. An interrupted run keeps every finished pair: rerun with
    --resume to finish it. Results do not depend on -j or on the executor.

    \b
    Examples:
      gctr batch pairs.csv -c configs/default.yaml -o results/ -j 4
      gctr batch pairs.csv -o results/ --resume -q --min-success 0.95   # cron / CI
      gctr batch pairs.csv -o results/ --scheduler tcp://HOST:8786

    With --executor dask the input files must be readable by every worker at the same absolute
    paths (a shared filesystem); outputs are written by this process only.
    """
    if executor is None:
        executor = "dask" if scheduler else "local"
    elif executor == "local" and scheduler:
        _die("--scheduler needs --executor dask")
    if retry_failed and not resume:
        _die("--retry-failed needs --resume (it runs again the failed pairs of an earlier run in OUTDIR)")
    if scheduler and workers is not None:  # the cluster's workers run the pairs, as many as it has
        logger.warning("-j %d has no effect with --scheduler: the cluster's workers run the pairs (start fewer "
                       "workers, or give them fewer threads, to run fewer at a time)", workers)
    config = _load_config(config_path, runs_here=scheduler is None)  # a LocalCluster runs here too
    from gctr_cli import batch as batch_mod
    from gctr_cli.manifest import ManifestError, read_manifest

    try:
        pairs = read_manifest(manifest)
    except ManifestError as exc:
        _die(str(exc))
    if min_success is not None and not any(p.gt is not None for p in pairs):
        _die(f"--min-success needs pairs with ground truth, but no pair of {manifest} has a gt file")

    from tqdm import tqdm

    show_bar = not quiet and sys.stderr.isatty()
    bar: Any = None
    n_failed = 0

    def on_start(n_todo: int, n_done: int) -> None:
        nonlocal bar
        bar = tqdm(total=n_todo + n_done, initial=n_done, unit="pair", file=sys.stderr, disable=not show_bar,
                   dynamic_ncols=True, desc="gctr")

    def on_outcome(outcome: Any) -> None:
        nonlocal n_failed
        if not outcome.ok:
            n_failed += 1
        if bar is not None:
            bar.update(1)
            if n_failed:
                bar.set_postfix(failed=n_failed)

    if show_bar:
        from tqdm.contrib.logging import logging_redirect_tqdm

        redirect: Any = logging_redirect_tqdm(loggers=[logger])
    else:
        redirect = nullcontext()
    try:
        with _sigterm_as_interrupt(), redirect:
            summary = batch_mod.run_batch(
                pairs, config, outdir, workers=workers, resume=resume, on_start=on_start, on_outcome=on_outcome,
                executor=executor, scheduler=scheduler, snapshots=snapshots, write_aligned=write_aligned,
                manifest=manifest, retry_failed=retry_failed,
            )
    except batch_mod.ExecutorLost as exc:  # the cause's traceback (from distributed) only under -vv
        logger.debug("the batch stopped", exc_info=True)
        if _has_rows(outdir / batch_mod.TRANSFORMS_FILE):
            _die(f"{exc}; the finished pairs are saved in {outdir}: rerun with --resume against a running "
                 "scheduler to finish")
        _die(f"{exc}; no pair had finished, nothing was written")  # the run removed what it had created
    except batch_mod.BatchError as exc:
        # one clear line; the cause's traceback (e.g. from distributed) only under -vv
        logger.debug("the batch stopped", exc_info=True)
        _die(str(exc))
    except KeyboardInterrupt as exc:
        if bar is not None:
            bar.close()
        if _has_rows(outdir / batch_mod.TRANSFORMS_FILE):
            from gctr_cli.io.errors import escaped

            shown = escaped(outdir)
            _say_stopped(f"gctr: interrupted; finished pairs are saved in {shown}; rerun with --resume to finish")
        else:  # stopped before the first pair was recorded: the run removed what it had created
            _say_stopped("gctr: interrupted before the first pair finished; nothing was written")
        sys.exit(128 + _stop_signal(exc))
    finally:
        if bar is not None:
            bar.close()

    with _stdout_may_fail("the summary", results=outdir):  # cron: > /dev/full, >&-; the results are saved
        _print_summary(summary, config)
    if min_success is not None and summary.success_rate is not None:
        # fractions as given (repr: 0.87500001 stays that), never rounded onto each other
        rate = (f"success rate {summary.success_rate!r} ({summary.n_success} of {summary.n_gt} "
                f"{'pair' if summary.n_gt == 1 else 'pairs'} with ground truth)")
        if summary.success_rate < min_success:
            click.echo(f"gctr: {rate} is below --min-success {min_success!r}", err=True)
            sys.exit(EXIT_BELOW_MIN_SUCCESS)
        with _stdout_may_fail("the gate's line", results=outdir):  # a CI log shows that the gate was on
            click.echo(f"min-success {min_success!r}: passed, {rate}")
    sys.exit(EXIT_OK if summary.all_ok else EXIT_FAILED)


# ----------------------------------------------------------------------------------------------------
# show
# ----------------------------------------------------------------------------------------------------


@main.command()
@click.argument("source", type=_Path(path_type=Path))
@click.argument("target", type=_Path(path_type=Path))
@click.option("-m", "--matrix", type=_Path(path_type=Path),
              help="4x4 source->target matrix (e.g. OUTDIR/matrices/<pair_id>.txt): also show the clouds registered.")
@click.option("-o", "--output", required=True, type=_Path(dir_okay=False, path_type=Path),
              help="PNG file to write (missing folders are created).")
@click.option("--max-points", type=click.IntRange(min=10), default=3000, show_default=True,
              help="Points drawn per cloud (evenly subsampled).")
@click.option("--title", help="Title of the picture (default: the two file names).")
@verbose_option
def show(source: Path, target: Path, matrix: Path | None, output: Path, max_points: int, title: str | None) -> None:
    """Draw SOURCE (orange) and TARGET (blue) in three orthogonal views into a PNG.

    The top row shows the input clouds as they are; with --matrix, the bottom row shows the target
    with the source mapped by the matrix (same picture as batch --snapshots). Rendering is headless.

    \b
    Example:
      gctr show scan.ply model.pcd --matrix scan_to_model.txt -o check.png

    \b
    Exit codes:
      0  picture written
      2  usage error, unreadable cloud or matrix, or the PNG cannot be written
    """
    if output.suffix.lower() != ".png":
        _die(f"{output}: the picture is written as PNG; give the file the extension .png")
    _check_writable(output)
    _check_not_an_input(output, {"the SOURCE cloud": source, "the TARGET cloud": target, "the --matrix": matrix})
    from gctr_cli.io import MatrixError, PointCloudError, load_point_cloud, read_matrix
    from gctr_cli.metrics import is_similarity
    from gctr_cli.snapshots import render_snapshot, write_png

    try:
        src = load_point_cloud(source)
        tgt = load_point_cloud(target)
    except PointCloudError as exc:
        _die(str(exc))
    T = None
    if matrix is not None:
        try:
            T = read_matrix(matrix)
        except MatrixError as exc:
            _die(f"matrix {exc}")
        ok, reason = is_similarity(T)
        if not ok:
            logger.warning("%s is not a similarity transform (%s); drawing it anyway", matrix, reason)
    note = "" if T is not None else "input only (pass --matrix to also see the registered clouds)"
    png = render_snapshot(src, tgt, T, title=title or f"{source.name} -> {target.name}", note=note,
                          max_points=max_points)
    try:
        write_png(output, png)
    except OSError as exc:
        from gctr_cli.fsutil import write_error

        _die(f"{output}: cannot write file ({write_error(output, exc)})")
    with _stdout_may_fail("the summary line", results=output):
        click.echo(f"wrote {output}")


# ----------------------------------------------------------------------------------------------------
# manifest
# ----------------------------------------------------------------------------------------------------


@main.command()
@click.argument("source_dir", type=_Path(path_type=Path))
@click.argument("target_dir", type=_Path(path_type=Path))
@click.option("--gt-dir", type=_Path(path_type=Path),
              help="Folder of ground-truth matrices named <stem>.txt (or .TXT).")
@click.option("-o", "--output", required=True, type=_Path(dir_okay=False, path_type=Path),
              help="Manifest CSV to write.")
@verbose_option
def manifest(source_dir: Path, target_dir: Path, gt_dir: Path | None, output: Path) -> None:
    """Build a pair manifest by matching file stems of SOURCE_DIR and TARGET_DIR.

    a.ply in SOURCE_DIR pairs with a.pcd in TARGET_DIR (pair_id "a"); with --gt-dir, GT_DIR/a.txt is
    its ground truth. Stems found on one side only, stems held by several files of one folder (a.ply
    beside a.laz) and stems unsafe as a pair id are left out with a warning. Exit 2 when no stem pairs
    or on another error.

    \b
    Example:
      gctr manifest scans/ models/ --gt-dir gt/ -o pairs.csv
    """
    from gctr_cli.manifest import ManifestError, build_manifest, write_manifest

    _check_writable(output)
    try:
        pairs = build_manifest(source_dir, target_dir, gt_dir)
        _check_manifest_output(output, pairs, {"SOURCE_DIR": source_dir, "TARGET_DIR": target_dir, "--gt-dir": gt_dir})
        write_manifest(output, pairs)
    except ManifestError as exc:
        _die(str(exc))
    n_gt = sum(p.gt is not None for p in pairs)
    with _stdout_may_fail("the summary line", results=output):
        click.echo(f"wrote {len(pairs)} pair{'' if len(pairs) == 1 else 's'} ({n_gt} with ground truth) to {output}")


def _check_manifest_output(output: Path, pairs: Sequence[PairSpec], folders: dict[str, Path | None]) -> None:
    """Exit 2 when writing the manifest at ``output`` would replace one of its pairs' files (a cloud or a
    ground truth: ``-o scans/room1.ply`` turned the scan into CSV text) or another file of the input
    folders that folder pairing reads (a cloud whose stem has no partner, a ground-truth ``.txt``)."""
    from gctr_cli.manifest import FOLDER_EXTENSIONS

    if not output.exists():
        return
    for p in pairs:
        roles = {f"the source cloud of pair {p.pair_id}": p.source, f"the target cloud of pair {p.pair_id}": p.target,
                 f"the ground truth of pair {p.pair_id}": p.gt}
        _check_not_an_input(output, roles)
    for option, folder in folders.items():
        if (folder is not None and output.suffix.lower() in FOLDER_EXTENSIONS and folder.is_dir()
                and os.path.samefile(output.parent, folder)):
            _die(f"{output}: is an input file in {option} ({folder}); writing the manifest there would replace it: "
                 "choose another output file (e.g. pairs.csv)")


# ----------------------------------------------------------------------------------------------------
# config
# ----------------------------------------------------------------------------------------------------


def commented_yaml(config: Any) -> str:
    """YAML of a config with each section's docstring and each key's description as comments."""
    import typing

    import yaml
    from pydantic import BaseModel

    def scalar(value: Any) -> str:
        text = yaml.safe_dump(value, default_flow_style=True, width=10_000).strip()
        if text.endswith("\n..."):
            text = text[: -len("\n...")]
        return text.strip()

    lines = [
        "# gctr configuration. Every key is optional; missing keys take the defaults shown here.",
        "# Lengths in the engine section are relative to each cloud's own size (the scale between the",
        "# two clouds is unknown until the end). Validate a file with: gctr config check FILE",
    ]

    def emit(model: BaseModel, indent: int) -> None:
        dumped = model.model_dump(mode="json")
        pad = " " * indent
        for name, info in type(model).model_fields.items():
            value = getattr(model, name)
            if isinstance(value, BaseModel):
                doc = (type(value).__doc__ or "").strip()
                if doc:
                    for line in doc.split("\n\n")[0].splitlines():
                        lines.append(f"{pad}# {line.strip()}")
                lines.append(f"{pad}{name}:")
                emit(value, indent + 2)
                continue
            comment = info.description or ""
            args = typing.get_args(info.annotation)
            choices = [a for arg in ((info.annotation,) + args) if typing.get_origin(arg) is typing.Literal
                       for a in typing.get_args(arg)]
            if choices and len(choices) > 1:
                comment = (comment + "; " if comment else "") + "one of: " + ", ".join(map(str, choices))
            text = f"{pad}{name}: {scalar(dumped[name])}"
            lines.append(f"{text}  # {comment}" if comment else text)

    emit(config, 0)
    return "\n".join(lines) + "\n"


@main.group("config")
@verbose_option
def config_group() -> None:
    """Show the default configuration or validate a config file.

    \b
    Examples:
      gctr config show > my.yaml
      gctr config check my.yaml
    """


@config_group.command("show")
@click.argument("file", required=False, type=_Path(dir_okay=False))
@verbose_option
def config_show(file: str | None) -> None:
    """Print the default config (or FILE resolved with defaults) as commented YAML.

    Save it, edit what you need, and pass it with -c.

    \b
    Examples:
      gctr config show > my.yaml
      gctr config show my.yaml   # my.yaml with every default filled in
    """
    config = _load_config(file, runs_here=False)
    with _stdout_may_fail("the configuration", only_copy=True, advice=""):  # the printed YAML is the result
        click.echo(commented_yaml(config), nl=False)


@config_group.command("check")
@click.argument("file", type=_Path(dir_okay=False))
@verbose_option
def config_check(file: str) -> None:
    """Validate FILE: exit 0 and print "ok: FILE", or exit 2 naming each bad key and the expected type.

    Also checks that the method FILE selects is installed here.

    \b
    Example:
      gctr config check my.yaml
    """
    _load_config(file)
    with _stdout_may_fail(f"'ok: {file}'"):  # the exit code is the check's answer
        click.echo(f"ok: {file}")


if __name__ == "__main__":  # pragma: no cover
    main()
