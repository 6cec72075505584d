"""Frames -> results: batching, method dispatch, and per-frame failure isolation.

Every input frame gets exactly one :class:`FrameResult`, in input order, and a method that raises
spoils only the frames it was working on (status ``error`` with the exception text).
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ._io import (
    Frame,
    Inputs,
    check_rect,
    count_frames,
    expand_paths,
    iter_frames,
    resolve_rig,
)
from ._results import BAD_RECT, ERROR, NO_CONTACT, OK, FrameResult, ResultsWriter, failed
from ._rig import Rig

log = logging.getLogger("sinkjax")

METHODS = ("soft", "classic")

BatchMethod = Callable[[list[np.ndarray], Rig, list[str]], list[FrameResult]]


class MethodUnavailable(RuntimeError):
    """The requested estimator cannot be imported in this install; the message names a fix."""


def _classic_batch() -> BatchMethod:
    try:
        module = importlib.import_module("sinkjax._classic")
        estimate_classic = module.estimate_classic
    except (ImportError, AttributeError) as e:
        raise MethodUnavailable(
            f"the classic method (sinkjax._classic.estimate_classic) is not available: {e}"
        ) from e

    def run(images: list[np.ndarray], rig: Rig, names: list[str]) -> list[FrameResult]:
        return [
            estimate_classic(image, rig, name) for image, name in zip(images, names, strict=True)
        ]

    return run


def _soft_batch() -> BatchMethod:
    try:
        module = importlib.import_module("sinkjax._soft")
        estimate_batch: BatchMethod = module.estimate_batch
    except (ImportError, AttributeError) as e:
        raise MethodUnavailable(
            "the soft method (sinkjax._soft.estimate_batch) is not available in this install "
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
    at a time (``soft``; ``classic`` runs frame by frame). Frames that could not be read, or
    whose confidence rectangle lies off the image (``bad_rect``), get their row without
    reaching the method. ``method`` may also be a batch function ``(images, rig, names) ->
    results``. Raises ValueError / MethodUnavailable before reading any frame.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if callable(method):
        return _iter_estimates(frames, rig, method, batch_size, retry=True)
    run = load_method(method)
    if method == "soft":
        return _iter_estimates(frames, rig, run, batch_size, retry=True)
    return _iter_estimates(frames, rig, run, 1, retry=False)


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
        else:
            problem = check_rect(frame.image.shape, rig)
            if problem is not None:
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
) -> Iterator[FrameResult]:
    """Results for PATH arguments (images, directories, videos), one per frame, in order.

    ``rig`` None: ``rig_path``, else a ``rig.toml`` in the first directory. Raises InputError or
    RigError (bad arguments) before any frame is measured.
    """
    inputs = expand_paths(paths)
    if rig is None:
        rig = resolve_rig(inputs, rig_path=rig_path)
    return estimate_stream(iter_frames(inputs.sources), rig, method=method, batch_size=batch_size)


@dataclass
class RunSummary:
    """What a run produced: frames per status, how many had pixels, where the rows went."""

    out: Path | None
    counts: Counter[str] = field(default_factory=Counter)
    n_read: int = 0
    seconds: float = 0.0

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
        return text + (f" -> {self.out}" if self.out is not None else "")


def estimate_to_csv(
    paths: Sequence[str | Path] | Inputs,
    rig: Rig,
    out_csv: str | Path,
    *,
    method: str | BatchMethod = "soft",
    batch_size: int = 8,
    overlay_dir: str | Path | None = None,
    progress: bool = False,
) -> RunSummary:
    """Measure every frame of ``paths`` and write the results CSV, one flushed row per frame.

    ``overlay_dir``: also write one overlay PNG per readable frame there. ``progress``: show a
    progress bar (frames, frames/s) on stderr when it is a terminal. Rows already written stay
    if the run is interrupted. Raises InputError / ValueError / MethodUnavailable / OSError
    before the first frame for unusable arguments.
    """
    from tqdm import tqdm

    from ._overlay import OverlayWriter

    inputs = paths if isinstance(paths, Inputs) else expand_paths(paths)
    pairs = iter_estimates(iter_frames(inputs.sources), rig, method=method, batch_size=batch_size)
    out = Path(out_csv)
    out.parent.mkdir(parents=True, exist_ok=True)
    overlays = OverlayWriter(overlay_dir, rig) if overlay_dir is not None else None
    summary = RunSummary(out=out)
    start = time.perf_counter()
    total = count_frames(inputs.sources) if progress else None
    with (
        open(out, "w", newline="", encoding="utf-8") as stream,
        tqdm(total=total, unit=" frames", disable=None if progress else True) as bar,
    ):
        writer = ResultsWriter(stream)
        for frame, result in pairs:
            writer.write(result)
            summary.counts[result.status] += 1
            summary.n_read += frame.image is not None
            if overlays is not None:
                try:
                    overlays.write(frame.image, result, frame.stem or Path(frame.name).stem)
                except (OSError, cv2.error) as e:
                    log.warning("%s: overlay not written (%s)", frame.name, e)
            bar.update(1)
    summary.seconds = time.perf_counter() - start
    return summary
