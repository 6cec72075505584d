"""``sinkjax synth``, ``demo``, ``smooth`` and ``plot``: the commands around a run."""

from __future__ import annotations

import argparse
from types import ModuleType

from ..rig import ENCODINGS
from .cli_base import EXIT_OK, UsageError
from .cli_estimate import (
    _add_smoothing_options,
    _smoothing_options,
    add_cache_option,
    setup_compile_cache,
)
from .pipeline import MethodUnavailable, load_method

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
    p.add_argument(
        "--encoding",
        choices=ENCODINGS,
        default="linear",
        help="store the frames linear in light (default) or with the sRGB tone curve of a camera",
    )


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
    try:
        out = synth.write_recording(
            args.out,
            n_frames=args.frames,
            seed=args.seed,
            preset=args.preset,
            width=args.width,
            height=args.height,
            travel=args.travel,
            progress=True,
            encoding=args.encoding,
        )
    except OSError as e:
        raise UsageError(f"cannot write {e.filename or args.out}: {e.strerror or e}") from e
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
    add_cache_option(p)


def _run_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    _load_synth()
    try:
        load_method(args.method)
    except MethodUnavailable as e:
        raise UsageError(str(e)) from e
    setup_compile_cache(args)
    report = run_demo(args.out, method=args.method, progress=True)
    print("\n".join([*report.summary.segmenter_lines(), report.summary.line()]))
    print()
    print(f"errors against the truth ({args.method} method):")
    print(report.accuracy.table())
    print()
    print(f"results:  {report.results_csv}")
    print(f"overlays: {report.overlay_dir}")
    print(f"plot:     {report.plot_png}")
    return EXIT_OK


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
    p.add_argument(
        "--per-recording",
        action="store_true",
        help="a campaign's view instead: z0, θ1, θ2 over time, one line per recording",
    )
    _add_smoothing_options(p)


def _run_plot(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .plots import plot_recordings, plot_series

    options = _smoothing_options(args)
    out = args.out or str(Path(args.results).with_suffix(".png"))
    if args.per_recording and args.smoothed:
        raise UsageError("--per-recording draws no smoothed series; drop --smoothed")
    try:
        if args.per_recording:
            written = plot_recordings(args.results, out)
        else:
            written = plot_series(args.results, out, smoothed=args.smoothed, options=options)
    except ValueError as e:
        raise UsageError(str(e)) from e
    except OSError as e:
        raise UsageError(f"cannot use {e.filename or args.results}: {e.strerror or e}") from e
    print(f"plot -> {written}")
    return EXIT_OK
