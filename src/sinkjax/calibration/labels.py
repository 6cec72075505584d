"""Labelled frames for calibration: read and check LABELS.csv (docs/conventions.md §3).

Everything is validated before any other work, so that a bad cell stops ``sinkjax calibrate`` at
once with the row and column to fix instead of after minutes of compiling.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np
from jaxtyping import Float, UInt8

from ..rig import Rig, RigError, rect_problem

LABEL_COLUMNS = ("image", "sinkage_mm", "theta1_deg", "theta2_deg")
QUANTITIES = LABEL_COLUMNS[1:]


class LabelError(RigError):
    """LABELS.csv is unusable; the message names the row (1 = header), the column and the fix."""


@dataclasses.dataclass(frozen=True)
class LabelledFrames:
    """Checked labelled frames. ``images`` uint8 (N, H, W, 3); ``targets`` (N, 3) float64 as
    (sinkage_mm, theta1_deg, theta2_deg), NaN = not measured; ``names`` the ``image`` cells."""

    images: UInt8[np.ndarray, "N H W 3"]
    targets: Float[np.ndarray, "N 3"]
    names: tuple[str, ...]
    # The frames the rim circle is found from, as `sinkjax estimate` of the labels' folder finds
    # it: that recording's first frames of the labelled size (:func:`recording_rim_images`).
    # None: the labelled frames themselves.
    rim_images: UInt8[np.ndarray, "M H W 3"] | None = None

    @property
    def rim_source(self) -> UInt8[np.ndarray, "M H W 3"]:
        """The frames the labelled frames' rim is found from."""
        return self.images if self.rim_images is None else self.rim_images


def read_labels(path: str | Path, rig: Rig | None = None) -> LabelledFrames:
    """Read, validate and load LABELS.csv (conventions §3), all before any other work.

    Image paths are relative to the CSV's folder; an empty cell means "not measured". Raises
    :class:`LabelError` naming the row and column for: missing columns, an empty, missing or
    unreadable image, a number that does not parse or is out of range, no measured cell at all,
    images of different sizes, or a confidence rectangle of ``rig`` that lies off the images.
    With ``rig``, ``rim_images`` holds the frames ``sinkjax estimate`` of the CSV's folder finds
    the rim from (:func:`recording_rim_images`).
    """
    from ..app.frames import read_image

    p = Path(path)
    if not p.is_file():
        raise LabelError(f"labels file {str(p)!r} does not exist")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise LabelError(f"{p}: cannot read it as UTF-8 text ({e})") from e
    try:
        lines = list(csv.reader(text.splitlines()))
    except csv.Error as e:
        raise LabelError(f"{p}: not a CSV file ({e})") from e
    reader = iter(lines)
    header = [h.strip() for h in next(reader, [])]
    missing = [c for c in LABEL_COLUMNS if c not in header]
    if missing:
        raise LabelError(
            f"{p}: row 1 (header): missing column(s) {', '.join(missing)}; the header must "
            f"name {','.join(LABEL_COLUMNS)} (got {','.join(header) or 'an empty line'!r})"
        )
    col = {name: header.index(name) for name in LABEL_COLUMNS}
    names, targets, rows = [], [], []
    for row_no, row in enumerate(reader, start=2):
        if not any(cell.strip() for cell in row):
            continue
        cells = {name: (row[i].strip() if i < len(row) else "") for name, i in col.items()}
        where = f"{p}: row {row_no}, column"
        if not cells["image"]:
            raise LabelError(f"{where} image: empty; write the image file name")
        if not (p.parent / cells["image"]).is_file():
            raise LabelError(
                f"{where} image: {str(p.parent / cells['image'])!r} does not exist "
                "(image paths are relative to the folder of the labels file)"
            )
        targets.append([_parse_cell(cells[q], where, q) for q in QUANTITIES])
        names.append(cells["image"])
        rows.append(row_no)
    if not names:
        raise LabelError(f"{p}: no labelled rows after the header")
    t = np.asarray(targets, dtype=np.float64)
    if not np.isfinite(t).any():
        raise LabelError(
            f"{p}: rows {rows[0]}-{rows[-1]}, columns {', '.join(QUANTITIES)}: every cell is "
            "empty; measure at least one quantity in one frame"
        )
    images: list[np.ndarray] = []
    for row_no, name in zip(rows, names, strict=True):
        try:
            image = read_image(p.parent / name)
        except (OSError, ValueError) as e:
            reason = getattr(e, "strerror", None) or str(e)
            raise LabelError(
                f"{p}: row {row_no}, column image: cannot read {name!r}: {reason}"
            ) from e
        if images and image.shape != images[0].shape:
            raise LabelError(
                f"{p}: row {row_no}, column image: {name!r} is {image.shape[1]}x{image.shape[0]}"
                f" px but row {rows[0]} is {images[0].shape[1]}x{images[0].shape[0]} px; "
                "calibrate one camera set-up (one image size) at a time"
            )
        images.append(image)
    frames = LabelledFrames(np.stack(images), t, tuple(names))
    if rig is not None:
        height, width = images[0].shape[:2]
        problem = rect_problem(rig.confidence_rect, height, width)
        if problem is not None:
            raise LabelError(f"{p}: the images of these labels: {problem}")
        frames = dataclasses.replace(frames, rim_images=recording_rim_images(p, frames, rig))
    return frames


def _parse_cell(cell: str, where: str, column: str) -> float:
    if not cell:
        return math.nan
    try:
        value = float(cell)
    except ValueError:
        raise LabelError(
            f"{where} {column}: {cell!r} is not a number; write it with '.' decimals and no "
            "unit, or leave the cell empty if it was not measured"
        ) from None
    if not math.isfinite(value):
        raise LabelError(
            f"{where} {column}: {cell!r} is not a finite number; leave the cell empty if it was "
            "not measured"
        )
    # The angles are atan2 angles (docs/conventions.md §1): a boundary end below the centre
    # (hollow terrain) gives a negative angle, so only |angle| <= 180 degrees is required.
    low, high = (0.0, math.inf) if column == "sinkage_mm" else (-180.0, 180.0)
    if not low <= value <= high:
        unit = "mm >= 0" if column == "sinkage_mm" else "degrees in [-180, 180]"
        raise LabelError(f"{where} {column}: {cell!r} is out of range ({unit})")
    return value


def recording_rim_images(path: str | Path, frames: LabelledFrames, rig: Rig) -> np.ndarray | None:
    """The frames ``sinkjax estimate`` finds the rim from when it measures the folder of the
    labels file ``path``: the first ones of the labelled size (at most the soft method's
    ``RIM_FRAMES``) of the recording that holds the first labelled image. When the labels sit in
    the recording's folder (the usual case) these are the recording's first frames, not the
    labelled ones, and calibration then measures the labelled frames with the rim the calibrated
    rig will find in the recording. None where the folder holds no such recording (the labelled
    frames are then their own rim's frames)."""
    from ..app.frames import ALL_FRAMES
    from ..app.pipeline import first_frames_reader
    from ..app.sources import InputError, expand_paths

    folder = Path(path).parent
    first = (folder / frames.names[0]).resolve()
    try:
        inputs = expand_paths([folder])
    except InputError:
        return None
    for rec in inputs.recordings:
        if any(Path(src.path).resolve() == first for src in rec.sources):
            images = first_frames_reader(rec.sources, rig, ALL_FRAMES, 0)(*frames.images.shape[1:3])
            return np.stack(images) if images else None
    return None
