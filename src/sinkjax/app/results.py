"""One frame's result and the results CSV (conventions §4)."""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from typing import IO

import numpy as np

from ..status import Status

COLUMNS = (
    "image",
    "status",
    "sinkage_mm",
    "sinkage_std_mm",
    "theta1_deg",
    "theta1_std_deg",
    "theta2_deg",
    "theta2_std_deg",
    "center_x_px",
    "center_y_px",
    "radius_px",
    "message",
)

OK = Status.OK
NO_CONTACT = Status.NO_CONTACT
UNREADABLE = Status.UNREADABLE
NO_WHEEL = Status.NO_WHEEL
FIT_FAILED = Status.FIT_FAILED
BAD_RECT = Status.BAD_RECT
BAD_IMAGE = Status.BAD_IMAGE
ERROR = Status.ERROR


@dataclass
class Overlay:
    """What an overlay draws, in IMAGE pixels: rim circle, boundary, line ends, A and B."""

    centre_px: tuple[float, float]
    radius_px: float
    boundary_px: np.ndarray | None = None  # (n, 2) x, y
    line_px: tuple[tuple[float, float], tuple[float, float]] | None = None
    a_px: tuple[float, float] | None = None
    b_px: tuple[float, float] | None = None


@dataclass
class FrameResult:
    """One row of the results CSV, plus what an overlay needs. ``None`` = not available."""

    image: str
    status: str
    sinkage_mm: float | None = None
    sinkage_std_mm: float | None = None
    theta1_deg: float | None = None
    theta1_std_deg: float | None = None
    theta2_deg: float | None = None
    theta2_std_deg: float | None = None
    center_x_px: float | None = None
    center_y_px: float | None = None
    radius_px: float | None = None
    message: str = ""
    overlay: Overlay | None = field(default=None, repr=False, compare=False)

    def row(self) -> list[str]:
        return [_cell(getattr(self, c)) for c in COLUMNS]


def no_contact(
    image: str, centre_px: tuple[float, float], radius_px: float, overlay: Overlay | None
) -> FrameResult:
    """Conventions §1: no contact is sinkage 0 and both angles 0, with no sigma."""
    return FrameResult(
        image=image,
        status=NO_CONTACT,
        sinkage_mm=0.0,
        theta1_deg=0.0,
        theta2_deg=0.0,
        center_x_px=centre_px[0],
        center_y_px=centre_px[1],
        radius_px=radius_px,
        message="the soil does not reach inside the rim (no wheel-soil boundary)",
        overlay=overlay,
    )


def failed(image: str, status: str, message: str) -> FrameResult:
    """A row for a frame that produced no measurement."""
    return FrameResult(image=image, status=status, message=message)


def _cell(value: object) -> str:
    if value is None:
        return ""
    if isinstance(value, float | np.floating):
        v = float(value)
        return "" if not math.isfinite(v) else repr(round(v, 6))
    return str(value)


class ResultsWriter:
    """Writes rows as they come and flushes each, so an interrupted run keeps what it finished."""

    def __init__(self, stream: IO[str], *, header: bool = True) -> None:
        self._stream = stream
        self._writer = csv.writer(stream, lineterminator="\n")
        if header:
            self._writer.writerow(COLUMNS)
            stream.flush()

    def write(self, result: FrameResult) -> None:
        self._writer.writerow(result.row())
        self._stream.flush()
