"""``sinkjax estimate`` and the options of long runs (frames, resume, overlays, smoothing)."""

from __future__ import annotations

import argparse

from ..rig import ENCODINGS
from .cli_base import EXIT_OK, UsageError
from .compile_cache import cache_dir, enable_compile_cache
from .frames import FrameSelection
from .parallel import ParallelOptions, ParallelUnavailable, WorkerCannotRead, import_distributed
from .pipeline import MethodUnavailable, load_method
from .resume import ResumeError
from .run import estimate_to_csv
from .smoothing import SmoothingOptions
from .sources import RigOverrides, open_recordings, parse_rect

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
        "--encoding",
        choices=ENCODINGS,
        help="how the frames store brightness (overrides the rig's encoding): srgb for camera "
        "footage with the sRGB tone curve, linear for values proportional to light (the "
        "default); the soft method locates edges in linear light",
    )
    p.add_argument(
        "--method",
        choices=("soft", "classic"),
        default="soft",
        help="soft: differentiable estimator with uncertainty (default); classic: the paper's",
    )
    p.add_argument(
        "--segmenter",
        metavar="FILE",
        help="soft method: make the wheel masks with a learned segmenter written by "
        "'sinkjax train' instead of the default segmenter with the rig's thresholds",
    )
    p.add_argument(
        "--out", default="results.csv", metavar="CSV", help="results CSV (default: results.csv)"
    )
    p.add_argument("--overlay", metavar="DIR", help="also write one overlay PNG per frame here")
    p.add_argument(
        "--summary",
        metavar="CSV",
        help="also write a campaign summary: one row per recording (rig, segmenter features, "
        "frames, ok, failures by status, median and range of z0, θ1, θ2, median σ)",
    )
    p.add_argument(
        "--rim",
        choices=("recording", "frame"),
        default="recording",
        help="recording: find the rim circle once per recording from its first frames and "
        "measure every frame with it (a camera fixed to the wheel; default); frame: each frame "
        "its own rim (a camera that moves relative to the wheel). Soft method only",
    )
    p.add_argument(
        "--batch-size",
        type=int,
        default=8,
        metavar="N",
        help="frames measured together (soft method only; default: 8)",
    )
    _add_long_run_options(p)
    g = p.add_argument_group(
        "parallel runs on Dask (pip install 'sinkjax[parallel]'): the same CSV as a serial run"
    ).add_mutually_exclusive_group()
    g.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="measure recordings (and chunks of long ones) in N local worker processes",
    )
    g.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="use a running dask.distributed cluster (tcp://host:8786); its workers must see "
        "the PATHs at the same place (a shared filesystem)",
    )
    add_cache_option(p)


def add_cache_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--no-compile-cache",
        action="store_true",
        help="do not keep the soft method's compiled code on disk (default: kept in "
        "$SINKJAX_CACHE_DIR, else ~/.cache/sinkjax/jax, so the next run starts in a second; "
        "SINKJAX_CACHE_DIR=off also turns it off)",
    )


def setup_compile_cache(args: argparse.Namespace) -> None:
    """JAX's persistent compilation cache for this command (see :mod:`.compile_cache`)."""
    enable_compile_cache(cache_dir(enabled=not args.no_compile_cache))


def _run_estimate(args: argparse.Namespace) -> int:
    if args.batch_size < 1:
        raise UsageError(f"--batch-size must be at least 1, got {args.batch_size}")
    setup_compile_cache(args)
    select, smoothing = _long_run_options(args)
    rect = parse_rect(args.confidence_rect) if args.confidence_rect is not None else None
    overrides = RigOverrides(args.wheel_radius_mm, rect, args.travel, args.encoding)
    inputs = open_recordings(args.paths, rig_path=args.rig, overrides=overrides)
    try:
        load_method(args.method)
    except MethodUnavailable as e:
        raise UsageError(str(e)) from e
    segmenter = None
    if args.segmenter is not None:
        if args.method != "soft":
            raise UsageError("--segmenter needs the soft method (--method soft)")
        from ..learn.io import load_segmenter

        # A bad file raises SegmenterFileError (a RigError) naming the file and what is wrong.
        segmenter = load_segmenter(args.segmenter)
    parallel = None
    if args.workers is not None or args.scheduler is not None:
        try:
            import_distributed()
            parallel = ParallelOptions(workers=args.workers, scheduler=args.scheduler)
        except (ParallelUnavailable, ValueError) as e:
            raise UsageError(str(e)) from e
    try:
        summary = estimate_to_csv(
            inputs,
            args.out,
            method=args.method,
            batch_size=args.batch_size,
            rim=args.rim,
            segmenter=segmenter,
            overlay_dir=args.overlay,
            overlay_video=args.overlay_video,
            select=select,
            resume=args.resume,
            smoothing=smoothing,
            summary_csv=args.summary,
            parallel=parallel,
            progress=True,
        )
    except (ResumeError, ValueError, WorkerCannotRead) as e:
        raise UsageError(str(e)) from e
    except OSError as e:
        raise UsageError(f"cannot write {e.filename or args.out}: {e.strerror or e}") from e
    if len(summary.recordings) > 1:
        print("\n".join(["rigs:", *summary.rig_lines()]))
    if lines := summary.segmenter_lines():
        print("\n".join(lines))
    print(summary.line())
    if summary.summary_csv is not None:
        print(f"summary of {len(summary.recordings)} recording(s) -> {summary.summary_csv}")
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
        raise UsageError(
            "the confidence rectangle lies off every image (see the message column of "
            f"{args.out}); fix confidence_rect in the rig or pass --confidence-rect X,Y,W,H "
            "inside the images"
        )
    return EXIT_OK


# --------------------------------------------------------------------------------------------
# long runs: frame selection, resume, overlay video, smoothing (estimate); smooth; plot


def _add_smoothing_options(p: argparse.ArgumentParser) -> None:
    from . import smoothing as S

    g = p.add_argument_group(
        "smoothing (random walk per quantity, Kalman filter + RTS smoother over the frames)"
    )
    options = (
        (
            "--process-std-mm",
            S.PROCESS_STD_MM,
            "MM",
            "how far sinkage may drift per frame, one sigma",
        ),
        (
            "--process-std-deg",
            S.PROCESS_STD_DEG,
            "DEG",
            "how far θ1, θ2 may drift per frame, one sigma",
        ),
        (
            "--measurement-std-mm",
            S.MEASUREMENT_STD_MM,
            "MM",
            "sinkage sigma for rows that have none, e.g. the classic method's",
        ),
        (
            "--measurement-std-deg",
            S.MEASUREMENT_STD_DEG,
            "DEG",
            "angle sigma for rows that have none",
        ),
    )
    for flag, default, metavar, text in options:
        g.add_argument(
            flag, type=float, default=default, metavar=metavar, help=f"{text} (default: {default})"
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
    for flag, default, metavar, text in (
        ("--start", 0, "N", "first frame index (0)"),
        ("--stop", None, "N", "stop before this frame index (end)"),
        ("--stride", 1, "K", "measure every K-th frame (1)"),
    ):
        g.add_argument(flag, type=int, default=default, metavar=metavar, help=text)
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
