"""Overlays: one frame with its measurement drawn on it (rim, boundary, line, A, B, numbers).

Written as one PNG per frame (:class:`OverlayWriter`) or as one annotated MP4
(:class:`OverlayVideoWriter`).
"""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

import cv2
import numpy as np

from ..result import FrameResult
from ..rig import Rig
from ..status import Status

# RGB colours (the image is drawn in RGB and converted to BGR only when written).
_RIM = (255, 215, 0)
_CENTRE = (255, 215, 0)
_BOUNDARY = (0, 255, 255)
_LINE = (255, 0, 255)
_ENTRY = (255, 64, 64)
_EXIT = (64, 160, 255)
_RECT = (160, 160, 160)
_TEXT = (255, 255, 255)
_ALERT = (255, 80, 80)
_SHIFT = 4  # fixed-point bits: cv2 draws at sub-pixel positions
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _pt(x: float, y: float) -> tuple[int, int]:
    return round(x * (1 << _SHIFT)), round(y * (1 << _SHIFT))


def _finite(*values: float | None) -> bool:
    return all(v is not None and np.isfinite(v) for v in values)


def _fmt(value: float | None, std: float | None, unit: str) -> str:
    if value is None or not np.isfinite(value):
        return "n/a"
    if std is not None and np.isfinite(std):
        return f"{value:.2f} +/- {std:.2f} {unit}"
    return f"{value:.2f} {unit}"


def _label(img: np.ndarray, text: str, org: tuple[int, int], scale: float, colour) -> None:
    thick = max(1, round(scale * 2))
    (w, h), base = cv2.getTextSize(text, _FONT, scale, thick)
    x, y = org
    cv2.rectangle(img, (x - 2, y - h - 3), (x + w + 2, y + base + 1), (0, 0, 0), -1)
    cv2.putText(img, text, (x, y), _FONT, scale, colour, thick, cv2.LINE_AA)


def draw_overlay(image: np.ndarray, result: FrameResult, rig: Rig | None = None) -> np.ndarray:
    """A copy of ``image`` (RGB uint8, (H, W, 3)) with ``result`` drawn on it, same shape.

    Draws the confidence rectangle (when ``rig`` is given), rim circle and centre O, boundary
    points, equivalent line, entry point A and exit point B, and the numbers (z0 mm +/- std,
    theta1, theta2 in degrees). A status other than ``ok`` is written on the image in words.
    """
    img = np.ascontiguousarray(image[:, :, :3], dtype=np.uint8).copy()
    height, width = img.shape[:2]
    scale = max(0.35, min(width, height) / 900.0)
    thick = max(1, round(min(width, height) / 400))
    aa = cv2.LINE_AA

    if rig is not None:
        x, y, w, h = rig.confidence_rect
        cv2.rectangle(img, (x, y), (x + w - 1, y + h - 1), _RECT, 1)

    ov = result.overlay
    cx, cy, r = result.center_x_px, result.center_y_px, result.radius_px
    if ov is not None:
        cx, cy = ov.centre_px
        r = ov.radius_px
    if _finite(cx, cy, r) and r is not None and r > 0:
        assert cx is not None and cy is not None
        cv2.circle(img, _pt(cx, cy), round(r * (1 << _SHIFT)), _RIM, thick, aa, _SHIFT)
        cv2.drawMarker(img, (round(cx), round(cy)), _CENTRE, cv2.MARKER_CROSS, 4 * thick + 8, thick)
        _label(img, "O", (round(cx) + 6, round(cy) - 6), scale, _CENTRE)

    if ov is not None:
        if ov.boundary_px is not None and len(ov.boundary_px):
            pts = np.asarray(ov.boundary_px, dtype=float).reshape(-1, 2)
            step = max(1, len(pts) // 400)  # keep dense boundaries readable
            for px, py in pts[::step]:
                if np.isfinite(px) and np.isfinite(py):
                    cv2.circle(img, _pt(px, py), 2 << _SHIFT, _BOUNDARY, -1, aa, _SHIFT)
        if ov.line_px is not None:
            (x0, y0), (x1, y1) = ov.line_px
            if _finite(x0, y0, x1, y1):
                cv2.line(img, _pt(x0, y0), _pt(x1, y1), _LINE, thick + 1, aa, _SHIFT)
        for point, name, colour in ((ov.a_px, "A", _ENTRY), (ov.b_px, "B", _EXIT)):
            if point is not None and _finite(*point):
                px, py = point
                cv2.circle(img, _pt(px, py), (3 * thick + 3) << _SHIFT, colour, -1, aa, _SHIFT)
                _label(img, name, (round(px) + 8, round(py) - 8), scale * 1.2, colour)

    line_h = round(30 * scale) + 6
    y_text = line_h
    if result.status in (Status.OK, Status.NO_CONTACT):
        lines = [
            f"z0 = {_fmt(result.sinkage_mm, result.sinkage_std_mm, 'mm')}",
            f"theta1 = {_fmt(result.theta1_deg, result.theta1_std_deg, 'deg')}",
            f"theta2 = {_fmt(result.theta2_deg, result.theta2_std_deg, 'deg')}",
        ]
        if result.status == Status.NO_CONTACT:
            lines.append("no contact")
        for text in lines:
            _label(img, text, (8, y_text), scale, _TEXT)
            y_text += line_h
    else:
        width_chars = max(20, int(width / (20 * scale)))
        wrapped = textwrap.wrap(result.message or "", width_chars)[:6]
        for i, text in enumerate([f"status: {result.status}", *wrapped]):
            _label(img, text, (8, y_text), scale * (1.2 if i == 0 else 1.0), _ALERT)
            y_text += line_h
    return img


def overlay_name(stem: str, used: set[str]) -> str:
    """``stem`` made a safe, unique PNG file name (``video_000123.png``); records it in ``used``."""
    base = re.sub(r"[^A-Za-z0-9._-]+", "_", stem).strip("._") or "frame"
    name = f"{base}.png"
    n = 2
    while name in used:
        name = f"{base}_{n}.png"
        n += 1
    used.add(name)
    return name


class OverlayWriter:
    """Writes one overlay PNG per frame into ``directory`` (created), names kept unique."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self._used: set[str] = set()

    def write(
        self, image: np.ndarray | None, result: FrameResult, stem: str, rig: Rig | None = None
    ) -> Path | None:
        """Write the overlay (``rig``: draw its confidence rectangle); None when the frame has
        no image."""
        if image is None:
            return None
        path = self.directory / overlay_name(stem, self._used)
        drawn = draw_overlay(image, result, rig)
        if not cv2.imwrite(str(path), cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR)):
            raise OSError(f"could not write overlay {path}")
        return path


class OverlayVideoWriter:
    """Writes the overlays of a run as one MP4 (OpenCV's ``mp4v`` codec), one video frame per row.

    The video takes the size of the first frame that has pixels; frames of another size are
    resized to it, and frames without pixels (unreadable) become a black frame that states their
    status, so the video stays in step with the results CSV. Call :meth:`close` at the end.
    """

    def __init__(self, path: str | Path, *, fps: float = 10.0) -> None:
        self.path = Path(path)
        if self.path.suffix.lower() not in (".mp4", ".m4v", ".mov"):
            raise ValueError(f"--overlay-video must name an .mp4 file, got {str(path)!r}")
        if not (fps > 0):
            raise ValueError(f"frame rate must be > 0, got {fps}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fps = float(fps)
        self.n_written = 0
        self._size: tuple[int, int] | None = None  # (width, height)
        self._writer: cv2.VideoWriter | None = None
        self._waiting: list[FrameResult] = []  # rows without pixels before the size is known
        self._broken = False

    def _open(self, width: int, height: int) -> None:
        # mp4v wants even sizes; an odd frame loses its last row or column.
        self._size = (max(2, width - width % 2), max(2, height - height % 2))
        fourcc = cv2.VideoWriter_fourcc(*"mp4v")  # type: ignore[attr-defined]
        writer = cv2.VideoWriter(str(self.path), fourcc, self.fps, self._size)
        if not writer.isOpened():
            self._broken = True
            raise OSError(f"OpenCV cannot write {self.path} with the mp4v codec")
        self._writer = writer
        for result in self._waiting:
            self._put(None, result)
        self._waiting.clear()

    def _put(self, image: np.ndarray | None, result: FrameResult, rig: Rig | None = None) -> None:
        assert self._writer is not None and self._size is not None
        width, height = self._size
        if image is None:
            drawn = draw_overlay(np.zeros((height, width, 3), np.uint8), result)
        else:
            drawn = draw_overlay(image, result, rig)
            if drawn.shape[:2] != (height, width):
                drawn = cv2.resize(drawn, (width, height), interpolation=cv2.INTER_AREA)
        self._writer.write(cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR))
        self.n_written += 1

    def write(self, image: np.ndarray | None, result: FrameResult, rig: Rig | None = None) -> None:
        """Append the overlay of one frame (``image`` None: a black frame with the status)."""
        if self._broken:
            return
        if self._writer is None:
            if image is None:
                self._waiting.append(result)
                return
            self._open(image.shape[1], image.shape[0])
        self._put(image, result, rig)

    def close(self) -> None:
        """Finish the file (a run whose frames all lacked pixels writes no video)."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
