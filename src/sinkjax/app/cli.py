"""The ``sinkjax`` command (conventions §3). Thin: parse, validate, call the API, report.

Subcommands live in :data:`COMMANDS` (name -> :class:`Command`); add one by adding an entry.
User errors (bad arguments, unusable rig, nothing readable) print one message and exit 2, never a
traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import ModuleType

from ..rig import RigError
from .inputs import FrameSelection, InputError, expand_paths, parse_rect, resolve_rig
from .pipeline import MethodUnavailable, ResumeError, estimate_to_csv, load_method
from .smoothing import SmoothingOptions

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class UsageError(Exception):
    """An unusable argument or input; printed as ``sinkjax CMD: error: ...``, exit code 2."""


@dataclass(frozen=True)
class Command:
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


# --------------------------------------------------------------------------------------------
# estimate


def _add_estimate(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "paths",
        nargs="+",
        metavar="PATH",
        help="image files, directories of images (sorted by name; a rig.toml inside is used), "
        "or video files (one row per frame)",
    )
    p.add_argument(
        "--rig", metavar="RIG.toml", help="rig file (default: rig.toml in the directory)"
    )
    p.add_argument(
        "--wheel-radius-mm", type=float, metavar="R", help="physical rim radius R in mm (overrides)"
    )
    p.add_argument(
        "--confidence-rect",
        metavar="X,Y,W,H",
        help="pixel rectangle that always shows the wheel face (overrides)",
    )
    p.add_argument("--travel", choices=("right", "left"), help="direction of travel (overrides)")
    p.add_argument(
        "--method",
        choices=("soft", "classic"),
        default="soft",
        help="soft: differentiable estimator with uncertainty (default); classic: the paper's",
    )
    p.add_argument(
        "--out", default="results.csv", metavar="CSV", help="results CSV (default: results.csv)"
    )
    p.add_argument("--overlay", metavar="DIR", help="also write one overlay PNG per frame here")
    p.add_argument(
        "--batch-size",
        type=int,
        default=8,
        metavar="N",
        help="frames measured together (soft method only; default: 8)",
    )
    _add_long_run_options(p)


def _run_estimate(args: argparse.Namespace) -> int:
    if args.batch_size < 1:
        raise UsageError(f"--batch-size must be at least 1, got {args.batch_size}")
    select, smoothing = _long_run_options(args)
    rect = parse_rect(args.confidence_rect) if args.confidence_rect is not None else None
    inputs = expand_paths(args.paths)
    rig = resolve_rig(
        inputs,
        rig_path=args.rig,
        wheel_radius_mm=args.wheel_radius_mm,
        confidence_rect=rect,
        travel=args.travel,
    )
    try:
        load_method(args.method)
    except MethodUnavailable as e:
        raise UsageError(str(e)) from e
    try:
        summary = estimate_to_csv(
            inputs,
            rig,
            args.out,
            method=args.method,
            batch_size=args.batch_size,
            overlay_dir=args.overlay,
            overlay_video=args.overlay_video,
            select=select,
            resume=args.resume,
            smoothing=smoothing,
            progress=True,
        )
    except ResumeError as e:
        raise UsageError(str(e)) from e
    except OSError as e:
        raise UsageError(f"cannot write {e.filename or args.out}: {e.strerror or e}") from e
    print(summary.line())
    if summary.n_frames == 0:
        if summary.n_resumed:
            print(f"nothing left to measure: {args.out} already has every selected frame")
            return EXIT_OK
        raise UsageError(
            f"no frames selected (--start {select.start}, --stop {select.stop}, --stride "
            f"{select.stride}); the videos are shorter than --start, or there are fewer images"
        )
    if summary.n_read == 0:
        raise UsageError(
            f"none of the {summary.n_frames} input frame(s) could be read (see the message "
            f"column of {args.out}); check that the PATHs are intact image or video files"
        )
    if summary.only_bad_rect:
        x, y, w, h = rig.confidence_rect
        raise UsageError(
            f"the confidence rectangle [{x}, {y}, {w}, {h}] lies off every image; fix "
            "confidence_rect in the rig or pass --confidence-rect X,Y,W,H inside the images"
        )
    return EXIT_OK


# --------------------------------------------------------------------------------------------
# synth


def _add_synth(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", metavar="OUT", help="directory to write frames, rig.toml, truth.csv")
    p.add_argument("--frames", type=int, default=12, metavar="N", help="number of frames (12)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (0)")
    p.add_argument("--preset", default="full", metavar="P", help="scene preset (default: full)")
    p.add_argument("--width", type=int, default=640, metavar="W", help="image width px (640)")
    p.add_argument("--height", type=int, default=480, metavar="H", help="image height px (480)")
    p.add_argument("--travel", choices=("right", "left"), default="right", help="travel (right)")


def _load_synth() -> ModuleType:
    try:
        import importlib

        synth = importlib.import_module("sinkjax.synth")
    except ImportError as e:
        raise UsageError(
            f"the synthetic renderer (sinkjax.synth.render) is not available: {e}"
        ) from e
    return synth


def _run_synth(args: argparse.Namespace) -> int:
    synth = _load_synth()
    presets = list(getattr(synth, "PRESETS", []))
    if presets and args.preset not in presets:
        raise UsageError(f"unknown --preset {args.preset!r}; choose one of {', '.join(presets)}")
    if args.frames < 1:
        raise UsageError(f"--frames must be at least 1, got {args.frames}")
    if args.width < 32 or args.height < 32:
        raise UsageError(f"--width/--height must be at least 32 px, got {args.width}x{args.height}")
    out = synth.write_recording(
        args.out,
        n_frames=args.frames,
        seed=args.seed,
        preset=args.preset,
        width=args.width,
        height=args.height,
        travel=args.travel,
        progress=True,
    )
    print(f"wrote {args.frames} frames, rig.toml and truth.csv to {out}")
    print(f"measure them with: sinkjax estimate {out}")
    return EXIT_OK


# --------------------------------------------------------------------------------------------
# demo


def _add_demo(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--out", default="sinkjax-demo", metavar="DIR", help="output folder (sinkjax-demo)"
    )
    p.add_argument("--method", choices=("soft", "classic"), default="soft", help="method (soft)")


def _run_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    _load_synth()
    try:
        load_method(args.method)
    except MethodUnavailable as e:
        raise UsageError(str(e)) from e
    report = run_demo(args.out, method=args.method, progress=True)
    print(report.summary.line())
    print()
    print(f"errors against the truth ({args.method} method):")
    print(report.accuracy.table())
    print()
    print(f"results:  {report.results_csv}")
    print(f"overlays: {report.overlay_dir}")
    print(f"plot:     {report.plot_png}")
    return EXIT_OK


# --------------------------------------------------------------------------------------------
# long runs: frame selection, resume, overlay video, smoothing (estimate); smooth; plot


def _add_smoothing_options(p: argparse.ArgumentParser) -> None:
    from . import smoothing as S

    g = p.add_argument_group(
        "smoothing (random walk per quantity, Kalman filter + RTS smoother over the frames)"
    )
    g.add_argument(
        "--process-std-mm",
        type=float,
        default=S.PROCESS_STD_MM,
        metavar="MM",
        help=f"how far sinkage may drift per frame, one sigma (default: {S.PROCESS_STD_MM})",
    )
    g.add_argument(
        "--process-std-deg",
        type=float,
        default=S.PROCESS_STD_DEG,
        metavar="DEG",
        help=f"how far θ1, θ2 may drift per frame, one sigma (default: {S.PROCESS_STD_DEG})",
    )
    g.add_argument(
        "--measurement-std-mm",
        type=float,
        default=S.MEASUREMENT_STD_MM,
        metavar="MM",
        help="sinkage sigma for rows that have none, e.g. the classic method's "
        f"(default: {S.MEASUREMENT_STD_MM})",
    )
    g.add_argument(
        "--measurement-std-deg",
        type=float,
        default=S.MEASUREMENT_STD_DEG,
        metavar="DEG",
        help=f"angle sigma for rows that have none (default: {S.MEASUREMENT_STD_DEG})",
    )


def _smoothing_options(args: argparse.Namespace) -> SmoothingOptions:
    try:
        return SmoothingOptions(
            process_std_mm=args.process_std_mm,
            process_std_deg=args.process_std_deg,
            measurement_std_mm=args.measurement_std_mm,
            measurement_std_deg=args.measurement_std_deg,
        )
    except ValueError as e:
        raise UsageError(str(e)) from e


def _add_long_run_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "long recordings (frame indices count within each video, and over all image files "
        "of the run together, in input order)"
    )
    g.add_argument("--start", type=int, default=0, metavar="N", help="first frame index (0)")
    g.add_argument("--stop", type=int, metavar="N", help="stop before this frame index (end)")
    g.add_argument(
        "--stride", type=int, default=1, metavar="K", help="measure every K-th frame (1)"
    )
    g.add_argument(
        "--resume",
        action="store_true",
        help="keep the rows already in --out and measure only the frames it lacks (by image "
        "name), appending to it; a fresh run if --out does not exist",
    )
    g.add_argument(
        "--overlay-video",
        metavar="OUT.mp4",
        help="also write an annotated video (mp4v), one video frame per row",
    )
    g.add_argument(
        "--smooth",
        action="store_true",
        help="when the run completes, add smoothed columns (sinkage_smooth_mm, ...) after the "
        "12 standard ones; see 'sinkjax smooth -h'",
    )
    _add_smoothing_options(p)


def _long_run_options(
    args: argparse.Namespace,
) -> tuple[FrameSelection, SmoothingOptions | None]:
    try:
        select = FrameSelection(start=args.start, stop=args.stop, stride=args.stride)
    except ValueError as e:
        raise UsageError(str(e)) from e
    if args.overlay_video is not None and not args.overlay_video.lower().endswith(
        (".mp4", ".m4v", ".mov")
    ):
        raise UsageError(f"--overlay-video must name an .mp4 file, got {args.overlay_video!r}")
    return select, _smoothing_options(args) if args.smooth else None


def _add_smooth(p: argparse.ArgumentParser) -> None:
    from .smoothing import SMOOTH_COLUMNS

    p.description = (
        "Add smoothed sinkage, θ1 and θ2 with their one-sigma after the 12 standard columns "
        f"({', '.join(SMOOTH_COLUMNS)}). Each quantity is a random walk over the frame index "
        "(a video's frame number; row order for images), seen through each frame's own sigma; "
        "a Kalman filter and Rauch-Tung-Striebel smoother combine all frames and bridge the "
        "failed ones. 'sinkjax estimate --smooth' does the same when a run completes."
    )
    p.add_argument("results", metavar="RESULTS.csv", help="a results CSV from 'sinkjax estimate'")
    p.add_argument(
        "--out", metavar="CSV", help="where to write (default: add the columns to RESULTS.csv)"
    )
    _add_smoothing_options(p)


def _run_smooth(args: argparse.Namespace) -> int:
    from .smoothing import NotAResultsCsv, smooth_csv

    options = _smoothing_options(args)
    try:
        out = smooth_csv(args.results, args.out, options)
    except NotAResultsCsv as e:
        raise UsageError(str(e)) from e
    except OSError as e:
        raise UsageError(f"cannot use {e.filename or args.results}: {e.strerror or e}") from e
    print(f"smoothed sinkage, θ1 and θ2 -> {out}")
    return EXIT_OK


def _add_plot(p: argparse.ArgumentParser) -> None:
    p.add_argument("results", metavar="RESULTS.csv", help="a results CSV from 'sinkjax estimate'")
    p.add_argument("--out", metavar="PNG", help="image to write (default: RESULTS.png)")
    p.add_argument(
        "--smoothed",
        action="store_true",
        help="also draw the smoothed series (its columns, or smoothed here with the options)",
    )
    _add_smoothing_options(p)


def _run_plot(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .plots import plot_series

    options = _smoothing_options(args)
    out = args.out or str(Path(args.results).with_suffix(".png"))
    try:
        written = plot_series(args.results, out, smoothed=args.smoothed, options=options)
    except ValueError as e:
        raise UsageError(str(e)) from e
    except OSError as e:
        raise UsageError(f"cannot use {e.filename or args.results}: {e.strerror or e}") from e
    print(f"plot -> {written}")
    return EXIT_OK


# --------------------------------------------------------------------------------------------
# registry and entry point

COMMANDS: dict[str, Command] = {
    "estimate": Command(
        "measure sinkage and angles in images or videos", _add_estimate, _run_estimate
    ),
    "synth": Command("write a synthetic recording with ground truth", _add_synth, _run_synth),
    # calibrate lives in _calibration (parse + run); imported when the parser is built.
    "calibrate": Command(
        "tune the segmentation thresholds to a few labelled frames; writes a rig file",
        lambda p: __import__("sinkjax.calibration.calibrate", fromlist=["_"]).add_cli_arguments(p),
        lambda a: __import__("sinkjax.calibration.calibrate", fromlist=["_"]).run_cli(a),
    ),
    "demo": Command("run the whole job on a built-in synthetic recording", _add_demo, _run_demo),
    "smooth": Command("add Kalman/RTS-smoothed columns to a results CSV", _add_smooth, _run_smooth),
    "plot": Command("plot sinkage and angles over the frames", _add_plot, _run_plot),
    "review": Command(
        "review a run and label frames for calibration in a local web page",
        lambda p: __import__("sinkjax.review.command", fromlist=["_"]).add_cli_arguments(p),
        lambda a: __import__("sinkjax.review.command", fromlist=["_"]).run_cli(a),
    ),
}


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="sinkjax",
        description="Wheel sinkage and entry/exit angles from images of a rover wheel.",
    )
    parser.add_argument("--version", action="version", version=f"sinkjax {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, command in COMMANDS.items():
        command.add_arguments(sub.add_parser(name, help=command.help, description=command.help))
    return parser


class _TqdmHandler(logging.Handler):
    """Warnings on stderr without tearing a progress bar apart."""

    def emit(self, record: logging.LogRecord) -> None:
        from tqdm import tqdm

        try:
            tqdm.write(f"sinkjax: warning: {record.getMessage()}", file=sys.stderr)
        except Exception:
            self.handleError(record)


def _setup_logging() -> None:
    logger = logging.getLogger("sinkjax")
    if not any(isinstance(h, _TqdmHandler) for h in logger.handlers):
        logger.addHandler(_TqdmHandler(level=logging.WARNING))
    logger.setLevel(logging.WARNING)
    logger.propagate = False


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``sinkjax``; returns the exit code (0 done, 2 unusable arguments or inputs)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging()
    try:
        return COMMANDS[args.command].run(args)
    except (UsageError, InputError, RigError) as e:
        print(f"sinkjax {args.command}: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        kept = ""
        if args.command == "estimate":
            kept = f"; the rows finished so far are in {args.out} (finish with --resume)"
        print(f"sinkjax {args.command}: interrupted{kept}", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
