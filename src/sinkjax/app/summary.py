"""The campaign summary (``--summary``): one row per recording, from the run's results CSV.

A test-bed campaign is dozens of recordings, one per load and slip setting; this table is the
first look at it: how many frames each recording has, how many were measured and why the others
failed, which features its segmenter separated wheel from soil with, and the median and range of
z0, θ1 and θ2 with the median one-sigma. It is computed from the results CSV when the run
completes, so a resumed run summarises the earlier rows too, and a parallel run gives the same
table as a serial one (docs/conventions.md §3). The features are no column of the results CSV:
they are counted as the run measures (:func:`describe_features`), over this run's frames only.
"""

from __future__ import annotations

import csv
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .. import metrics
from ..status import Status
from .results import cell
from .smoothing import read_results
from .sources import Inputs, Recording

log = logging.getLogger("sinkjax")

# Failure statuses, each its own count column (ok and no_contact are the measured ones).
FAILURES = tuple(s for s in Status if not s.measured)
# (results column, its sigma column, the summary's name stem, unit)
_QUANTITIES = (
    ("sinkage_mm", "sinkage_std_mm", "sinkage", "mm"),
    ("theta1_deg", "theta1_std_deg", "theta1", "deg"),
    ("theta2_deg", "theta2_std_deg", "theta2", "deg"),
)
SUMMARY_COLUMNS = (
    "recording",
    "rig",
    "segmenter",
    "frames",
    "ok",
    "no_contact",
    "failed",
    *(s.value for s in FAILURES),
    *(
        f"{stem}_{stat}_{unit}"
        for _, _, stem, unit in _QUANTITIES
        for stat in ("median", "min", "max")
    ),
    *(f"{stem}_std_median_{unit}" for _, _, stem, unit in _QUANTITIES),
)


def source_of(image: str) -> str:
    """The source (image file or video) a results row came from: a video frame's row is named
    ``VIDEO#NNNNNN`` (docs/conventions.md §4), an image's row is the image itself."""
    head, sep, tail = image.rpartition("#")
    return head if sep and tail.isdigit() else image


def _stats(values: np.ndarray) -> list[float | None]:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return [None, None, None]
    return [float(np.median(finite)), float(finite.min()), float(finite.max())]


def _median(values: np.ndarray) -> float | None:
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if finite.size else None


def describe_features(counts: Mapping[str, int]) -> str:
    """Which features a recording's frames were segmented by, most frames first:
    ``hue+saturation (12 frames)``, ``intensity+texture (10), hue+saturation (2)``; "" for
    none. ``counts``: frames per :data:`sinkjax.result.FEATURE_CHOICES` name."""
    items = sorted(((n, name) for name, n in counts.items() if n > 0), key=lambda t: (-t[0], t[1]))
    if len(items) == 1:
        n, name = items[0]
        return f"{name} ({n} frame{'' if n == 1 else 's'})"
    return ", ".join(f"{name} ({n})" for n, name in items)


def summary_row(
    recording: str,
    rig: str,
    rows: Sequence[dict[str, str]],
    features: Mapping[str, int] | None = None,
) -> dict[str, object]:
    """One recording's summary from its results rows (as read from the CSV) and the frames per
    segmenter features (:func:`describe_features`; None or none: an empty cell)."""
    status = [r["status"] for r in rows]
    measured = metrics.measured(status) if rows else np.zeros(0, bool)
    out: dict[str, object] = {
        "recording": recording,
        "rig": rig,
        "segmenter": describe_features(features or {}) or None,
        "frames": len(rows),
        "ok": status.count(Status.OK.value),
        "no_contact": status.count(Status.NO_CONTACT.value),
        "failed": int((~measured).sum()),
    }
    out.update({s.value: status.count(s.value) for s in FAILURES})
    for col, std_col, stem, unit in _QUANTITIES:
        # ok: its value; no_contact: 0 (docs/conventions.md §1); failed rows: left out.
        cells = [float(r[col]) if r[col] else None for r in rows]
        stats = _stats(metrics.measured_values(cells, status) if rows else np.zeros(0))
        for stat, v in zip(("median", "min", "max"), stats, strict=True):
            out[f"{stem}_{stat}_{unit}"] = v
        sigmas = np.array([float(r[std_col]) if r[std_col] else np.nan for r in rows], float)
        ok = np.array([s == Status.OK.value for s in status], bool)
        out[f"{stem}_std_median_{unit}"] = _median(sigmas[ok]) if rows else None
    return out


def summarise(
    results_csv: str | Path,
    inputs: Inputs,
    features: Mapping[str, Mapping[str, int]] | None = None,
) -> list[dict[str, object]]:
    """One summary row per recording of ``inputs``, in input order, from ``results_csv``.

    Rows are matched to recordings by their source's name; rows of the CSV that belong to none
    of them (a resumed file from other inputs) are left out, with a warning. ``features``:
    per recording name, its frames per segmenter features (the run counts them; the results
    CSV does not hold them).
    """
    _, rows = read_results(results_csv)
    owner: dict[str, Recording] = {}
    for rec in inputs.recordings:
        for source in rec.sources:
            owner.setdefault(source.name, rec)
    grouped: dict[str, list[dict[str, str]]] = {rec.name: [] for rec in inputs.recordings}
    stray = 0
    for row in rows:
        found = owner.get(row["image"]) or owner.get(source_of(row["image"]))
        if found is None:
            stray += 1
            continue
        grouped[found.name].append(row)
    if stray:
        log.warning(
            "%d row(s) of %s belong to none of the inputs: not summarised", stray, results_csv
        )
    features = features or {}
    return [
        summary_row(rec.name, rec.rig_source, grouped[rec.name], features.get(rec.name))
        for rec in inputs.recordings
    ]


def write_summary(
    results_csv: str | Path,
    inputs: Inputs,
    out_csv: str | Path,
    features: Mapping[str, Mapping[str, int]] | None = None,
) -> Path:
    """Write the campaign summary of ``results_csv`` (and ``features``, see :func:`summarise`)
    to ``out_csv`` (atomically); its path."""
    out = Path(out_csv)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp")
    with open(tmp, "w", newline="", encoding="utf-8", errors="surrogateescape") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(SUMMARY_COLUMNS)
        for row in summarise(results_csv, inputs, features):
            writer.writerow([cell(row[c]) for c in SUMMARY_COLUMNS])
    os.replace(tmp, out)
    return out
