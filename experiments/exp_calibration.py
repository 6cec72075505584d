"""Calibration: gradient (``sinkjax calibrate``) against a grid search over P_a/P_d, as a figure.

Does not redo that experiment: it reads the numbers that ``experiments/calibration_vs_grid.py``
saved (``experiments/results/calibration_vs_grid.json``, or ``calibration_vs_grid_quick.json``
when only the quick run exists) and plots them: held-out median relative sinkage error with the
default thresholds, the best grid point and the calibrated thresholds per hard-lighting rig, and
what each search cost. ``--run`` first runs ``calibration_vs_grid.py`` (with ``--quick`` in quick
mode; it takes minutes and writes its own report into experiments/results).

    python experiments/exp_calibration.py [--quick] [--run] [--out-dir DIR] [--cache-dir DIR]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import report, runs

from sinkjax import metrics as sm

NAME = "exp_calibration"
SCRIPT = runs.HERE / "calibration_vs_grid.py"


def source(quick: bool) -> Path | None:
    """The calibration_vs_grid report to use: full unless in quick mode or only quick exists."""
    names = ["calibration_vs_grid_quick.json", "calibration_vs_grid.json"]
    for name in names if quick else names[::-1]:
        if (runs.RESULTS / name).is_file():
            return runs.RESULTS / name
    return None


def run_external(quick: bool) -> None:
    cmd = [sys.executable, str(SCRIPT)] + (["--quick"] if quick else [])
    runs.log(f"{NAME}: running {' '.join(cmd[1:])}")
    subprocess.run(cmd, check=True)


def run(setup: runs.Setup, *, refresh: bool = False) -> dict[str, Any]:
    t0 = time.perf_counter()
    if refresh or source(setup.quick) is None:
        run_external(setup.quick)
    src = source(setup.quick)
    assert src is not None, "calibration_vs_grid.py saved no numbers"
    data = json.loads(src.read_text(encoding="utf-8"))
    rows = data["rigs"]
    if not rows:
        raise RuntimeError(f"{src}: no rigs")
    rigs = [r["name"] for r in rows]
    err = {
        k: [100 * r[field]["sinkage_rel"] for r in rows]
        for k, field in (
            ("default", "default"),
            ("grid best", "grid"),
            ("calibrated", "calibrated"),
        )
    }
    cost = {
        "grid": ([r["grid_evals"] for r in rows], [r["grid_s"] for r in rows]),
        "calibration": ([r["cal_evals"] for r in rows], [r["cal_s"] for r in rows]),
    }
    _figure(setup, rigs, err, cost, src)
    png = src.with_suffix(".png")
    link = os.path.relpath(png, setup.out_dir)
    md_link = os.path.relpath(src.with_suffix(".md"), setup.out_dir)
    origin = data["generated"]
    table = report.md_table(
        [
            "rig",
            "default (%)",
            "grid best (%)",
            "calibrated (%)",
            "grid evals / s",
            "calibration evals / s",
        ],
        [
            [
                rig,
                report.fmt(err["default"][i], 1),
                report.fmt(err["grid best"][i], 1),
                report.fmt(err["calibrated"][i], 1),
                f"{cost['grid'][0][i]:.0f} / {cost['grid'][1][i]:.0f}",
                f"{cost['calibration'][0][i]:.0f} / {cost['calibration'][1][i]:.0f}",
            ]
            for i, rig in enumerate(rigs)
        ],
    )
    gain_grid = sm.median(np.asarray(err["default"]) / np.asarray(err["grid best"]))
    gain_cal = sm.median(np.asarray(err["default"]) / np.asarray(err["calibrated"]))
    doc = "\n\n".join(
        [
            "# Calibration: gradient vs grid search",
            f"Figure by `python experiments/{NAME}.py` from the numbers of "
            f"[`{src.with_suffix('.md').name}`]({md_link}) (saved in `{src.name}`; "
            f"{time.perf_counter() - t0:.0f} s); that report says: "
            f"{origin}",
            "Held-out median relative sinkage error (%) of the soft method per hard-lighting rig "
            "(6 labelled frames tune the thresholds, 20 other frames of the rig score them; as "
            "`sinkjax.calibrate` scores frames, a held-out frame the soft method does not measure "
            "as `ok` counts as 0 mm, a 100 % error):",
            table,
            f"Median error reduction over the default thresholds: grid best {gain_grid:.2f}x, "
            f"gradient calibration {gain_cal:.2f}x.",
            f"![calibration vs grid]({NAME}.png)",
            f"The original figure (with the loss curves): ![calibration_vs_grid]({link})",
        ]
    )
    report.write_md(setup, NAME, doc)
    return {
        "source": src.with_suffix(".md").name,
        "rigs": len(rigs),
        "median_default_pct": sm.median(err["default"]),
        "median_grid_pct": sm.median(err["grid best"]),
        "median_calibrated_pct": sm.median(err["calibrated"]),
        "gain_grid": gain_grid,
        "gain_calibrated": gain_cal,
    }


def _figure(
    setup: runs.Setup,
    rigs: list[str],
    err: dict[str, list[float]],
    cost: dict[str, tuple[list[float], list[float]]],
    src: Path,
) -> None:
    fig, axes = report.figure(1, 2, (12.0, 4.5))
    ax, ax2 = axes[0, 0], axes[0, 1]
    x = np.arange(len(rigs))
    bars = (
        ("default", "default thresholds", "#999999"),
        ("grid best", "grid search best", report.METHOD_COLOURS["classic"]),
        ("calibrated", "gradient calibration", report.METHOD_COLOURS["calibrated"]),
    )
    for j, (key, label, colour) in enumerate(bars):
        ax.bar(x + (j - 1) * 0.27, np.maximum(err[key], 0.05), 0.27, label=label, color=colour)
    report.log_axis(ax)
    ax.set_xticks(x, rigs, rotation=15)
    ax.set_xlabel("hard-lighting rig (preset/seed)")
    ax.set_ylabel("held-out median relative sinkage error (%)")
    ax.set_title("Soft method on held-out frames of each rig")
    ax.legend(fontsize=8)
    for j, (key, colour) in enumerate(
        (
            ("grid", report.METHOD_COLOURS["classic"]),
            ("calibration", report.METHOD_COLOURS["calibrated"]),
        )
    ):
        ax2.bar(
            x + (j - 0.5) * 0.4,
            cost[key][1],
            0.4,
            color=colour,
            label=f"{key} (wall s; labels: frame evaluations)",
        )
        for xi, (n, s) in enumerate(zip(*cost[key], strict=True)):
            ax2.text(xi + (j - 0.5) * 0.4, s, f"{n:.0f}", ha="center", va="bottom", fontsize=7)
    ax2.set_xticks(x, rigs, rotation=15)
    ax2.set_xlabel("hard-lighting rig (preset/seed)")
    ax2.set_ylabel("search time (s, wall clock)")
    ax2.set_title("Cost of each search")
    ax2.legend(fontsize=8)
    fig.suptitle(f"Gradient calibration vs grid search (numbers from {src.name})")
    report.save_figure(setup, fig, NAME)


def main(argv: list[str] | None = None) -> int:
    setup, args = runs.parse_args(
        __doc__.splitlines()[0], argv, run_help="first rerun calibration_vs_grid.py (minutes)"
    )
    runs.timed(lambda s: run(s, refresh=args.run), setup, NAME)
    return 0


if __name__ == "__main__":
    sys.exit(main())
