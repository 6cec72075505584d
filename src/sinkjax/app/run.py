"""A run: recordings -> the results CSV (one flushed row per frame), overlays, summary."""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2

from ..result import FrameResult
from ..rig import Rig
from ..status import Status
from .compile_cache import CompileClock, compile_notices
from .frames import ALL_FRAMES, Frame, FrameSelection, count_frames, frame_rate
from .overlay import OverlayVideoWriter, OverlayWriter
from .parallel import ParallelOptions, ParallelRun, plan_tasks
from .pipeline import BatchMethod, iter_recordings, load_method
from .results import ResultsWriter
from .resume import prepare_resume
from .smoothing import SmoothingOptions, smooth_csv
from .sources import Inputs, Recording, expand_paths, open_recordings, with_rig
from .summary import describe_features, write_summary

if TYPE_CHECKING:
    from ..soft.segmenter import Segmenter

log = logging.getLogger("sinkjax")


@dataclass
class RunSummary:
    """What a run produced: frames per status, how many had pixels, where the rows went, and
    per recording its rig and which features its segmenter chose on how many frames."""

    out: Path | None
    counts: Counter[str] = field(default_factory=Counter)
    n_read: int = 0
    seconds: float = 0.0
    n_resumed: int = 0  # rows an earlier run had written (``resume``)
    smoothed: bool = False
    # Part of ``seconds`` spent compiling (tracing, lowering, compiling or loading from the
    # persistent cache), summed over the processes of a parallel run.
    compile_seconds: float = 0.0
    summary_csv: Path | None = None  # the campaign summary, if one was asked for
    workers: bool = False  # measured on a Dask cluster (compile time summed over its workers)

    @property
    def n_frames(self) -> int:
        return sum(self.counts.values())

    recordings: list[tuple[str, str]] = field(default_factory=list)  # (recording, its rig)
    # Per recording: frames of this run per segmenter features (FrameResult.segmenter_features).
    features: dict[str, Counter[str]] = field(default_factory=dict)

    @property
    def only_bad_rect(self) -> bool:
        """Every frame that could be read had its confidence rectangle off the image."""
        return self.n_read > 0 and self.counts[Status.BAD_RECT] == self.n_read

    def rig_lines(self) -> list[str]:
        """One line per recording: which rig it was measured with."""
        return [f"  {name}: rig {source}" for name, source in self.recordings]

    def segmenter_lines(self) -> list[str]:
        """Which features separated wheel from soil, on how many of this run's frames: one
        line for one recording (``segmenter: hue+saturation (12 frames)``), else a heading and
        a line per recording (``  runB: intensity+texture (10), hue+saturation (2)``); no line
        when no frame was segmented (none could be read, or all were resumed)."""
        if not any(self.features.values()):
            return []
        heading = "segmenter" + (" (frames measured in this run)" if self.n_resumed else "")
        if len(self.recordings) == 1:
            name = self.recordings[0][0]
            return [f"{heading}: {describe_features(self.features.get(name, {}))}"]
        lines = [f"{heading}:"]
        for name, _ in self.recordings:
            text = describe_features(self.features.get(name, {}))
            lines.append(f"  {name}: {text or 'no frame segmented'}")
        return lines

    def line(self) -> str:
        """One line: ``12 frames: 10 ok, 1 no_contact; failed: 1 unreadable -> results.csv``."""
        measured = [f"{self.counts[Status.OK]} ok"]
        if self.counts[Status.NO_CONTACT]:
            measured.append(f"{self.counts[Status.NO_CONTACT]} no_contact")
        failures = sorted((s, n) for s, n in self.counts.items() if not Status(s).measured)
        text = f"{self.n_frames} frames: {', '.join(measured)}"
        text += "; failed: " + (", ".join(f"{n} {s}" for s, n in failures) if failures else "0")
        if self.seconds > 0 and self.n_frames:
            text += f" ({self.n_frames / self.seconds:.2f} frames/s"
            if self.compile_seconds > 0:
                text += f"; {self.seconds:.1f} s, " + (
                    f"workers compiling {self.compile_seconds:.1f} s in all"
                    if self.workers
                    else f"of which compiling {self.compile_seconds:.1f} s"
                )
            text += ")"
        if self.n_resumed:
            text += f"; {self.n_resumed} rows kept from the earlier run"
        if self.smoothed:
            text += "; smoothed columns added"
        return text + (f" -> {self.out}" if self.out is not None else "")


def estimate_to_csv(
    paths: Sequence[str | Path] | Inputs,
    out_csv: str | Path,
    *,
    rig: Rig | None = None,
    rig_path: str | Path | None = None,
    method: str | BatchMethod = "soft",
    batch_size: int = 8,
    rim: str = "recording",
    segmenter: Segmenter | None = None,
    overlay_dir: str | Path | None = None,
    overlay_video: str | Path | None = None,
    select: FrameSelection = ALL_FRAMES,
    resume: bool = False,
    smoothing: SmoothingOptions | None = None,
    summary_csv: str | Path | None = None,
    parallel: ParallelOptions | None = None,
    progress: bool = False,
) -> RunSummary:
    """Measure every frame of ``inputs`` and write the results CSV, one flushed row per frame.

    ``paths``: PATH arguments, or recordings with their rigs
    (:func:`sinkjax.app.sources.open_recordings`). For PATHs, ``rig`` (if given) serves every
    recording; else each uses its own ``rig.toml``, then ``rig_path`` (docs/conventions.md §2).
    ``rim``: "recording" (the soft method finds each recording's rim once, from its first
    frames) or "frame" (each frame its own; a moving camera). ``segmenter``: the soft method's
    segmenter (e.g. :func:`sinkjax.learn.load_segmenter`); None: the default.
    ``overlay_dir``: also write one overlay PNG per readable frame there; ``overlay_video``: an
    annotated MP4 (mp4v) with one video frame per row. ``select``: which frame indices (see
    :class:`FrameSelection`). ``resume``: keep the rows already in ``out_csv`` and append only
    the frames it lacks (by ``image`` name). ``smoothing``: when the run completes, add the
    smoothed columns (:mod:`sinkjax.app.smoothing`). ``summary_csv``: when the run completes,
    write the campaign summary there (:mod:`sinkjax.app.summary`; its ``segmenter`` column, as
    :meth:`RunSummary.segmenter_lines`, counts this run's frames). ``parallel``: measure on a
    Dask cluster (:mod:`sinkjax.app.parallel`; the same rows, written here in the same order;
    overlays are written by the workers, ``overlay_video`` needs a serial run). ``progress``:
    a progress bar (frames/s, ETA) on stderr when it is a terminal. Rows already written stay
    if the run is interrupted.
    Raises InputError / ValueError / ResumeError / MethodUnavailable / OSError before the first
    frame for unusable arguments.
    """
    from tqdm import tqdm

    if isinstance(paths, Inputs):
        inputs = paths
    elif rig is not None:
        inputs = with_rig(expand_paths(paths), rig)
    else:
        inputs = open_recordings(paths, rig_path=rig_path)
    out = Path(out_csv)
    check_output(out, inputs, overlay_dir=overlay_dir, overlay_video=overlay_video)
    if summary_csv is not None:
        check_summary_output(Path(summary_csv), out, inputs)
    if parallel is not None and overlay_video is not None:
        raise ValueError(
            "--overlay-video is drawn from the frames in this process: drop it, or run without "
            "--workers/--scheduler"
        )
    if (parallel is not None or segmenter is not None) and isinstance(method, str):
        # An unknown or missing method, or a segmenter for classic, fails here, not on every
        # worker (or after the output was opened).
        load_method(method, rim, segmenter=segmenter)
    done: set[str] = set()  # filled below; the frames are read lazily, after that
    # Only now, with every argument checked, may an output be touched; prepare_resume checks
    # the whole file before it changes a byte of it.
    if resume:
        done.update(prepare_resume(out))
    video = None
    if overlay_video is not None:
        video = OverlayVideoWriter(overlay_video, fps=frame_rate(inputs.sources, select=select))
    fresh = not (resume and out.is_file() and out.stat().st_size > 0)
    out.parent.mkdir(parents=True, exist_ok=True)
    overlays = OverlayWriter(overlay_dir) if overlay_dir is not None else None
    if video is not None and done:
        log.warning(
            "%s holds only the frames measured in this run (not the %d resumed rows)",
            overlay_video,
            len(done),
        )
    summary = RunSummary(out=out, n_resumed=len(done))
    summary.recordings = [(rec.name, rec.rig_source) for rec in inputs.recordings]
    start = time.perf_counter()
    total = count_frames(inputs.sources, select=select) if progress else None
    bar = tqdm(
        total=total,
        initial=min(len(done), total or 0),
        unit=" frames",
        desc=method if isinstance(method, str) else None,
        disable=None if progress else True,
    )
    clock = CompileClock()
    runner = ParallelRun(parallel) if parallel is not None else None
    try:
        with (
            open(
                out, "w" if fresh else "a", newline="", encoding="utf-8", errors="surrogateescape"
            ) as stream,
            clock,
            compile_notices(_CompileNote(bar)),
            runner or contextlib.nullcontext(),
        ):
            writer = ResultsWriter(stream, header=fresh)
            rows: Iterator[tuple[Recording, FrameResult, bool, Frame | None]]
            if runner is None:
                pairs = iter_recordings(
                    inputs,
                    method=method,
                    batch_size=batch_size,
                    select=select,
                    skip=done,
                    rim=rim,
                    segmenter=segmenter,
                )
                rows = (
                    (rec, result, frame.image is not None, frame) for rec, frame, result in pairs
                )
            else:
                rows = _parallel_rows(
                    runner, inputs, method, batch_size, select, done, overlay_dir, rim, segmenter
                )
            for rec, result, was_read, frame in rows:
                writer.write(result)
                summary.counts[result.status] += 1
                if result.segmenter_features:
                    summary.features.setdefault(rec.name, Counter())[result.segmenter_features] += 1
                summary.n_read += was_read
                if frame is not None:
                    _write_overlays(rec, frame, result, overlays, video)
                bar.update(1)
    finally:
        bar.close()
        if video is not None:
            video.close()
    summary.seconds = time.perf_counter() - start
    summary.compile_seconds = clock.seconds + (runner.compile_seconds if runner else 0.0)
    summary.workers = runner is not None
    if smoothing is not None:
        smooth_csv(out, out, smoothing)
        summary.smoothed = True
    if summary_csv is not None:
        summary.summary_csv = write_summary(out, inputs, summary_csv, summary.features)
    return summary


class _CompileNote:
    """A :func:`~sinkjax.app.compile_cache.compile_notices` listener: while the soft method is
    compiled for a new image size (tens of seconds the first time), the bar says so; the wait
    is left out of its rate, ETA and elapsed time (which would otherwise read the compile as
    the first frame's time), and the bar says how long the run's compiles took."""

    PREPARING = "preparing the soft method for {}x{} frames (once per image size, then cached)"
    PREPARED = "prepared in {:.0f} s, not counted in the rate"

    def __init__(self, bar: Any) -> None:
        self._bar, self._open, self._lock = bar, 0, threading.Lock()
        self._began = self._spent = 0.0

    def __call__(self, size: tuple[int, int] | None, started: bool) -> None:
        with self._lock:
            self._began = time.perf_counter() if started and not self._open else self._began
            self._open += 1 if started else -1
            if started and size is not None:
                self._bar.set_postfix_str(self.PREPARING.format(*size))
            elif not started and not self._open:
                self._spent += time.perf_counter() - self._began
                self._bar.set_postfix_str(self.PREPARED.format(self._spent))
                self._bar.unpause()


def _parallel_rows(
    runner: ParallelRun,
    inputs: Inputs,
    method: str | BatchMethod,
    batch_size: int,
    select: FrameSelection,
    done: set[str],
    overlay_dir: str | Path | None,
    rim: str,
    segmenter: Segmenter | None,
) -> Iterator[tuple[Recording, FrameResult, bool, Frame | None]]:
    tasks = plan_tasks(
        inputs,
        method=method,
        batch_size=batch_size,
        rim=rim,
        segmenter=segmenter,
        select=select,
        skip=done,
        chunk_frames=runner.options.chunk_frames,
        overlay_dir=overlay_dir,
    )
    for task, result in runner.results(tasks):
        rec = inputs.recordings[task.recording]
        for row, was_read in result.rows:
            yield rec, row, was_read, None


def check_output(
    out: Path,
    inputs: Inputs,
    *,
    overlay_dir: str | Path | None = None,
    overlay_video: str | Path | None = None,
) -> None:
    """Every check of a run's outputs, made before any work: raise ValueError if the results CSV
    or the overlay video would overwrite an input or each other, is a folder, or lies in a folder
    that cannot be written; or if the overlay folder is a file or holds input images (overlays
    are named after their frames and would replace them)."""
    inputs_at = {_resolved(s.path): s.name for s in inputs.sources}
    files = [("--out", out)]
    if overlay_video is not None:
        files.append(("--overlay-video", Path(overlay_video)))
        if _resolved(Path(overlay_video)) == _resolved(out):
            raise ValueError(f"--overlay-video and --out both name {str(out)!r}")
    for flag, path in files:
        if _resolved(path) in inputs_at:
            raise ValueError(
                f"{flag} {str(path)!r} is one of the inputs ({inputs_at[_resolved(path)]}); "
                "choose another file"
            )
        if path.is_dir():
            raise ValueError(f"{flag} {str(path)!r} is a folder; name a file in it")
        check_writable_folder(path.parent, flag)
    if overlay_dir is not None:
        folder = Path(overlay_dir)
        if folder.exists() and not folder.is_dir():
            raise ValueError(f"--overlay {str(folder)!r} is a file, not a folder")
        here = _resolved(folder)
        held = [
            s.name for s in inputs.sources if s.kind == "image" and _resolved(s.path).parent == here
        ]
        if held:
            raise ValueError(
                f"--overlay {str(folder)!r} holds input images ({held[0]}); overlays named after "
                "them would replace them, choose another folder"
            )
        check_writable_folder(folder, "--overlay")


def check_summary_output(path: Path, out: Path, inputs: Inputs) -> None:
    """Raise ValueError if the ``--summary`` file would overwrite an input or the results CSV,
    is a folder, or lies in a folder that cannot be written."""
    if _resolved(path) == _resolved(out):
        raise ValueError(f"--summary and --out both name {str(out)!r}")
    if _resolved(path) in {_resolved(s.path) for s in inputs.sources}:
        raise ValueError(f"--summary {str(path)!r} is one of the inputs; choose another file")
    if path.is_dir():
        raise ValueError(f"--summary {str(path)!r} is a folder; name a file in it")
    check_writable_folder(path.parent, "--summary")


def _resolved(path: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError):  # a symlink loop
        return path.absolute()


def check_writable_folder(folder: Path, flag: str) -> None:
    """Raise ValueError unless ``folder`` is, or can be made as, a folder we may write into."""
    existing = folder if str(folder) else Path(".")
    while not existing.exists() and existing != existing.parent:
        if existing.is_symlink():
            raise ValueError(f"{flag}: {str(existing)!r} is a broken symbolic link")
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"{flag}: {str(existing)!r} is not a folder, so nothing can go in it")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"{flag}: no permission to write into folder {str(existing)!r}")


def _write_overlays(
    rec: Recording,
    frame: Frame,
    result: FrameResult,
    overlays: OverlayWriter | None,
    video: OverlayVideoWriter | None,
) -> None:
    if overlays is not None:
        try:
            overlays.write(frame.image, result, frame.stem or Path(frame.name).stem, rec.rig)
        except (OSError, cv2.error) as e:
            log.warning("%s: overlay not written (%s)", frame.name, e)
    if video is not None:
        try:
            video.write(frame.image, result, rec.rig)
        except (OSError, cv2.error) as e:
            log.warning("%s: overlay video frame not written (%s)", frame.name, e)
