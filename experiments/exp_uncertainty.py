"""Honest uncertainty: do the soft method's reported intervals cover the truth as often as they say?

Pools the soft method's per-frame results of the other experiments of this run (the
``*_frames.csv`` records in the cache folder: terrain, precision, depth and lighting frames, all
with exact truth) and, for every frame the soft method measured (status ``ok``) and that has
contact, compares the error |estimate - truth| with the reported one-sigma sigma:

- reliability diagram: for nominal central coverage p, the fraction of frames with
  |error| <= z_p sigma (z_p the uncertainty model's multiplier for level p:
  ``UncertaintyModel.multiplier``, a Student-t quantile), for z0, θ1 and θ2;
- error against reported sigma: per sigma bin, the RMS error (a calibrated sigma gives RMS = sigma).

Run the other experiments first (``run_all.py`` does).

    python experiments/exp_uncertainty.py [--quick] [--out-dir DIR] [--cache-dir DIR]
"""

from __future__ import annotations

import itertools
import math
import sys
import time
from typing import Any

import numpy as np
from common import records, report, runs

from sinkjax import metrics as sm
from sinkjax.soft.uncertainty import UncertaintyModel

NAME = "exp_uncertainty"
SOURCES = ("paper_terrain", "paper_precision", "paper_depth", "exp_lighting")
TABLE_LEVELS = (0.5, 0.68, 0.8, 0.9, 0.95, 0.99)
CURVE_LEVELS = tuple(float(p) for p in np.linspace(0.05, 0.99, 48))
N_SIGMA_BINS = 6


def z_for(p: float, q: str) -> float:
    """Half-width in sigmas of the soft method's central interval at level p for quantity q."""
    return float(UncertaintyModel().multiplier(p, q))


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion k / n."""
    if n == 0:
        return math.nan, math.nan
    p = k / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return mid - half, mid + half


def usable(recs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [
        r
        for r in recs
        if r.get("soft_status") == "ok"
        and r["true_sinkage"] > 0
        and all(math.isfinite(float(r[f"soft_{q}_std"])) for q in records.QUANTITIES)
    ]


def errors(recs: list[dict[str, Any]], q: str) -> tuple[np.ndarray, np.ndarray]:
    """The soft method's signed errors and reported sigmas of ``q`` per record."""
    err = records.signed_errors(recs, "soft", q)
    sd = np.asarray(records.estimates(recs, "soft", f"{q}_std"))
    return err, sd


def covered(recs: list[dict[str, Any]], q: str, p: float) -> np.ndarray:
    """1 / 0 per record: the central interval ± z_p σ holds the truth (``sinkjax.metrics``)."""
    return sm.covered(
        records.truth(recs, q),
        records.estimates(recs, "soft", q),
        records.estimates(recs, "soft", f"{q}_std"),
        records.statuses(recs, "soft"),
        k=z_for(p, q),
    )


def run(setup: runs.Setup) -> dict[str, Any]:
    t0 = time.perf_counter()
    pooled: dict[str, list[dict[str, Any]]] = {}
    for src in SOURCES:
        path = setup.cache_dir / f"{src}_frames.csv"
        if not path.is_file():
            raise FileNotFoundError(
                f"{path} is missing: run experiments/{src}.py"
                + (" --quick" if setup.quick else "")
                + " first (or experiments/run_all.py)"
            )
        pooled[src] = usable(records.load_records(path))
    recs = [r for rr in pooled.values() for r in rr]
    if not recs:
        raise RuntimeError("no frame measured by the soft method in the pooled records")

    rows = []
    summary: dict[str, Any] = {"frames": len(recs)}
    for q in records.QUANTITIES:
        err, sd = errors(recs, q)
        row = [f"{report.LABELS[q]} ({report.UNITS[q]})"]
        for p in TABLE_LEVELS:
            hits = covered(recs, q, p)
            k, n = int(np.nansum(hits)), sm.count(hits)
            lo, hi = wilson(k, n)
            row.append(f"{100 * k / n:.1f} [{100 * lo:.0f}-{100 * hi:.0f}]")
            summary[f"coverage_{q}_{round(100 * p)}"] = 100 * k / n
        rms_z = float(np.sqrt(np.mean((err / sd) ** 2)))
        row.append(f"{rms_z:.2f}")
        row.append(f"{np.median(np.abs(err)):.3g} / {np.median(sd):.3g}")
        summary[f"rms_z_{q}"] = rms_z
        rows.append(row)
    per_source = []
    for src, rr in pooled.items():
        if not rr:
            continue
        cells = [src, str(len(rr))]
        for q in records.QUANTITIES:
            cells.append(f"{sm.mean(covered(rr, q, 0.95)) * 100:.1f}")
        per_source.append(cells)
    _reliability_figure(setup, recs)
    _sigma_figure(setup, recs)
    text = "\n\n".join(
        [
            "# Honest uncertainty: coverage of the soft method's intervals",
            report.generated_line(setup, f"{NAME}.py", time.perf_counter() - t0, 0).replace(
                "; 0 rendered frames", f"; pools {len(recs)} soft-measured frames of this run"
            ),
            "Every frame of the other experiments that the soft method measured (status `ok`, "
            f"true contact), default rig; {sm.RULE_COVERAGE}. Empirical coverage (%) of the "
            "central interval ± z_p σ at nominal level p (z_p: `UncertaintyModel.multiplier`), "
            "with its 95 % Wilson interval; "
            "RMS z = RMS of error / σ (1 for a calibrated σ). Sources: "
            + ", ".join(f"`{s}`" for s in SOURCES)
            + ".",
            report.md_table(
                ["quantity"]
                + [f"{100 * p:g} % nominal" for p in TABLE_LEVELS]
                + ["RMS z", "median abs err / median σ"],
                rows,
            ),
            "Per experiment, empirical coverage (%) at 95 % nominal:",
            report.md_table(["experiment", "frames", "z0", "θ1", "θ2"], per_source),
            f"![reliability diagram]({NAME}_reliability.png)",
            f"![error vs sigma]({NAME}_sigma.png)",
        ]
    )
    report.write_md(setup, NAME, text)
    return summary


def _reliability_figure(setup: runs.Setup, recs: list[dict[str, Any]]) -> None:
    fig, axes = report.figure(1, 1, (5.8, 5.4))
    ax = axes[0, 0]
    levels = np.asarray(CURVE_LEVELS)
    ax.plot([0, 100], [0, 100], "k:", lw=1, label="ideal (empirical = nominal)")
    for q, colour in zip(records.QUANTITIES, ("#dd8452", "#4c72b0", "#55a868"), strict=True):
        emp = [100 * sm.mean(covered(recs, q, p)) for p in levels]
        ax.plot(100 * levels, emp, "-", color=colour, label=f"{report.LABELS[q]}")
    ax.set_xlabel("nominal coverage of ± z σ (%)")
    ax.set_ylabel("empirical coverage (%)")
    ax.set_xlim(0, 100)
    ax.set_ylim(0, 100)
    ax.set_title(f"Reliability of the soft method's intervals ({len(recs)} frames)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    report.save_figure(setup, fig, f"{NAME}_reliability")


def _sigma_figure(setup: runs.Setup, recs: list[dict[str, Any]]) -> None:
    fig, axes = report.figure(1, 3, (15.0, 4.6))
    for ax, q in zip(axes[0], records.QUANTITIES, strict=True):
        err, sd = errors(recs, q)
        a = np.maximum(np.abs(err), 1e-4)
        ax.scatter(sd, a, s=8, alpha=0.35, color="#dd8452", label="frames: |error|")
        edges = np.quantile(sd, np.linspace(0, 1, N_SIGMA_BINS + 1))
        xs, rms = [], []
        for lo, hi in itertools.pairwise(edges):
            sel = (sd >= lo) & (sd <= hi)
            if sel.sum() >= 3:
                xs.append(float(np.median(sd[sel])))
                rms.append(float(np.sqrt(np.mean(err[sel] ** 2))))
        ax.plot(xs, rms, "o-", color="k", label="RMS error per σ bin")
        lim = [float(sd.min()) * 0.8, float(sd.max()) * 1.25]
        ax.plot(lim, lim, "--", color="#4c72b0", label="RMS error = σ (calibrated)")
        ax.plot(lim, [1.96 * v for v in lim], ":", color="#4c72b0", label="1.96 σ")
        report.log_axis(ax, "x")
        report.log_axis(ax)
        ax.set_xlabel(f"reported σ of {report.LABELS[q]} ({report.UNITS[q]})")
        ax.set_ylabel(f"|error| of {report.LABELS[q]} ({report.UNITS[q]})")
        ax.set_title(f"{report.LABELS[q]}: error vs reported σ")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("Soft method: error against its reported uncertainty")
    report.save_figure(setup, fig, f"{NAME}_sigma")


def main(argv: list[str] | None = None) -> int:
    setup, _ = runs.parse_args(__doc__.splitlines()[0], argv)
    runs.timed(run, setup, NAME)
    return 0


if __name__ == "__main__":
    sys.exit(main())
