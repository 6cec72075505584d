"""Frames -> results: method dispatch, batching, per-frame failure isolation, recordings.

Every input frame gets exactly one :class:`FrameResult`, in input order, and a method that raises
spoils only the frames it was working on (status ``error`` with the exception text). Each
recording is measured with its own rig.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import inspect
import logging
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..result import FrameResult, failed, finite_or_failed, with_rect_hint
from ..rig import Rig, rect_problem
from ..status import Status

if TYPE_CHECKING:
    from ..soft.segmenter import Segmenter
from .frames import ALL_FRAMES, Frame, FrameSelection, check_image_size, iter_frames
from .sources import Inputs, Recording, Source, assign_rigs, expand_paths, with_rig

log = logging.getLogger("sinkjax")

METHODS = ("soft", "classic")

BatchMethod = Callable[[list[np.ndarray], Rig, list[str]], list[FrameResult]]


class MethodUnavailable(RuntimeError):
    """The requested estimator cannot be imported in this install; the message names a fix."""


FirstFrames = Callable[[int, int], list[np.ndarray]]


def _soft_batch(
    rim: str = "recording",
    first_frames: FirstFrames | None = None,
    segmenter: Segmenter | None = None,
) -> BatchMethod:
    try:
        module = importlib.import_module("sinkjax.soft.batch")
        recording: BatchMethod = module.SoftRecording(
            rim=rim, first_frames=first_frames, segmenter=segmenter
        )
    except (ImportError, AttributeError) as e:
        raise MethodUnavailable(
            "the soft method (sinkjax.soft.batch.SoftRecording) is not available in this "
            f"install ({e}); use --method classic, or reinstall sinkjax"
        ) from e
    return recording


def _classic_batch(rim: str = "recording", first_frames: FirstFrames | None = None) -> BatchMethod:
    try:
        module = importlib.import_module("sinkjax.classic.recording")
        recording: BatchMethod = module.ClassicRecording(first_frames)
    except (ImportError, AttributeError) as e:
        raise MethodUnavailable(
            f"the classic method (sinkjax.classic.recording.ClassicRecording) is not available: {e}"
        ) from e
    return recording


_LOADERS: dict[str, Callable[[str, FirstFrames | None], BatchMethod]] = {
    "soft": _soft_batch,
    "classic": _classic_batch,
}
RIM_MODES = ("recording", "frame")


def load_method(
    method: str,
    rim: str = "recording",
    first_frames: FirstFrames | None = None,
    segmenter: Segmenter | None = None,
) -> BatchMethod:
    """The batch function for ``method`` ("soft" or "classic") for ONE recording: call it again
    for the next recording. The soft method keeps the recording's rim (``rim`` "recording",
    found from ``first_frames(height, width)``, the recording's first readable frames of a size;
    see :class:`sinkjax.soft.batch.SoftRecording`), or measures each frame with its own
    ("frame"). ``segmenter``: the soft method's segmenter (None: the default with the rig's
    thresholds; see :class:`sinkjax.soft.segmenter.Segmenter`).

    Raises ValueError for an unknown name, a segmenter for the classic method, and
    MethodUnavailable if the method cannot be imported.
    """
    if method not in _LOADERS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if rim not in RIM_MODES:
        raise ValueError(f"unknown rim mode {rim!r}; choose one of {', '.join(RIM_MODES)}")
    if segmenter is not None:
        if method != "soft":
            raise ValueError(f"a segmenter needs the soft method, not {method!r}")
        return _soft_batch(rim, first_frames, segmenter)
    return _LOADERS[method](rim, first_frames)


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
        with_rect_hint(
            finite_or_failed(r if r.image == n else dataclasses.replace(r, image=n)),
            im,
            rig.confidence_rect,
        )
        for r, n, im in zip(results, names, images, strict=True)
    ]


def _run_group(
    run: BatchMethod, images: list[np.ndarray], rig: Rig, names: list[str], *, retry: bool
) -> list[FrameResult]:
    try:
        return _call(run, images, rig, names)
    except Exception as e:
        if not retry or len(names) == 1:
            return [failed(n, Status.ERROR, _error_text(e)) for n in names]
    # One bad frame must not spoil its batch: try each frame alone.
    out: list[FrameResult] = []
    for image, name in zip(images, names, strict=True):
        try:
            out.extend(_call(run, [image], rig, [name]))
        except Exception as e:
            out.append(failed(name, Status.ERROR, _error_text(e)))
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
    rim: str = "recording",
    first_frames: FirstFrames | None = None,
    segmenter: Segmenter | None = None,
) -> Iterator[tuple[Frame, FrameResult]]:
    """Each frame with its result, in input order, exactly one per frame.

    Consecutive readable frames of the same size are measured together, up to ``batch_size``
    at a time (``soft``; ``classic`` runs frame by frame). Frames that could not be read, that
    are smaller than ``MIN_IMAGE_SIDE_PX`` (``bad_image``), or whose confidence rectangle lies
    off the image (``bad_rect``), get their row without reaching the method. ``method`` may
    also be a batch function ``(images, rig, names) -> results``. ``frames`` are one recording
    (``rim``, ``first_frames`` and ``segmenter``: see :func:`load_method`). Raises ValueError /
    MethodUnavailable before reading any frame.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if callable(method):
        return _iter_estimates(frames, rig, method, batch_size, retry=True)
    run = load_method(method, rim, first_frames, segmenter)
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
            ready = failed(frame.name, frame.status or Status.ERROR, frame.message or "no image")
        elif (problem := check_image_size(frame.image.shape)) is not None:
            ready = failed(frame.name, Status.BAD_IMAGE, problem)
        elif (problem := rect_problem(rig.confidence_rect, *frame.image.shape[:2])) is not None:
            ready = failed(frame.name, Status.BAD_RECT, problem)
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
    rim: str = "recording",
) -> Iterator[FrameResult]:
    """Results for ``frames`` (:class:`Frame` or ``(name, RGB uint8 (H, W, 3))``) of one
    recording, in order.

    Exactly one result per input frame; see :func:`iter_estimates` for batching and failures.
    """
    pairs = iter_estimates(frames, rig, method=method, batch_size=batch_size, rim=rim)
    return (result for _, result in pairs)


def iter_recordings(
    inputs: Inputs,
    *,
    method: str | BatchMethod = "soft",
    batch_size: int = 8,
    select: FrameSelection = ALL_FRAMES,
    skip: Collection[str] = frozenset(),
    rim: str = "recording",
    segmenter: Segmenter | None = None,
) -> Iterator[tuple[Recording, Frame, FrameResult]]:
    """Every selected frame of every recording, with its result, in input order.

    Each recording is measured with its own rig (see :func:`sinkjax.app.sources.assign_rigs`)
    and, for the soft method, its own rim (``rim``, see :func:`load_method`) found from its
    first selected frames whatever ``skip`` leaves out, so a resumed run gives the rows of an
    uninterrupted one. Frames are read lazily and batches never span two recordings. Raises
    ValueError / MethodUnavailable before reading any frame, and ValueError if a recording has
    no rig.
    """
    for rec in inputs.recordings:
        if rec.rig is None:
            raise ValueError(f"recording {rec.name!r} has no rig; use assign_rigs first")
    image_index = 0
    for rec in inputs.recordings:
        assert rec.rig is not None
        frames = iter_frames(rec.sources, select=select, skip=skip, first_image_index=image_index)
        first = first_frames_reader(rec.sources, rec.rig, select, image_index)
        image_index += sum(s.kind == "image" for s in rec.sources)
        pairs = iter_estimates(
            frames,
            rec.rig,
            method=method,
            batch_size=batch_size,
            rim=rim,
            first_frames=first,
            segmenter=segmenter,
        )
        for frame, result in pairs:
            yield rec, frame, result


def first_frames_reader(
    sources: Sequence[Source], rig: Rig, select: FrameSelection, first_image_index: int
) -> FirstFrames:
    """``first_frames(height, width)``: the first frames of that size of a recording that the
    method would measure (readable, large enough, the rig's rectangle inside), at most the soft
    method's ``RIM_FRAMES``, read from the recording's start once per size."""
    found: dict[tuple[int, int], list[np.ndarray]] = {}

    def first_frames(height: int, width: int) -> list[np.ndarray]:
        from ..soft.batch import RIM_FRAMES

        if (height, width) not in found:
            images: list[np.ndarray] = []
            frames = iter_frames(sources, select=select, first_image_index=first_image_index)
            try:
                for frame in frames:
                    image = frame.image
                    if (
                        image is None
                        or image.shape[:2] != (height, width)
                        or check_image_size(image.shape) is not None
                        or rect_problem(rig.confidence_rect, height, width) is not None
                    ):
                        continue
                    images.append(image)
                    if len(images) >= RIM_FRAMES:
                        break
            finally:
                close = getattr(frames, "close", None)
                if close is not None:
                    close()
            found[(height, width)] = images
        return found[(height, width)]

    return first_frames


def estimate_paths(
    paths: Sequence[str | Path],
    rig: Rig | None = None,
    method: str | BatchMethod = "soft",
    *,
    batch_size: int = 8,
    rig_path: str | Path | None = None,
    select: FrameSelection = ALL_FRAMES,
    rim: str = "recording",
) -> Iterator[FrameResult]:
    """Results for PATH arguments (images, directories, videos), one per frame, in order.

    ``rig`` given: every recording uses it. None: each recording its own ``rig.toml``, else
    ``rig_path`` (docs/conventions.md §2). ``select``: which frame indices (see
    :class:`FrameSelection`); ``rim``: see :func:`load_method`. Raises InputError or RigError
    (bad arguments) before any frame is measured.
    """
    inputs = expand_paths(paths)
    if rig is not None:
        inputs = with_rig(inputs, rig)
    else:
        inputs = assign_rigs(inputs, rig_path=rig_path)
    pairs = iter_recordings(inputs, method=method, batch_size=batch_size, select=select, rim=rim)
    return (result for _, _, result in pairs)
