"""Temporal smoothing of a results series: a random-walk Kalman filter with an RTS smoother.

Beyond the paper, which measures every frame on its own. Each quantity (sinkage, θ1, θ2) is an
independent random walk over the frame index t,

    x_t = x_{t-1} + w_t,   w_t ~ N(0, q * (t - t_prev))      (q: process variance per frame)
    y_t = x_t + v_t,       v_t ~ N(0, σ_t²)                  (σ_t: the frame's own std column)

and the Rauch-Tung-Striebel smoother gives the posterior mean and std of x_t from ALL frames.
Frames without a measurement (failed status, empty cell) are time steps without an update, so the
smoother bridges them. The prior is diffuse (no guess before the first measurement).

The smoothed columns (:data:`SMOOTH_COLUMNS`) go AFTER the contract's 12; the default results
CSV never has them. Time: a video row ``clip.mp4#000123`` is at t = 123, so frames left out by
``--stride`` or failed frames widen the step; image rows are at t = their position among the
consecutive image rows. Each video, and each run of consecutive image rows, is its own series.
"""

from __future__ import annotations

import csv
import math
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from jaxtyping import Float

from ..status import Status
from .results import COLUMNS, cell

# (value column, std column, smoothed column, smoothed std column, unit)
QUANTITIES = (
    ("sinkage_mm", "sinkage_std_mm", "sinkage_smooth_mm", "sinkage_smooth_std_mm", "mm"),
    ("theta1_deg", "theta1_std_deg", "theta1_smooth_deg", "theta1_smooth_std_deg", "deg"),
    ("theta2_deg", "theta2_std_deg", "theta2_smooth_deg", "theta2_smooth_std_deg", "deg"),
)
SMOOTH_COLUMNS = tuple(c for q in QUANTITIES for c in q[2:4])

# Defaults: a wheel's sinkage changes by about half a millimetre and its angles by about a degree
# from one frame to the next at typical rover speeds and frame rates (a few cm/s, 5-30 fps).
PROCESS_STD_MM = 0.5
PROCESS_STD_DEG = 1.0
# Rows with a value but no std (the classic method has none) are weighted with these.
MEASUREMENT_STD_MM = 1.0
MEASUREMENT_STD_DEG = 2.0
# A zero std would pin the state exactly; keep the algebra finite.
_MIN_VARIANCE = 1e-12


@dataclass(frozen=True)
class SmoothingOptions:
    """Random-walk steps (one std per frame) and fallback measurement stds, mm and degrees."""

    process_std_mm: float = PROCESS_STD_MM
    process_std_deg: float = PROCESS_STD_DEG
    measurement_std_mm: float = MEASUREMENT_STD_MM
    measurement_std_deg: float = MEASUREMENT_STD_DEG

    def __post_init__(self) -> None:
        for name in ("process_std_mm", "process_std_deg"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                flag = "--" + name.replace("_", "-")
                raise ValueError(f"{flag} must be a number >= 0, got {value}")
        for name in ("measurement_std_mm", "measurement_std_deg"):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0:
                flag = "--" + name.replace("_", "-")
                raise ValueError(f"{flag} must be a number > 0, got {value}")

    def process_std(self, unit: str) -> float:
        return self.process_std_mm if unit == "mm" else self.process_std_deg

    def measurement_std(self, unit: str) -> float:
        return self.measurement_std_mm if unit == "mm" else self.measurement_std_deg


def rts_random_walk(
    y: Float[np.ndarray, " n"],
    r: Float[np.ndarray, " n"],
    q: float,
    t: Float[np.ndarray, " n"] | None = None,
) -> tuple[Float[np.ndarray, " n"], Float[np.ndarray, " n"]]:
    """Smoothed mean and variance of a random walk observed with noise.

    ``y``: measurements (NaN = none at that step); ``r``: their variances; ``q``: process
    variance per unit of ``t`` (non-decreasing times; default 0, 1, 2, ...). Returns (mean,
    variance), NaN everywhere when nothing was measured. Before the first measurement the
    variance grows backwards from it; after the last, forwards.
    """
    y = np.asarray(y, dtype=float)
    r = np.maximum(np.asarray(r, dtype=float), _MIN_VARIANCE)
    n = y.shape[0]
    t = np.arange(n, dtype=float) if t is None else np.asarray(t, dtype=float)
    if r.shape != (n,) or t.shape != (n,):
        shapes = f"{y.shape}, {r.shape}, {t.shape}"
        raise ValueError(f"y, r and t must have one shape (n,), got {shapes}")
    if n and np.any(np.diff(t) < 0):
        raise ValueError("times t must be non-decreasing")
    if q < 0:
        raise ValueError(f"process variance q must be >= 0, got {q}")
    mean = np.full(n, np.nan)
    var = np.full(n, np.nan)
    if n == 0 or not np.any(np.isfinite(y)):
        return mean, var
    step = q * np.diff(t, prepend=t[0])  # process variance added before each step
    m_f = np.empty(n)  # filtered (all measurements up to and including t)
    p_f = np.empty(n)
    m, p = 0.0, math.inf  # diffuse prior
    for i in range(n):
        p = p + step[i]
        if np.isfinite(y[i]):
            if math.isinf(p):
                m, p = y[i], r[i]
            else:
                gain = p / (p + r[i])
                m, p = m + gain * (y[i] - m), p * r[i] / (p + r[i])
        m_f[i], p_f[i] = m, p
    mean[-1], var[-1] = m_f[-1], p_f[-1]
    for i in range(n - 2, -1, -1):
        if math.isinf(p_f[i]):  # nothing measured yet: walk back from the smoothed next step
            mean[i], var[i] = mean[i + 1], var[i + 1] + step[i + 1]
            continue
        p_pred = p_f[i] + step[i + 1]
        gain = p_f[i] / p_pred if p_pred > 0 else 1.0
        mean[i] = m_f[i] + gain * (mean[i + 1] - m_f[i])
        var[i] = p_f[i] + gain * gain * (var[i + 1] - p_pred)
    return mean, np.maximum(var, 0.0)


def _number(cell: str | None) -> float:
    if cell is None or not cell.strip():
        return math.nan
    try:
        return float(cell)
    except ValueError:
        return math.nan


def series_time(images: Sequence[str]) -> tuple[list[str], Float[np.ndarray, " n"]]:
    """Per row: its series key (video path, or "" for images) and its time t in frames."""
    keys: list[str] = []
    times = np.zeros(len(images))
    position = 0
    for i, image in enumerate(images):
        path, sep, frame = image.rpartition("#")
        if sep and frame.isdigit():
            keys.append(path)
            times[i] = int(frame)
            continue
        if i and keys[-1] != "":
            position = 0
        keys.append("")
        times[i] = position
        position += 1
    return keys, times


def smooth_rows(
    rows: Sequence[dict[str, str]], options: SmoothingOptions = SmoothingOptions()
) -> list[dict[str, float]]:
    """The smoothed columns for results rows (dicts keyed by :data:`COLUMNS`), one per row.

    Rows whose status is ``ok`` or ``no_contact`` with a value are measurements; every other row
    is bridged. Values are NaN where a series has no measurement at all.
    """
    keys, times = series_time([row.get("image", "") for row in rows])
    out: list[dict[str, float]] = [{} for _ in rows]
    start = 0
    while start < len(rows):
        stop = start + 1
        while stop < len(rows) and keys[stop] == keys[start]:
            stop += 1
        segment = rows[start:stop]
        t = times[start:stop]
        if np.any(np.diff(t) < 0):  # rows out of order (e.g. hand-edited): use row positions
            t = np.arange(stop - start, dtype=float)
        measured = np.array(
            [row.get("status") in (Status.OK, Status.NO_CONTACT) for row in segment]
        )
        for col, std_col, s_col, s_std_col, unit in QUANTITIES:
            y = np.array([_number(row.get(col)) for row in segment])
            y[~measured] = np.nan
            std = np.array([_number(row.get(std_col)) for row in segment])
            std = np.where(np.isfinite(std) & (std >= 0), std, options.measurement_std(unit))
            mean, var = rts_random_walk(y, std**2, options.process_std(unit) ** 2, t)
            for k in range(stop - start):
                out[start + k][s_col] = float(mean[k])
                out[start + k][s_std_col] = float(math.sqrt(var[k]))
        start = stop
    return out


class NotAResultsCsv(ValueError):
    """The file is not a sinkjax results CSV; the message says what was found."""


def read_results(path: str | Path) -> tuple[list[str], list[dict[str, str]]]:
    """Header and rows of a results CSV. Raises NotAResultsCsv unless it starts with COLUMNS."""
    with open(path, newline="", encoding="utf-8", errors="surrogateescape") as f:
        reader = csv.DictReader(f, restval="")
        try:
            header = list(reader.fieldnames or [])
            if tuple(header[: len(COLUMNS)]) != COLUMNS:
                raise NotAResultsCsv(
                    f"{path} is not a sinkjax results CSV: its header is {_shown(header)} "
                    f"instead of {','.join(COLUMNS[:3])},..."
                )
            return header, list(reader)
        except csv.Error as e:
            raise NotAResultsCsv(f"{path} is not a sinkjax results CSV: {e}") from None


def _shown(header: list[str]) -> str:
    """A header in a message: quoted and short, or "binary data" when it is not text."""
    text = ",".join(header)
    if not text:
        return "empty"
    if not text.isprintable() or any("\udc80" <= ch <= "\udcff" for ch in text):
        return "binary data (not text)"
    return repr(text[:80])


def smooth_csv(
    results_csv: str | Path,
    out_csv: str | Path | None = None,
    options: SmoothingOptions = SmoothingOptions(),
) -> Path:
    """Write ``results_csv`` with the smoothed columns appended to ``out_csv`` (default: in place).

    Existing smoothed columns are recomputed; the contract's 12 cells of every row are copied
    unchanged. The file is replaced atomically, so an interrupted write leaves the old one.
    Raises NotAResultsCsv or OSError.
    """
    _, rows = read_results(results_csv)
    smoothed = smooth_rows(rows, options)
    out = Path(out_csv) if out_csv is not None else Path(results_csv)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    try:
        with os.fdopen(fd, "w", newline="", encoding="utf-8", errors="surrogateescape") as f:
            writer = csv.writer(f, lineterminator="\n")
            writer.writerow((*COLUMNS, *SMOOTH_COLUMNS))
            for row, extra in zip(rows, smoothed, strict=True):
                cells = [row.get(c) or "" for c in COLUMNS]
                writer.writerow(cells + [cell(extra[c]) for c in SMOOTH_COLUMNS])
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out
