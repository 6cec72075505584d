"""Frames -> results: batching, method dispatch, per-frame failure isolation, resuming.

Every input frame gets exactly one :class:`FrameResult`, in input order, and a method that raises
spoils only the frames it was working on (status ``error`` with the exception text). Rows are
appended and flushed one by one; ``resume`` skips the frames an earlier run already wrote, so an
interrupted run, resumed, leaves the same file as one that never stopped.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import importlib
import inspect
import logging
import os
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..rig import Rig
from .inputs import (
    ALL_FRAMES,
    Frame,
    FrameSelection,
    Inputs,
    check_image_size,
    check_rect,
    count_frames,
    expand_paths,
    frame_rate,
    iter_frames,
    resolve_rig,
)
from .overlay import OverlayVideoWriter, OverlayWriter
from .results import (
    BAD_IMAGE,
    BAD_RECT,
    COLUMNS,
    ERROR,
    NO_CONTACT,
    OK,
    FrameResult,
    ResultsWriter,
    failed,
)
from .smoothing import SMOOTH_COLUMNS, SmoothingOptions, smooth_csv

log = logging.getLogger("sinkjax")

METHODS = ("soft", "classic")

BatchMethod = Callable[[list[np.ndarray], Rig, list[str]], list[FrameResult]]


class MethodUnavailable(RuntimeError):
    """The requested estimator cannot be imported in this install; the message names a fix."""


def _classic_batch() -> BatchMethod:
    try:
        module = importlib.import_module("sinkjax.classic.estimator")
        estimate_classic = module.estimate_classic
    except (ImportError, AttributeError) as e:
        raise MethodUnavailable(
            f"the classic method (sinkjax.classic.estimator.estimate_classic) is not available: {e}"
        ) from e

    def run(images: list[np.ndarray], rig: Rig, names: list[str]) -> list[FrameResult]:
        return [
            estimate_classic(image, rig, name) for image, name in zip(images, names, strict=True)
        ]

    return run


def _soft_batch() -> BatchMethod:
    try:
        module = importlib.import_module("sinkjax.soft.estimator")
        estimate_batch: BatchMethod = module.estimate_batch
    except (ImportError, AttributeError) as e:
        raise MethodUnavailable(
            "the soft method (sinkjax.soft.estimator.estimate_batch) is not available in this install "
            f"({e}); use --method classic, or reinstall sinkjax"
        ) from e
    return estimate_batch


_LOADERS: dict[str, Callable[[], BatchMethod]] = {"soft": _soft_batch, "classic": _classic_batch}


def load_method(method: str) -> BatchMethod:
    """The batch function for ``method`` ("soft" or "classic").

    Raises ValueError for an unknown name and MethodUnavailable if it cannot be imported.
    """
    if method not in _LOADERS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    return _LOADERS[method]()


def _error_text(e: BaseException) -> str:
    text = str(e).strip().replace("\n", " ")
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _call(
    run: BatchMethod, images: list[np.ndarray], rig: Rig, names: list[str]
) -> list[FrameResult]:
    """``run`` on one group; raises if it fails or returns the wrong number of results."""
    results = list(run(images, rig, names))
    if len(results) != len(names):
        raise RuntimeError(f"method returned {len(results)} results for {len(names)} frames")
    # The row must carry the input's name whatever the method put there.
    return [
        r if r.image == n else dataclasses.replace(r, image=n)
        for r, n in zip(results, names, strict=True)
    ]


def _run_group(
    run: BatchMethod, images: list[np.ndarray], rig: Rig, names: list[str], *, retry: bool
) -> list[FrameResult]:
    try:
        return _call(run, images, rig, names)
    except Exception as e:
        if not retry or len(names) == 1:
            return [failed(n, ERROR, _error_text(e)) for n in names]
    # One bad frame must not spoil its batch: try each frame alone.
    out: list[FrameResult] = []
    for image, name in zip(images, names, strict=True):
        try:
            out.extend(_call(run, [image], rig, [name]))
        except Exception as e:
            out.append(failed(name, ERROR, _error_text(e)))
    return out


def _as_frame(item: Frame | tuple[str, np.ndarray]) -> Frame:
    if isinstance(item, Frame):
        return item
    name, image = item
    return Frame(str(name), image, stem=Path(str(name)).stem)


def iter_estimates(
    frames: Iterable[Frame | tuple[str, np.ndarray]],
    rig: Rig,
    *,
    method: str | BatchMethod = "soft",
    batch_size: int = 8,
) -> Iterator[tuple[Frame, FrameResult]]:
    """Each frame with its result, in input order, exactly one per frame.

    Consecutive readable frames of the same size are measured together, up to ``batch_size``
    at a time (``soft``; ``classic`` runs frame by frame). Frames that could not be read, that
    are smaller than ``MIN_IMAGE_SIDE_PX`` (``bad_image``), or whose confidence rectangle lies
    off the image (``bad_rect``), get their row without reaching the method. ``method`` may
    also be a batch function ``(images, rig, names) -> results``. Raises ValueError /
    MethodUnavailable before reading any frame.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if callable(method):
        return _iter_estimates(frames, rig, method, batch_size, retry=True)
    run = load_method(method)
    if method == "soft":
        return _iter_estimates(frames, rig, _fixed_shape(run, batch_size), batch_size, retry=True)
    return _iter_estimates(frames, rig, run, 1, retry=False)


def _fixed_shape(run: BatchMethod, batch_size: int) -> BatchMethod:
    """``run`` with every call padded to ``batch_size`` frames, where it can pad.

    A jit-compiled estimator compiles once per batch shape (tens of seconds on a CPU); a short
    batch (the end of a video, a size change, a retried frame) would otherwise compile anew.
    """
    try:
        pads = "pad_to" in inspect.signature(run).parameters
    except (TypeError, ValueError):
        pads = False
    if not pads:
        return run
    return functools.partial(run, pad_to=batch_size)  # type: ignore[call-arg]


def _iter_estimates(
    frames: Iterable[Frame | tuple[str, np.ndarray]],
    rig: Rig,
    run: BatchMethod,
    size: int,
    *,
    retry: bool,
) -> Iterator[tuple[Frame, FrameResult]]:
    # Slots keep input order: a finished row, or an index into the batch being collected.
    pending: list[tuple[Frame, FrameResult | int]] = []
    batch: list[Frame] = []

    def flush() -> Iterator[tuple[Frame, FrameResult]]:
        results: list[FrameResult] = []
        if batch:
            results = _run_group(
                run,
                [f.image for f in batch if f.image is not None],
                rig,
                [f.name for f in batch],
                retry=retry,
            )
        for frame, slot in pending:
            yield frame, results[slot] if isinstance(slot, int) else slot
        pending.clear()
        batch.clear()

    for item in frames:
        frame = _as_frame(item)
        ready: FrameResult | None = None
        if frame.image is None:
            ready = failed(frame.name, frame.status or ERROR, frame.message or "no image")
        elif (problem := check_image_size(frame.image.shape)) is not None:
            ready = failed(frame.name, BAD_IMAGE, problem)
        elif (problem := check_rect(frame.image.shape, rig)) is not None:
            ready = failed(frame.name, BAD_RECT, problem)
        if ready is not None:
            if not batch:
                yield frame, ready
                continue
            pending.append((frame, ready))
            # Finished rows (with their images, for overlays) must not pile up behind a batch.
            if len(pending) >= 2 * size + 16:
                yield from flush()
            continue
        assert frame.image is not None
        if batch and frame.image.shape != batch[0].image.shape:  # type: ignore[union-attr]
            yield from flush()
        pending.append((frame, len(batch)))
        batch.append(frame)
        if len(batch) >= size:
            yield from flush()
    yield from flush()


def estimate_stream(
    frames: Iterable[Frame | tuple[str, np.ndarray]],
    rig: Rig,
    *,
    method: str | BatchMethod = "soft",
    batch_size: int = 8,
) -> Iterator[FrameResult]:
    """Results for ``frames`` (:class:`Frame` or ``(name, RGB uint8 (H, W, 3))``), in order.

    Exactly one result per input frame; see :func:`iter_estimates` for batching and failures.
    """
    pairs = iter_estimates(frames, rig, method=method, batch_size=batch_size)
    return (result for _, result in pairs)


def estimate_paths(
    paths: Sequence[str | Path],
    rig: Rig | None = None,
    method: str | BatchMethod = "soft",
    *,
    batch_size: int = 8,
    rig_path: str | Path | None = None,
    select: FrameSelection = ALL_FRAMES,
) -> Iterator[FrameResult]:
    """Results for PATH arguments (images, directories, videos), one per frame, in order.

    ``rig`` None: ``rig_path``, else a ``rig.toml`` in the first directory. ``select``: which
    frame indices (see :class:`FrameSelection`). Raises InputError or RigError (bad arguments)
    before any frame is measured.
    """
    inputs = expand_paths(paths)
    if rig is None:
        rig = resolve_rig(inputs, rig_path=rig_path)
    frames = iter_frames(inputs.sources, select=select)
    return estimate_stream(frames, rig, method=method, batch_size=batch_size)


@dataclass
class RunSummary:
    """What a run produced: frames per status, how many had pixels, where the rows went."""

    out: Path | None
    counts: Counter[str] = field(default_factory=Counter)
    n_read: int = 0
    seconds: float = 0.0
    n_resumed: int = 0  # rows an earlier run had written (``resume``)
    smoothed: bool = False

    @property
    def n_frames(self) -> int:
        return sum(self.counts.values())

    @property
    def only_bad_rect(self) -> bool:
        """Every frame that could be read had its confidence rectangle off the image."""
        return self.n_read > 0 and self.counts[BAD_RECT] == self.n_read

    def line(self) -> str:
        """One line: ``12 frames: 10 ok, 1 no_contact; failed: 1 unreadable -> results.csv``."""
        measured = [f"{self.counts[OK]} ok"]
        if self.counts[NO_CONTACT]:
            measured.append(f"{self.counts[NO_CONTACT]} no_contact")
        failures = sorted((s, n) for s, n in self.counts.items() if s not in (OK, NO_CONTACT))
        text = f"{self.n_frames} frames: {', '.join(measured)}"
        text += "; failed: " + (", ".join(f"{n} {s}" for s, n in failures) if failures else "0")
        if self.seconds > 0 and self.n_frames:
            text += f" ({self.n_frames / self.seconds:.2f} frames/s)"
        if self.n_resumed:
            text += f"; {self.n_resumed} rows kept from the earlier run"
        if self.smoothed:
            text += "; smoothed columns added"
        return text + (f" -> {self.out}" if self.out is not None else "")


class ResumeError(ValueError):
    """``resume`` was asked for, but the output file is not a results CSV this run can extend."""


def _truncate_partial_row(path: Path) -> None:
    """Cut a row that a killed run left half-written (no final newline); it is measured again."""
    with open(path, "rb+") as f:
        f.seek(0, os.SEEK_END)
        size = f.tell()
        if size == 0:
            return
        f.seek(size - 1)
        if f.read(1) == b"\n":
            return
        # Rows are short: look back a block at a time for the last newline.
        end = size
        while end > 0:
            start = max(0, end - 65536)
            f.seek(start)
            block = f.read(end - start)
            cut = block.rfind(b"\n")
            if cut != -1:
                f.truncate(start + cut + 1)
                return
            end = start
        f.truncate(0)


def _strip_columns(path: Path, n_columns: int) -> None:
    """Rewrite ``path`` keeping its first ``n_columns`` columns (atomically)."""
    tmp = path.with_name(f".{path.name}.resume.tmp")
    with (
        open(path, newline="", encoding="utf-8") as src,
        open(tmp, "w", newline="", encoding="utf-8") as dst,
    ):
        writer = csv.writer(dst, lineterminator="\n")
        for row in csv.reader(src):
            writer.writerow(row[:n_columns])
    os.replace(tmp, path)


def prepare_resume(out_csv: str | Path) -> set[str]:
    """Make ``out_csv`` ready to be appended to; return the image names it already has.

    A missing or empty file is a fresh start (empty set; the caller writes the header). A row
    left half-written is removed; smoothed columns from an earlier ``smooth`` are dropped (they
    are recomputed over the whole file). Raises ResumeError for a file with another header.
    """
    path = Path(out_csv)
    if not path.is_file():
        return set()
    _truncate_partial_row(path)
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            return set()
        if tuple(header) not in (COLUMNS, (*COLUMNS, *SMOOTH_COLUMNS)):
            raise ResumeError(
                f"cannot resume into {path}: it is not a sinkjax results CSV (its header is "
                f"{','.join(header)[:80]!r}); pass another --out, or drop --resume to overwrite it"
            )
        done = {row[0] for row in reader if row}
    if len(header) != len(COLUMNS):
        _strip_columns(path, len(COLUMNS))
    return done


def estimate_to_csv(
    paths: Sequence[str | Path] | Inputs,
    rig: Rig,
    out_csv: str | Path,
    *,
    method: str | BatchMethod = "soft",
    batch_size: int = 8,
    overlay_dir: str | Path | None = None,
    overlay_video: str | Path | None = None,
    select: FrameSelection = ALL_FRAMES,
    resume: bool = False,
    smoothing: SmoothingOptions | None = None,
    progress: bool = False,
) -> RunSummary:
    """Measure every frame of ``paths`` and write the results CSV, one flushed row per frame.

    ``overlay_dir``: also write one overlay PNG per readable frame there; ``overlay_video``: an
    annotated MP4 (mp4v) with one video frame per row. ``select``: which frame indices (see
    :class:`FrameSelection`). ``resume``: keep the rows already in ``out_csv`` and append only
    the frames it lacks (by ``image`` name). ``smoothing``: when the run completes, add the
    smoothed columns (:mod:`sinkjax.app.smoothing`). ``progress``: a progress bar (frames/s, ETA)
    on stderr when it is a terminal. Rows already written stay if the run is interrupted.
    Raises InputError / ValueError / ResumeError / MethodUnavailable / OSError before the first
    frame for unusable arguments.
    """
    from tqdm import tqdm

    inputs = paths if isinstance(paths, Inputs) else expand_paths(paths)
    out = Path(out_csv)
    done: set[str] = set()  # filled below; the frames are read lazily, after that
    frames = iter_frames(inputs.sources, select=select, skip=done)
    pairs = iter_estimates(frames, rig, method=method, batch_size=batch_size)
    video = None
    if overlay_video is not None:
        video = OverlayVideoWriter(
            overlay_video, rig, fps=frame_rate(inputs.sources, select=select)
        )
    # Only now, with every argument checked, may the output file be touched.
    if resume:
        done.update(prepare_resume(out))
    fresh = not (resume and out.is_file() and out.stat().st_size > 0)
    out.parent.mkdir(parents=True, exist_ok=True)
    overlays = OverlayWriter(overlay_dir, rig) if overlay_dir is not None else None
    if video is not None and done:
        log.warning(
            "%s holds only the frames measured in this run (not the %d resumed rows)",
            overlay_video,
            len(done),
        )
    summary = RunSummary(out=out, n_resumed=len(done))
    start = time.perf_counter()
    total = count_frames(inputs.sources, select=select) if progress else None
    bar = tqdm(
        total=total,
        initial=min(len(done), total or 0),
        unit=" frames",
        desc=method if isinstance(method, str) else None,
        disable=None if progress else True,
    )
    try:
        with open(out, "w" if fresh else "a", newline="", encoding="utf-8") as stream:
            writer = ResultsWriter(stream, header=fresh)
            for frame, result in pairs:
                writer.write(result)
                summary.counts[result.status] += 1
                summary.n_read += frame.image is not None
                _write_overlays(frame, result, overlays, video)
                bar.update(1)
    finally:
        bar.close()
        if video is not None:
            video.close()
    summary.seconds = time.perf_counter() - start
    if smoothing is not None:
        smooth_csv(out, out, smoothing)
        summary.smoothed = True
    return summary


def _write_overlays(
    frame: Frame,
    result: FrameResult,
    overlays: OverlayWriter | None,
    video: OverlayVideoWriter | None,
) -> None:
    if overlays is not None:
        try:
            overlays.write(frame.image, result, frame.stem or Path(frame.name).stem)
        except (OSError, cv2.error) as e:
            log.warning("%s: overlay not written (%s)", frame.name, e)
    if video is not None:
        try:
            video.write(frame.image, result)
        except (OSError, cv2.error) as e:
            log.warning("%s: overlay video frame not written (%s)", frame.name, e)
