"""Plots of results: against ground truth, and over time (matplotlib's Agg renderer, no display)."""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path

from .. import metrics
from .smoothing import SmoothingOptions

QUANTITIES = (
    # (results column, std column, truth column, label, unit)
    ("sinkage_mm", "sinkage_std_mm", "sinkage_mm", "sinkage z0", "mm"),
    ("theta1_deg", "theta1_std_deg", "theta1_deg", "entry angle θ1", "deg"),
    ("theta2_deg", "theta2_std_deg", "theta2_deg", "exit angle θ2", "deg"),
)


@dataclass
class Matched:
    """One results row with its truth row (``truth`` None when the truth has no such image)."""

    result: dict[str, str]
    truth: dict[str, str] | None

    @property
    def measured(self) -> bool:
        """A measurement by :mod:`sinkjax.metrics` (``ok`` or ``no_contact``, which reads 0)."""
        return bool(metrics.measured([self.result.get("status", "")])[0])


def number(cell: str | None) -> float | None:
    """A CSV cell as a float; None for an empty or non-numeric cell."""
    if cell is None or not cell.strip():
        return None
    try:
        value = float(cell)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def _read_rows(path: str | Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or "image" not in reader.fieldnames:
            raise ValueError(f"{path}: not a CSV with an 'image' column")
        return list(reader)


def _key(image: str, base: Path) -> tuple[str, str]:
    path, sep, frame = image.partition("#")
    p = Path(path)
    return os.path.normcase(os.path.abspath(p if p.is_absolute() else base / p)), sep + frame


def match_truth(results_csv: str | Path, truth_csv: str | Path) -> list[Matched]:
    """Results rows paired with truth rows, in results order.

    Results ``image`` paths are relative to the working directory (as given on the command line),
    truth paths to the truth CSV's folder (the LABELS convention); when no path matches, a
    unique file name does. Raises ValueError for a file that is not such a CSV.
    """
    results = _read_rows(results_csv)
    truth = _read_rows(truth_csv)
    truth_dir = Path(truth_csv).parent
    by_path = {_key(t["image"], truth_dir): t for t in truth}
    by_name: dict[str, dict[str, str] | None] = {}
    for row in truth:
        name = os.path.basename(row["image"])
        by_name[name] = None if name in by_name else row  # None: ambiguous
    out = []
    for r in results:
        match = by_path.get(_key(r["image"], Path.cwd()))
        if match is None:
            match = by_name.get(os.path.basename(r["image"]))
        out.append(Matched(r, match))
    return out


def plot_accuracy(
    results_csv: str | Path,
    truth_csv: str | Path,
    out_png: str | Path,
    *,
    title: str | None = None,
) -> Path:
    """Estimated against true sinkage (mm), θ1 and θ2 (deg): one panel each, PNG at ``out_png``.

    Error bars are one standard deviation where the results have std columns (clipped to the
    panel, which spans the values); frames without an estimate are marked on the x axis at their
    true value. Returns the PNG's path.
    """
    # A bare Figure renders with Agg and leaves pyplot's global backend alone (notebooks).
    from matplotlib.figure import Figure
    from matplotlib.transforms import blended_transform_factory

    matched = [m for m in match_truth(results_csv, truth_csv) if m.truth is not None]
    n_failed = sum(not m.measured for m in matched)
    fig = Figure(figsize=(13.5, 4.6), layout="constrained")
    axes = fig.subplots(1, 3)
    for ax, (col, std_col, truth_col, label, unit) in zip(axes, QUANTITIES, strict=True):
        xs, ys, es, misses = [], [], [], []
        for m in matched:
            assert m.truth is not None
            true = number(m.truth.get(truth_col))
            if true is None:
                continue
            est = number(m.result.get(col)) if m.measured else None
            if est is None:
                misses.append(true)
                continue
            xs.append(true)
            ys.append(est)
            es.append(number(m.result.get(std_col)) or 0.0)
        values = xs + ys + misses
        lo, hi = (min(values), max(values)) if values else (0.0, 1.0)
        pad = 0.05 * (hi - lo) + 1e-9
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], "k--", lw=1, label="identity (y = x)")
        if xs:
            has_std = any(e > 0 for e in es)
            ax.errorbar(
                xs,
                ys,
                yerr=es if has_std else None,
                fmt="o",
                ms=4,
                capsize=3,
                label="estimate ± 1σ" if has_std else "estimate",
            )
        if misses:
            trans = blended_transform_factory(ax.transData, ax.transAxes)
            ax.plot(
                misses,
                [0.02] * len(misses),
                "x",
                color="tab:red",
                transform=trans,
                label="no estimate (at true value)",
            )
        # Limits from the values, not the error bars: one frame with a huge sigma must not
        # squash every other point onto the identity line.
        ax.set_xlim(lo - pad, hi + pad)
        ax.set_ylim(lo - pad, hi + pad)
        ax.set_xlabel(f"true {label} [{unit}]")
        ax.set_ylabel(f"estimated {label} [{unit}]")
        ax.set_title(label)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
    heading = title or "Estimated vs true"
    fig.suptitle(f"{heading} ({len(matched)} frames, {n_failed} without an estimate)")
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    return out


def _frame_axis(images: list[str]) -> tuple[list[float], str]:
    """x values for results rows: the video frame number when every row is a frame of one
    video, else the row's position in the CSV."""
    paths = {image.rpartition("#")[0] for image in images}
    frames = [image.rpartition("#")[2] for image in images]
    if len(paths) == 1 and "" not in paths and all(f.isdigit() for f in frames):
        return [float(f) for f in frames], "frame index (video frame)"
    return [float(i) for i in range(len(images))], "frame index (row of the results CSV)"


def plot_series(
    results_csv: str | Path,
    out_png: str | Path,
    *,
    smoothed: bool = False,
    options: SmoothingOptions | None = None,
    title: str | None = None,
) -> Path:
    """Sinkage (mm), θ1 and θ2 (deg) over the frame index, each with a ±1σ band, as a PNG.

    Frames without an estimate are gaps, marked with a red tick under the curve. ``smoothed``:
    also draw the smoothed series and its ±1σ band, from the CSV's smoothed columns or, when it
    has none, computed here with ``options``. Raises ValueError for a file that is not a
    results CSV. Returns the PNG's path.
    """
    import numpy as np
    from matplotlib.figure import Figure
    from matplotlib.transforms import blended_transform_factory

    from .smoothing import QUANTITIES as SMOOTHED, read_results, smooth_rows

    header, rows = read_results(results_csv)
    x, xlabel = _frame_axis([r["image"] for r in rows])
    xs = np.asarray(x)
    measured = metrics.measured([r.get("status", "") for r in rows])
    smooth: list[dict[str, float]] | None = None
    if smoothed:
        if all(q[2] in header for q in SMOOTHED):
            smooth = [
                {c: math.nan if (v := number(r.get(c))) is None else v for c in header}
                for r in rows
            ]
        else:
            smooth = smooth_rows(rows, options or SmoothingOptions())

    def column(name: str, source: list[dict[str, str]]) -> np.ndarray:
        values = [number(r.get(name)) for r in source]
        return np.array([math.nan if v is None else v for v in values], dtype=float)

    fig = Figure(figsize=(11, 8.5), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    marker = "o" if len(rows) <= 200 else None
    for ax, (col, std_col, _, label, unit), smooth_cols in zip(
        axes, QUANTITIES, SMOOTHED, strict=True
    ):
        y = np.where(measured, column(col, rows), math.nan)
        s = np.where(measured, column(std_col, rows), math.nan)
        ax.plot(xs, y, marker=marker, ms=3, lw=1, color="tab:blue", label="estimate")
        if np.isfinite(s).any():
            ax.fill_between(
                xs, y - s, y + s, color="tab:blue", alpha=0.25, lw=0, label="estimate ± 1σ"
            )
        if smooth is not None:
            m = np.array([row.get(smooth_cols[2], math.nan) for row in smooth], dtype=float)
            ms = np.array([row.get(smooth_cols[3], math.nan) for row in smooth], dtype=float)
            ax.plot(xs, m, lw=1.5, color="tab:orange", label="smoothed")
            ax.fill_between(
                xs, m - ms, m + ms, color="tab:orange", alpha=0.25, lw=0, label="smoothed ± 1σ"
            )
        failed_x = xs[~measured]
        if failed_x.size:
            trans = blended_transform_factory(ax.transData, ax.transAxes)
            ax.plot(
                failed_x,
                np.full(failed_x.shape, 0.03),
                "|",
                color="tab:red",
                ms=10,
                transform=trans,
                label="no estimate",
            )
        ax.set_ylabel(f"{label} [{unit}]")
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, ncols=5)
    axes[-1].set_xlabel(xlabel)
    n_failed = int((~measured).sum())
    heading = title or f"sinkjax results: {Path(results_csv).name}"
    fig.suptitle(f"{heading} ({len(rows)} frames, {n_failed} without an estimate)")
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    return out


def recording_of(image: str) -> tuple[str, float | None]:
    """A results row's recording and its place in it: a video frame's row (``VIDEO#NNNNNN``)
    is the video and the frame number; an image's row is its folder (frame number None)."""
    head, sep, tail = image.rpartition("#")
    if sep and tail.isdigit():
        return head, float(tail)
    return str(Path(image).parent), None


def plot_recordings(
    results_csv: str | Path, out_png: str | Path, *, title: str | None = None
) -> Path:
    """z0 (mm), θ1 and θ2 (deg) over time, one line per recording, as a PNG (a campaign's view).

    Time is the video frame number, or the image's place in its folder's rows. Frames without
    an estimate are gaps. Raises ValueError for a file that is not a results CSV.
    """
    import numpy as np
    from matplotlib.figure import Figure

    from .smoothing import read_results

    _, rows = read_results(results_csv)
    series: dict[str, list[tuple[float, dict[str, str]]]] = {}
    for row in rows:
        name, frame = recording_of(row["image"])
        group = series.setdefault(name, [])
        group.append((float(len(group)) if frame is None else frame, row))
    fig = Figure(figsize=(11, 8.5), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    marker = "o" if len(rows) <= 400 else None
    for name, points in series.items():
        xs = np.array([x for x, _ in points])
        status = [r["status"] for _, r in points]
        for ax, (col, _, _, label, unit) in zip(axes, QUANTITIES, strict=True):
            y = metrics.measured_values([number(r.get(col)) for _, r in points], status)
            ax.plot(xs, y, marker=marker, ms=3, lw=1, label=Path(name).name or name)
            ax.set_ylabel(f"{label} [{unit}]")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    if len(series) <= 20:
        axes[0].legend(loc="upper right", fontsize=7, ncols=min(len(series), 5))
    axes[-1].set_xlabel("frame (video frame number, or image's place in its recording)")
    heading = title or f"sinkjax results: {Path(results_csv).name}"
    fig.suptitle(f"{heading} ({len(series)} recordings, {len(rows)} frames)")
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    return out
