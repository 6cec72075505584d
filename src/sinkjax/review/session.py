"""What a review page shows: recordings, their frames and rigs, results, and label starts.

A :class:`ReviewSession` is built from the ``sinkjax review`` PATH arguments (conventions §2: a
directory of images uses its own ``rig.toml``; image files given one by one form one recording
per folder and use the ``rig.toml`` there; ``--rig`` serves inputs that have none). It holds one
result per frame (read from a results CSV or measured on demand), serves only the frame files of
its recordings, and proposes where labelling starts: the estimate when there is one, else a rim
circle from the soft method's Hough stage.
"""

from __future__ import annotations

import csv
import functools
import math
import os
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np

from ..app.frames import read_image
from ..app.results import COLUMNS
from ..app.sources import InputError, assign_rigs, expand_paths
from ..geometry import from_wheel_frame
from ..result import FrameResult
from ..rig import Rig, srgb_flag
from ..status import Status
from .labels import LabelStore, rim_chord
from .suspicion import suspicion

LABELS_FILENAME = "LABELS.csv"
# Where labelling starts without an estimate: A and B this far from the bottom of the rim.
_DEFAULT_ANGLE_DEG = 30.0


@dataclass
class Recording:
    """One camera set-up: a folder (``root``, whose frame files may be served) and its rig."""

    root: Path
    rig: Rig


@dataclass(frozen=True)
class ReviewFrame:
    """One frame: ``name`` is its results ``image`` cell, ``path`` its file, ``url`` where the
    page fetches it."""

    index: int
    name: str
    path: Path
    recording: int
    url: str


def _number(cell: str | None) -> float | None:
    try:
        value = float(cell) if cell not in (None, "") else None
    except ValueError:
        return None
    return value if value is not None and math.isfinite(value) else None


class ReviewSession:
    """Frames, rigs, results and labels behind one review page. Thread-safe for the server."""

    def __init__(
        self,
        paths: Sequence[str | Path],
        *,
        results: str | Path | None = None,
        labels: str | Path | None = None,
        rig_path: str | Path | None = None,
        method: str = "soft",
    ) -> None:
        self.recordings: list[Recording] = []
        self.frames: list[ReviewFrame] = []
        self.method = method
        self._lock = threading.Lock()
        self._guesses: dict[int, dict[str, Any]] = {}
        for arg in paths:
            self._add(str(arg), rig_path)
        self._served = {
            f.path.resolve(): f for f in self.frames if self._inside(f.path, f.recording)
        }
        self.results: list[FrameResult | None] = [None] * len(self.frames)
        self.results_path = Path(results) if results is not None else None
        if self.results_path is not None:
            self.load_results(self.results_path)
        self.labels = LabelStore(labels or self.recordings[0].root / LABELS_FILENAME)

    def _add(self, arg: str, rig_path: str | Path | None) -> None:
        inputs = expand_paths([arg])
        if any(s.kind != "image" for s in inputs.sources):
            raise InputError(f"{arg!r}: review shows image files; extract a video's frames first")
        root = Path(arg) if Path(arg).is_dir() else Path(arg).parent
        root = root.absolute()
        index = next((i for i, r in enumerate(self.recordings) if r.root == root), None)
        if index is None:
            # The rig of the recording (its folder's rig.toml, else --rig): conventions §2.
            rig = assign_rigs(inputs, rig_path=rig_path).recordings[0].rig
            assert rig is not None
            self.recordings.append(Recording(root, rig))
            index = len(self.recordings) - 1
        for source in inputs.sources:
            rel = Path(os.path.relpath(source.path.absolute(), root)).as_posix()
            url = f"/files/{index}/{quote(rel, errors='surrogateescape')}"
            self.frames.append(ReviewFrame(len(self.frames), source.name, source.path, index, url))

    def _inside(self, path: Path, recording: int) -> bool:
        return path.resolve().is_relative_to(self.recordings[recording].root.resolve())

    # ---------------------------------------------------------------------------- files

    def file_for(self, recording: int, relative: str) -> Path:
        """The frame file at ``relative`` in a recording. Raises PermissionError for anything
        outside the recording's folder (``..``, a symlink out of it) and LookupError for a file
        that is not one of its frames."""
        if not 0 <= recording < len(self.recordings):
            raise LookupError(f"no recording {recording}; there are {len(self.recordings)}")
        root = self.recordings[recording].root.resolve()
        target = (root / relative).resolve()
        if not target.is_relative_to(root):
            raise PermissionError(f"{relative!r} lies outside the recording's folder")
        frame = self._served.get(target)
        if frame is None or frame.recording != recording:
            raise LookupError(f"{relative!r} is not a frame of recording {recording}")
        return target

    def frame(self, index: int) -> ReviewFrame:
        if not 0 <= index < len(self.frames):
            raise LookupError(f"no frame {index}; frames are 0 to {len(self.frames) - 1}")
        return self.frames[index]

    def rig_of(self, index: int) -> Rig:
        return self.recordings[self.frame(index).recording].rig

    # ---------------------------------------------------------------------------- results

    def load_results(self, path: Path) -> int:
        """Read a results CSV (conventions §4) and match its rows to the frames by ``image``
        (as written, then the file it names, then a unique file name); returns rows matched."""
        try:
            with path.open(newline="", encoding="utf-8", errors="surrogateescape") as fh:
                rows = list(csv.DictReader(fh))
        except OSError as e:
            raise InputError(f"cannot read --results {str(path)!r}: {e.strerror or e}") from e
        by_name = {f.name: f.index for f in self.frames}
        by_file = {f.path.resolve(): f.index for f in self.frames}
        stems: dict[str, list[int]] = {}
        for f in self.frames:
            stems.setdefault(f.path.name, []).append(f.index)
        matched = 0
        for row in rows:
            image = row.get("image") or ""
            i = by_name.get(image)
            if i is None:
                i = by_file.get(Path(image).resolve())
            if i is None and len(stems.get(Path(image).name, [])) == 1:
                i = stems[Path(image).name][0]
            if i is None or row.get("status") not in set(Status):
                continue
            values = {c: _number(row.get(c)) for c in _NUMERIC}
            self.results[i] = FrameResult(
                image=self.frames[i].name,
                status=Status(row["status"]),
                message=row.get("message") or "",
                **values,  # type: ignore[arg-type]
            )
            matched += 1
        return matched

    def set_results(self, indices: Sequence[int], results: Sequence[FrameResult]) -> None:
        with self._lock:
            for i, r in zip(indices, results, strict=True):
                self.results[i] = r
                self._guesses.pop(i, None)

    def measure(
        self,
        indices: Sequence[int] | None = None,
        *,
        progress: Callable[[int, int], None] | None = None,
    ) -> None:
        """Measure frames (all by default) with each recording's rig; results replace the old."""
        from .. import estimate_paths

        todo = list(range(len(self.frames)) if indices is None else indices)
        done = 0
        for rec, recording in enumerate(self.recordings):
            mine = [i for i in todo if self.frames[i].recording == rec]
            if not mine:
                continue
            paths = [str(self.frames[i].path) for i in mine]
            results = estimate_paths(paths, recording.rig, self.method)
            for i, result in zip(mine, results, strict=True):
                self.set_results([i], [result])
                done += 1
                if progress is not None:
                    progress(done, len(todo))

    def result_json(self, index: int) -> dict[str, Any] | None:
        r = self.results[index]
        if r is None:
            return None
        out: dict[str, Any] = {c: getattr(r, c) for c in ("status", "message", *_NUMERIC)}
        ov = r.overlay
        if ov is not None:
            boundary = ov.boundary_px
            out["overlay"] = {
                "boundary_px": [] if boundary is None else np.asarray(boundary).tolist(),
                "line_px": ov.line_px,
                "a_px": ov.a_px,
                "b_px": ov.b_px,
            }
        return out

    def table(self) -> list[dict[str, Any]]:
        """One entry per frame: result, suspicion score and reasons (see :mod:`.suspicion`)."""
        with self._lock:
            results = list(self.results)
        groups = [f.recording for f in self.frames]
        flags = suspicion(results, groups)
        return [
            {"index": f.index, "result": self.result_json(f.index), **flags[f.index].as_json()}
            for f in self.frames
        ]

    # ---------------------------------------------------------------------------- labelling

    def label_start(self, index: int) -> dict[str, Any]:
        """Where labelling a frame starts (image px): the estimate's rim, A, B and line when
        there is one; else the Hough rim guess with A and B 30 degrees either side of the
        bottom and the line through them."""
        rig, result = self.rig_of(index), self.results[index]
        if result is not None and result.radius_px is not None and result.center_x_px is not None:
            start = _from_result(result, rig)
        else:
            start = self._guess(index, rig)
        return start

    def _guess(self, index: int, rig: Rig) -> dict[str, Any]:
        if index not in self._guesses:
            image = read_image(self.frame(index).path)
            circle = rim_guess(image, rig)
            if circle is None:
                h, w = image.shape[:2]
                start = _around((w / 2, h / 2), 0.3 * min(h, w), rig, "default")
            else:
                start = _around(circle[:2], circle[2], rig, "rim guess")
            self._guesses[index] = start
        return self._guesses[index]


# The numeric columns of a results row (conventions §4).
_NUMERIC = tuple(c for c in COLUMNS if c not in ("image", "status", "message"))


def _on_rim(theta_deg: float, side: float, centre, r: float, travel: str) -> list[float]:
    # side +1: A (entry side, +u), -1: B; angle from the downward vertical (conventions §1).
    t = math.radians(theta_deg)
    x, y = from_wheel_frame(side * r * math.sin(t), r * math.cos(t), centre[0], centre[1], travel)
    return [float(x), float(y)]


def _around(centre, r: float, rig: Rig, source: str, t1=None, t2=None, z0_px=None):
    t1 = _DEFAULT_ANGLE_DEG if t1 is None else t1
    t2 = _DEFAULT_ANGLE_DEG if t2 is None else t2
    a = _on_rim(t1, 1.0, centre, r, rig.travel)
    b = _on_rim(t2, -1.0, centre, r, rig.travel)
    # The chord A-B in the wheel frame; its offset from O is r - z0 where z0 is known.
    ua, va = math.sin(math.radians(t1)) * r, math.cos(math.radians(t1)) * r
    ub, vb = -math.sin(math.radians(t2)) * r, math.cos(math.radians(t2)) * r
    k = (va - vb) / (ua - ub) if abs(ua - ub) > 1e-9 else 0.0
    offset = vb - k * ub
    if z0_px is not None:
        offset = (r - z0_px) * math.sqrt(k * k + 1.0)
    soil = [list(p) for p in rim_chord(k, offset, r, tuple(centre), rig.travel)]
    return {
        "centre_px": [float(centre[0]), float(centre[1])],
        "radius_px": float(r),
        "a_px": a,
        "b_px": b,
        "soil_px": soil,
        "source": source,
    }


def _from_result(result: FrameResult, rig: Rig) -> dict[str, Any]:
    centre = (float(result.center_x_px), float(result.center_y_px))  # type: ignore[arg-type]
    r = float(result.radius_px)  # type: ignore[arg-type]
    measured = result.status == Status.OK and result.sinkage_mm is not None
    if not measured:
        return _around(centre, r, rig, "estimate (rim only)")
    z0_px = result.sinkage_mm * r / rig.wheel_radius_mm  # type: ignore[operator]
    start = _around(centre, r, rig, "estimate", result.theta1_deg, result.theta2_deg, z0_px)
    ov = result.overlay
    if ov is not None and ov.a_px is not None and ov.b_px is not None:
        start["a_px"], start["b_px"] = list(ov.a_px), list(ov.b_px)
    if ov is not None and ov.line_px is not None:
        start["soil_px"] = [list(p) for p in ov.line_px]
    return start


def rim_guess(image: np.ndarray, rig: Rig) -> tuple[float, float, float] | None:
    """The soft method's starting rim circle (cx, cy, r px) for an RGB uint8 image, or None
    when its edge support is too weak to call it a rim. Compiled once per image size."""
    from ..soft.settings import SoftSettings

    cx, cy, r, support = (
        float(v)
        for v in _rim_guess(image, rig.segmentation, rig.confidence_rect, srgb_flag(rig.encoding))
    )
    min_support = float(SoftSettings().min_rim_support)
    if not (support >= min_support and all(map(math.isfinite, (cx, cy, r)))):
        return None
    return cx, cy, r


@functools.cache
def _rim_guess_fn() -> Callable[..., Any]:
    import jax
    import jax.numpy as jnp

    from ..soft.colour import linear_light
    from ..soft.hough import hough_rim
    from ..soft.outline import extract_outline, refine_outline
    from ..soft.segmentation import wheel_mask
    from ..soft.settings import SoftSettings
    from ..xla import jit

    @jit(static_argnames=("rect",))
    def guess(image_u8, seg, rect, srgb):
        image = image_u8.astype(jax.dtypes.canonicalize_dtype(jnp.float64)) / 255.0
        settings = SoftSettings().astype(image.dtype)
        mask = wheel_mask(image, seg, rect)
        edges = linear_light(image, srgb)
        outline = refine_outline(edges, extract_outline(mask, settings), settings)
        c = hough_rim(outline, image.shape[0], image.shape[1], settings)
        return jnp.stack([c.cx_px, c.cy_px, c.r_px, c.support])

    return guess


def _rim_guess(
    image: np.ndarray, seg: Any, rect: tuple[int, int, int, int], srgb: float = 0.0
) -> Any:
    # A traced float flag (rig.srgb_flag): one compiled guess for both encodings.
    return _rim_guess_fn()(image, seg, rect=tuple(rect), srgb=srgb)
