"""Frames: pixels from image files and videos, read lazily, one frame at a time.

Every frame comes out as a :class:`Frame` holding either an RGB uint8 image of shape (H, W, 3) or
the :class:`~sinkjax.Status` and message saying why it has none. A :class:`FrameSelection`
(``--start/--stop/--stride``) picks frames by index: within each video (its frame numbers, as in
``video.mp4#000123``), and over the image files of a run taken together in input order. Frames
left out are never decoded, and frames named in ``skip`` (``--resume``) are passed over the same
way.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..status import Status
from .image_file import BadImageError, read_image, to_rgb8

__all__ = ["read_image", "to_rgb8"]  # re-exported: their home before image_file
from .sources import Source, expand_paths

log = logging.getLogger("sinkjax")

# Smaller frames cannot show a measurable wheel; they get ``bad_image`` before any estimator runs.
MIN_IMAGE_SIDE_PX = 16
# Overlay videos of image sequences have no frame rate of their own.
DEFAULT_FPS = 10.0


@dataclass
class Frame:
    """One frame to measure: an RGB uint8 (H, W, 3) ``image``, or ``status``/``message`` why not.

    ``stem`` names its overlay file (``frame_001``, ``video_000123``).
    """

    name: str
    image: np.ndarray | None
    status: str = ""
    message: str = ""
    stem: str = ""


@dataclass(frozen=True)
class FrameSelection:
    """Frame indices to measure: ``start <= i < stop`` (``stop`` None: to the end), every
    ``stride``-th from ``start`` -- Python's ``range(start, stop, stride)``.

    Applies to each video's frame numbers and to the run's image files as one sequence.
    Raises ValueError (naming the flag) for a negative start, stride < 1 or stop <= start.
    """

    start: int = 0
    stop: int | None = None
    stride: int = 1

    def __post_init__(self) -> None:
        if self.start < 0:
            raise ValueError(f"--start must be >= 0 (a frame index), got {self.start}")
        if self.stride < 1:
            raise ValueError(f"--stride must be >= 1 (1 = every frame), got {self.stride}")
        if self.stop is not None and self.stop <= self.start:
            raise ValueError(
                f"--stop ({self.stop}) must be greater than --start ({self.start}); "
                "--stop is the first frame index NOT measured"
            )

    @property
    def everything(self) -> bool:
        return self.start == 0 and self.stop is None and self.stride == 1

    def __contains__(self, index: object) -> bool:
        if not isinstance(index, int) or index < self.start:
            return False
        if self.stop is not None and index >= self.stop:
            return False
        return (index - self.start) % self.stride == 0

    def past_end(self, index: int) -> bool:
        """True once ``index`` and every later index are outside the selection."""
        return self.stop is not None and index >= self.stop

    def count(self, n: int) -> int:
        """How many of the indices ``0 .. n-1`` are selected."""
        return len(range(self.start, n if self.stop is None else min(n, self.stop), self.stride))


ALL_FRAMES = FrameSelection()


def check_image_size(shape: tuple[int, ...]) -> str | None:
    """None if an image of ``shape`` is big enough to measure; else why not (``bad_image``)."""
    height, width = int(shape[0]), int(shape[1])
    if height >= MIN_IMAGE_SIDE_PX and width >= MIN_IMAGE_SIDE_PX:
        return None
    return (
        f"image is only {width}x{height} px; sinkjax needs at least "
        f"{MIN_IMAGE_SIDE_PX}x{MIN_IMAGE_SIDE_PX} px to find a wheel in it"
    )


def _image_frame(source: Source) -> Frame:
    stem = source.path.stem
    try:
        image = read_image(source.path)
    except OSError as e:
        reason = f"cannot read file: {e.strerror or e}"
        if source.path.is_symlink() and not source.path.exists():
            reason = f"broken symbolic link (to {os.readlink(source.path)!r}): {reason}"
        return Frame(source.name, None, Status.UNREADABLE, reason, stem)
    except BadImageError as e:
        return Frame(source.name, None, Status.BAD_IMAGE, str(e), stem)
    except ValueError as e:
        return Frame(source.name, None, Status.UNREADABLE, str(e), stem)
    return Frame(source.name, image, stem=stem)


def _video_frames(source: Source, select: FrameSelection, skip: Collection[str]) -> Iterator[Frame]:
    capture = cv2.VideoCapture(str(source.path))
    try:
        if not capture.isOpened():
            if source.name not in skip:
                yield Frame(
                    source.name,
                    None,
                    Status.UNREADABLE,
                    "could not open the video (corrupt, empty, or a codec OpenCV lacks)",
                    source.path.stem,
                )
            return
        index = 0
        while not select.past_end(index):
            name = f"{source.name}#{index:06d}"
            if index not in select or name in skip:
                # grab() advances without converting to BGR: skipping is cheap and exact, where
                # seeking (CAP_PROP_POS_FRAMES) may land on the wrong frame in some containers.
                if not capture.grab():
                    break
                index += 1
                continue
            ok, bgr = capture.read()
            if not ok or bgr is None:
                break
            stem = f"{source.path.stem}_{index:06d}"
            try:
                yield Frame(name, to_rgb8(bgr, bgr=True), stem=stem)
            except ValueError as e:
                yield Frame(name, None, Status.BAD_IMAGE, str(e), stem)
            index += 1
        expected = capture.get(cv2.CAP_PROP_FRAME_COUNT)
        if index == 0:
            if source.name not in skip:
                yield Frame(
                    source.name,
                    None,
                    Status.UNREADABLE,
                    "the video has no decodable frames",
                    source.path.stem,
                )
        elif select.count(index) == 0:
            log.warning(
                "%s: --start %d selects none of its %d frames", source.name, select.start, index
            )
        elif not select.past_end(index):
            if math.isfinite(expected) and expected > 0 and index < 0.95 * expected:
                log.warning(
                    "%s: decoding stopped after %d of %d frames (truncated or corrupt video?)",
                    source.name,
                    index,
                    int(expected),
                )
    finally:
        capture.release()


def iter_frames(
    sources: Sequence[Source],
    *,
    select: FrameSelection = ALL_FRAMES,
    skip: Collection[str] = frozenset(),
    first_image_index: int = 0,
) -> Iterator[Frame]:
    """Frames of ``sources`` in order, read lazily: one image or one video frame at a time.

    ``select`` picks frame indices (see :class:`FrameSelection`); frames whose name is in
    ``skip`` (rows already in a results CSV) are left out without decoding them.
    ``first_image_index``: the run-wide index of the first image file among ``sources`` (image
    indices count over all recordings of a run together).
    """
    image_index = first_image_index
    for source in sources:
        if source.kind == "video":
            yield from _video_frames(source, select, skip)
            continue
        index, image_index = image_index, image_index + 1
        if index in select and source.name not in skip:
            yield _image_frame(source)


def _video_property(path: Path, prop: int) -> float:
    """One property of a video container (0.0 when OpenCV cannot open it)."""
    capture = cv2.VideoCapture(str(path))
    try:
        return float(capture.get(prop)) if capture.isOpened() else 0.0
    finally:
        capture.release()


def count_frames(sources: Sequence[Source], *, select: FrameSelection = ALL_FRAMES) -> int:
    """The number of frames to expect (video containers' frame counts; may be approximate)."""
    n_images = 0
    total = 0
    for source in sources:
        if source.kind != "video":
            n_images += 1
            continue
        n = _video_property(source.path, cv2.CAP_PROP_FRAME_COUNT)
        total += select.count(int(n)) if math.isfinite(n) and n > 0 else 1
    return total + select.count(n_images)


def frame_rate(sources: Sequence[Source], *, select: FrameSelection = ALL_FRAMES) -> float:
    """Frames per second for an overlay video: the first video's rate over ``stride``, else
    :data:`DEFAULT_FPS`."""
    for source in sources:
        if source.kind != "video":
            continue
        fps = _video_property(source.path, cv2.CAP_PROP_FPS)
        if math.isfinite(fps) and fps > 0:
            return max(fps / select.stride, 1.0)
    return DEFAULT_FPS


def read_frames(
    paths: Sequence[str | Path], *, select: FrameSelection = ALL_FRAMES
) -> Iterator[Frame]:
    """Frames of PATH arguments in order: :func:`expand_paths`, then :func:`iter_frames`."""
    return iter_frames(expand_paths(paths).sources, select=select)
