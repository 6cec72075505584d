"""The demo: render a small synthetic recording, measure it, and compare with the truth."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

from .. import metrics
from .plots import QUANTITIES, Matched, match_truth, number, plot_accuracy
from .run import RunSummary, estimate_to_csv
from .sources import RIG_FILENAME, resolve_rig

DEMO_FRAMES = 12
DEMO_SEED = 0
DEMO_PRESET = "full"
# Relative sinkage errors are only meaningful where there is sinkage to speak of.
_MIN_SINKAGE_FOR_RELATIVE_MM = 1.0


@dataclass
class Accuracy:
    """Errors against the truth by the rule of :mod:`sinkjax.metrics`: failed frames are left
    out of the errors and counted in ``n_failed``; ``no_contact`` is a measurement of 0."""

    n_frames: int
    n_failed: int
    failed_by_status: dict[str, int]
    sinkage_abs_mm: list[float]
    sinkage_rel_pct: list[float]
    theta1_abs_deg: list[float]
    theta2_abs_deg: list[float]

    def table(self) -> str:
        """A short plain-text table: median and max of each error, then the failures."""
        rows = [
            ("|sinkage error| [mm]", self.sinkage_abs_mm),
            ("|sinkage error| [% of true]", self.sinkage_rel_pct),
            ("|theta1 error| [deg]", self.theta1_abs_deg),
            ("|theta2 error| [deg]", self.theta2_abs_deg),
        ]
        width = max(len(name) for name, _ in rows)
        lines = [f"{'':<{width}}  {'median':>8}  {'max':>8}  {'frames':>6}"]
        for name, values in rows:
            if values:
                med, top = f"{metrics.median(values):8.3f}", f"{metrics.maximum(values):8.3f}"
            else:
                med = top = f"{'n/a':>8}"
            lines.append(f"{name:<{width}}  {med}  {top}  {len(values):>6}")
        failures = ", ".join(f"{n} {s}" for s, n in sorted(self.failed_by_status.items()))
        lines.append(
            f"failures: {self.n_failed} of {self.n_frames}" + (f" ({failures})" if failures else "")
        )
        return "\n".join(lines)


def accuracy(matched: list[Matched]) -> Accuracy:
    """Absolute errors per quantity over the frames that have a truth (``sinkjax.metrics``);
    relative sinkage errors only where the true sinkage is at least 1 mm."""
    rows = [m for m in matched if m.truth is not None]
    status = [m.result.get("status", "?") for m in rows]
    failed = metrics.failed(status)
    by_status: dict[str, int] = {}
    for s, bad in zip(status, failed, strict=True):
        if bad:
            by_status[s] = by_status.get(s, 0) + 1
    errors: dict[str, list[float]] = {}
    rel: list[float] = []
    for col, _, truth_col, _, _ in QUANTITIES:
        true = [number(m.truth.get(truth_col)) for m in rows if m.truth is not None]
        est = [number(m.result.get(col)) for m in rows]
        errors[col] = metrics.finite(metrics.abs_error(true, est, status)).tolist()
        if col == "sinkage_mm":
            big = [t is not None and abs(t) >= _MIN_SINKAGE_FOR_RELATIVE_MM for t in true]
            pct = metrics.relative_error_pct(true, est, status)
            rel = metrics.finite(pct[big]).tolist()
    return Accuracy(
        len(rows),
        int(failed.sum()),
        by_status,
        errors["sinkage_mm"],
        rel,
        errors["theta1_deg"],
        errors["theta2_deg"],
    )


@dataclass
class DemoReport:
    out_dir: Path
    results_csv: Path
    overlay_dir: Path
    plot_png: Path
    summary: RunSummary
    accuracy: Accuracy


def _truth_images(truth_csv: Path) -> list[str]:
    with open(truth_csv, newline="", encoding="utf-8") as f:
        return [str(truth_csv.parent / row["image"]) for row in csv.DictReader(f)]


def run_demo(
    out_dir: str | Path = "sinkjax-demo",
    *,
    method: str = "soft",
    n_frames: int = DEMO_FRAMES,
    progress: bool = True,
) -> DemoReport:
    """Render the built-in recording into ``out_dir/recording``, measure it, plot and score it.

    Writes ``results.csv``, ``overlays/`` and ``accuracy.png`` in ``out_dir``. Raises
    MethodUnavailable if ``method`` cannot be imported.
    """
    from ..synth import write_recording

    out = Path(out_dir)
    recording = Path(
        write_recording(
            out / "recording",
            n_frames=n_frames,
            seed=DEMO_SEED,
            preset=DEMO_PRESET,
            progress=progress,
        )
    )
    truth_csv = recording / "truth.csv"
    rig = resolve_rig(rig_path=recording / RIG_FILENAME)
    # The truth lists exactly this run's frames, so leftovers of an older demo are not measured.
    images = _truth_images(truth_csv)
    results_csv = out / "results.csv"
    overlay_dir = out / "overlays"
    summary = estimate_to_csv(
        images, results_csv, rig=rig, method=method, overlay_dir=overlay_dir, progress=progress
    )
    plot_png = plot_accuracy(
        results_csv, truth_csv, out / "accuracy.png", title=f"sinkjax demo, method {method}"
    )
    return DemoReport(
        out,
        results_csv,
        overlay_dir,
        plot_png,
        summary,
        accuracy(match_truth(results_csv, truth_csv)),
    )
