"""The classic method over the frames of a recording: the paper's steps, frame by frame, with
one check across frames.

The paper finds the rim in every frame on its own, and so does this. But the camera is fixed to
the wheel, so the rim's radius is the recording's: a frame whose Hough circle is far from it took
another circle for the rim (lug tips, a shadow's edge) and is reported ``implausible`` with its
numbers, never ``ok``. The recording's radius is the median over its first frames
(:data:`RIM_FRAMES`, read from the recording's start, so a resumed run or a chunk of a video
checks against the same radius as the whole run).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from ..result import FrameResult
from ..rig import Rig
from ..status import Status
from .estimator import estimate_classic, recording_radius_px
from .plausible import MAX_RADIUS_DEVIATION

# The recording's radius comes from its first this many readable frames of each image size.
RIM_FRAMES = 8

FirstFrames = Callable[[int, int], list[np.ndarray]]


class ClassicRecording:
    """The classic method for one recording, called like a batch method
    ``(images, rig, names) -> results``. ``first_frames(height, width)`` returns the
    recording's first frames of a size (None: the first frames this object is given)."""

    def __init__(self, first_frames: FirstFrames | None = None) -> None:
        self.first_frames = first_frames
        self.radius_px: dict[tuple[int, int], float | None] = {}
        # The first frames' own results, reused when the same frame comes to be measured.
        self._firsts: dict[tuple[int, int], list[tuple[np.ndarray, FrameResult]]] = {}

    def __call__(self, images: list[np.ndarray], rig: Rig, names: list[str]) -> list[FrameResult]:
        return [self._one(im, rig, n) for im, n in zip(images, names, strict=True)]

    def _learn(self, image: np.ndarray, rig: Rig) -> None:
        key = image.shape[:2]
        if self.first_frames is None:
            # Without a reader the recording's frames arrive one by one: the radius is that of
            # the frames seen so far, settled at RIM_FRAMES.
            firsts = self._firsts.setdefault(key, [])
            if len(firsts) < RIM_FRAMES:
                firsts.append((image, estimate_classic(image, rig)))
                self.radius_px[key] = recording_radius_px([r for _, r in firsts])
            return
        if key in self.radius_px:
            return
        first = self.first_frames(*key)[:RIM_FRAMES]
        firsts = [(im, estimate_classic(im, rig)) for im in first]
        self._firsts[key] = firsts
        self.radius_px[key] = recording_radius_px([r for _, r in firsts])

    def _one(self, image: np.ndarray, rig: Rig, name: str) -> FrameResult:
        key = image.shape[:2]
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            return estimate_classic(image, rig, name)
        self._learn(image, rig)
        radius = self.radius_px.get(key)
        for first, result in self._firsts.get(key, []):
            if first is image or np.array_equal(first, image):
                # The check against the recording's radius is the only difference, and it
                # applies to a measured frame whose rim is far from that radius.
                if radius is None or not _far(result, radius):
                    return dataclasses.replace(result, image=name)
                break
        return estimate_classic(image, rig, name, recording_radius_px=radius)


def _far(result: FrameResult, radius_px: float) -> bool:
    if result.status not in (Status.OK, Status.NO_CONTACT) or result.radius_px is None:
        return False
    tol = max(3.0, MAX_RADIUS_DEVIATION * radius_px)
    return not math.isclose(result.radius_px, radius_px, abs_tol=tol)
