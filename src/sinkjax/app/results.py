"""The results CSV (docs/conventions.md §4): its columns, one row per frame, written as produced."""

from __future__ import annotations

import csv
import math
from typing import IO

import numpy as np

from ..result import FrameResult

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


def csv_row(result: FrameResult) -> list[str]:
    """The CSV cells of one result, in :data:`COLUMNS` order (empty cell = not available)."""
    return [cell(getattr(result, c)) for c in COLUMNS]


def cell(value: object) -> str:
    """One CSV cell: floats rounded to 6 decimals, non-finite and None as an empty cell."""
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
        self._writer.writerow(csv_row(result))
        self._stream.flush()
