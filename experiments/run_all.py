"""Run every paper-reproduction experiment and write the results index (``make experiments``).

1. ``paper_terrain``   terrain adaptability (paper Fig. 8)
2. ``paper_precision`` precision per slip and load (paper Tables 2-3)
3. ``paper_depth``     error against sinkage depth (paper Fig. 9)
4. ``exp_lighting``    light and shadow, classic vs soft vs soft-calibrated
5. ``exp_uncertainty`` coverage of the soft method's intervals (pools 1-4)
6. ``exp_calibration`` gradient calibration vs grid search (``calibration_vs_grid.py``'s numbers)
7. ``exp_speed``       frames/s by image and batch size (``bench.py``'s numbers)

1-4 run in two worker processes (one per core of the reference machine; ``--jobs 1``: one), each
compiling the soft method once for all its experiments; 5-7 then read their outputs here. Writes
``README.md`` (the index with the headline table) and every experiment's ``.md`` and ``.png``
into the output folder: ``experiments/results`` (full) or ``experiments/results/quick``
(``--quick``: 320x240 and a few frames each, a smoke run).

    python experiments/run_all.py [--quick] [--out-dir DIR] [--jobs 2] [--bench] [--calibration]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from common import paper, records, report, runs

from sinkjax import metrics as sm

COMPUTE = ("exp_lighting", "paper_precision", "paper_terrain", "paper_depth")  # longest first
READERS = ("exp_uncertainty", "exp_calibration", "exp_speed")
ORDER = ("paper_terrain", "paper_precision", "paper_depth", "exp_lighting", *READERS)
TITLES = {
    "paper_terrain": ("Terrain adaptability (paper Fig. 8)", ["paper_terrain.png"]),
    "paper_precision": ("Precision per slip and load (paper Tables 2-3)", ["paper_precision.png"]),
    "paper_depth": ("Error against sinkage depth (paper Fig. 9)", ["paper_depth.png"]),
    "exp_lighting": ("Light and shadow (paper's future work)", ["exp_lighting.png"]),
    "exp_uncertainty": (
        "Honest uncertainty: interval coverage",
        ["exp_uncertainty_reliability.png", "exp_uncertainty_sigma.png"],
    ),
    "exp_calibration": ("Calibration: gradient vs grid search", ["exp_calibration.png"]),
    "exp_speed": ("Speed by image and batch size", ["exp_speed.png"]),
}


def _worker_command(names: tuple[str, ...], setup: runs.Setup) -> list[str]:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--only", ",".join(names)]
    cmd += ["--out-dir", str(setup.out_dir), "--cache-dir", str(setup.cache_dir)]
    return cmd + ["--seed", str(setup.seed)] + (["--quick"] if setup.quick else [])


def _run_in_process(name: str, setup: runs.Setup, refresh: bool = False) -> bool:
    """Run one experiment module's ``run`` here; False (and the traceback logged) on failure."""
    import importlib
    import traceback

    module = importlib.import_module(name)
    try:
        if name in ("exp_calibration", "exp_speed"):
            runs.timed(lambda s: module.run(s, refresh=refresh), setup, name)
        else:
            runs.timed(module.run, setup, name)
    except Exception:
        runs.log(f"{name}: FAILED\n{traceback.format_exc()}")
        return False
    return True


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="320x240, a few frames each (< 3 min)")
    p.add_argument("--out-dir", type=Path, default=None, help="output folder for .md and .png")
    p.add_argument("--cache-dir", type=Path, default=None, help="per-frame records (CSV, JSON)")
    p.add_argument("--seed", type=int, default=2024, help="base seed (2024)")
    p.add_argument("--jobs", type=int, default=2, help="worker processes for 1-4 (2)")
    p.add_argument("--bench", action="store_true", help="rerun bench.py (alone, at the end)")
    p.add_argument(
        "--calibration", action="store_true", help="rerun calibration_vs_grid.py (minutes)"
    )
    p.add_argument("--only", default=None, help=argparse.SUPPRESS)  # a worker: these, in-process
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    setup = runs.make_setup(args.quick, args.out_dir, args.cache_dir, args.seed)
    if args.only:
        ok = [_run_in_process(name, setup) for name in args.only.split(",")]
        return 0 if all(ok) else 1
    for name in (*COMPUTE, *READERS):
        for stale in (
            setup.cache_dir / f"{name}_frames.csv",
            setup.cache_dir / f"{name}_run.json",
            setup.cache_dir / f"{name}_summary.json",
        ):
            stale.unlink(missing_ok=True)
    runs.log(f"run_all ({setup.mode}): out {setup.out_dir}, cache {setup.cache_dir}")
    failed: list[str] = []
    # Lighting (calibration: a long compile) in one worker, the paper experiments in the other;
    # each worker compiles the soft method once for all its experiments.
    groups = [COMPUTE[:1], COMPUTE[1:]] if args.jobs > 1 else [COMPUTE]
    procs = [(g, subprocess.Popen(_worker_command(g, setup))) for g in groups]
    for group, proc in procs:
        if proc.wait():
            failed += [n for n in group if runs.load_summary(setup.cache_dir, n) is None]
    for name in READERS:
        if name == "exp_uncertainty" and failed:
            failed.append(name)  # it pools the failed experiments' records
            continue
        refresh = {"exp_calibration": args.calibration, "exp_speed": args.bench}.get(name, False)
        if not _run_in_process(name, setup, refresh):
            failed.append(name)
    seconds = time.perf_counter() - t0
    index = write_index(setup, seconds, failed)
    runs.log(
        f"run_all: wrote {index} in {seconds:.0f} s" + (f"; FAILED: {failed}" if failed else "")
    )
    return 1 if failed else 0


# ----------------------------------------------------------------------------- index


def _pct(x: Any, nd: int = 1) -> str:
    cell = report.fmt(None if x is None else float(x), nd)
    return cell if cell == "—" else f"{cell} %"


def headline(s: dict[str, dict[str, Any]]) -> list[list[str]]:
    """The headline rows: quantity, paper, classic, soft, where."""
    rows = []
    pr = s.get("paper_precision")
    if pr:
        for q, short in (("sinkage", "REDS"), ("theta1", "REEA"), ("theta2", "REDA")):
            rows.append(
                [
                    f"{report.LABELS[q]}: relative error, flat terrain, mean of the 16 experiments "
                    f"(Tables 2-3, {short})",
                    _pct(pr[f"paper_{q}"], 2),
                    _pct(pr[f"classic_{q}"], 2),
                    _pct(pr[f"soft_{q}"], 2),
                    "[precision](paper_precision.md)",
                ]
            )
    dp = s.get("paper_depth")
    if dp:
        rows.append(
            [
                f"sinkage: median relative error, z0 ≥ 5 mm ({dp['deep']} frames, 5-40 mm)",
                f"~{paper.PAPER_CLAIM_SINKAGE_PCT:g} % (claim)",
                _pct(dp["classic_deep_rel_pct"]),
                _pct(dp["soft_deep_rel_pct"]),
                "[depth](paper_depth.md)",
            ]
        )
        rows.append(
            [
                "angles: median relative error θ1 / θ2, z0 ≥ 5 mm",
                f"~{paper.PAPER_CLAIM_ANGLE_PCT:g} % (claim)",
                f"{_pct(dp['classic_deep_theta1_rel_pct'])} / "
                f"{_pct(dp['classic_deep_theta2_rel_pct'])}",
                f"{_pct(dp['soft_deep_theta1_rel_pct'])} / {_pct(dp['soft_deep_theta2_rel_pct'])}",
                "[depth](paper_depth.md)",
            ]
        )
        for tag, span in (("shallow", "2-5 mm"), ("tiny", "0.5-2 mm")):
            rows.append(
                [
                    f"sinkage {span} ({dp[tag]} frames): median relative / absolute error; "
                    "frames read as no contact / failed",
                    '"lower accuracy" below 5 mm (no number)',
                    *(
                        f"{_pct(dp[f'{m}_{tag}_rel_pct'])} / "
                        f"{report.fmt(dp[f'{m}_{tag}_abs_mm'])} mm; "
                        f"{dp[f'{m}_{tag}_no_contact']} / {dp[f'{m}_{tag}_failed']}"
                        for m in ("classic", "soft")
                    ),
                    "[depth](paper_depth.md)",
                ]
            )
    te = s.get("paper_terrain")
    if te:
        n = te["ordering_checked"]
        rows.append(
            [
                "terrain adaptability: raised reads deeper, hollow and rough shallower than the "
                f"flat-level sensor (runs of {n})",
                '"corresponds to the design"',
                f"{te['ordering_classic']}/{n} (truth {te['ordering_truth']}/{n})",
                f"{te['ordering_soft']}/{n}",
                "[terrain](paper_terrain.md)",
            ]
        )
        rows.append(
            [
                "terrain runs: median absolute sinkage error (all 12 runs)",
                "—",
                f"{report.fmt(te['median_abs_err_classic_mm'])} mm",
                f"{report.fmt(te['median_abs_err_soft_mm'])} mm",
                "[terrain](paper_terrain.md)",
            ]
        )
    li = s.get("exp_lighting")
    if li:
        factors = ("shadow", "light", "cast", "dust")
        worst = {
            m: sm.maximum(li[f"{f}_max_{m}_rel_pct"] for f in factors)
            for m in ("classic", "soft", "calibrated")
        }
        most_failed = {
            m: max(int(li[f"{f}_max_{m}_failed"]) for f in factors)
            for m in ("classic", "soft", "calibrated")
        }
        rows.append(
            [
                f"light and shadow ({li['test_frames']} test frames): median relative sinkage "
                "error over all conditions; failed frames (soft-calibrated in brackets)",
                "future work",
                f"{_pct(li['all_classic_rel_pct'])}; {li['all_classic_failed']}",
                f"{_pct(li['all_soft_rel_pct'])}; {li['all_soft_failed']} "
                f"({_pct(li['all_calibrated_rel_pct'])}; {li['all_calibrated_failed']})",
                "[lighting](exp_lighting.md)",
            ]
        )
        rows.append(
            [
                "light and shadow: worst condition's median relative sinkage error; most failed "
                "frames in one condition (soft-calibrated in brackets)",
                "future work",
                f"{_pct(worst['classic'])}; {most_failed['classic']}",
                f"{_pct(worst['soft'])}; {most_failed['soft']} "
                f"({_pct(worst['calibrated'])}; {most_failed['calibrated']})",
                "[lighting](exp_lighting.md)",
            ]
        )
    un = s.get("exp_uncertainty")
    if un:
        cov = " / ".join(_pct(un[f"coverage_{q}_95"]) for q in records.QUANTITIES)
        rows.append(
            [
                f"95 % intervals: empirical coverage z0 / θ1 / θ2 ({un['frames']} frames)",
                "no uncertainty",
                "no uncertainty",
                cov,
                "[uncertainty](exp_uncertainty.md)",
            ]
        )
    ca = s.get("exp_calibration")
    if ca:
        rows.append(
            [
                "hard lighting: held-out median relative sinkage error, default → grid search → "
                f"gradient calibration ({ca['rigs']} rigs, {ca['source']})",
                "hand-tuned P_a/P_d",
                "—",
                f"{_pct(ca['median_default_pct'])} → {_pct(ca['median_grid_pct'])} → "
                f"{_pct(ca['median_calibrated_pct'])}",
                "[calibration](exp_calibration.md)",
            ]
        )
    sp = s.get("exp_speed")
    if sp:
        for key in sp:
            if key.endswith("_classic_fps"):
                size = key.removesuffix("_classic_fps")
                rows.append(
                    [
                        f"throughput at {size} (frames/s, CPU; soft batch "
                        f"{sp[f'{size}_soft_batch']})",
                        "—",
                        report.fmt(sp[key]),
                        report.fmt(sp[f"{size}_soft_fps"]),
                        "[speed](exp_speed.md)",
                    ]
                )
    return rows


def write_index(setup: runs.Setup, seconds: float, failed: list[str]) -> Path:
    summaries = {n: s for n in ORDER if (s := runs.load_summary(setup.cache_dir, n)) is not None}
    flag = " --quick" if setup.quick else ""
    lines = [
        "# Paper experiments, reproduced and extended"
        + (" (quick smoke run)" if setup.quick else ""),
        f"Generated by `python experiments/run_all.py{flag}` (`make experiments"
        f"{'-quick' if setup.quick else ''}`) in {seconds / 60:.1f} min ({seconds:.0f} s) on "
        f"{runs.machine()}; seed {setup.seed}, {setup.width}x{setup.height} px frames of one "
        "synthetic camera set-up modelled on the paper's rig (R = 140 mm, 28 lugs 15 mm high, "
        "one lamp). Every number below is produced by the scripts; the paper's numbers are "
        f"copied from its text (Tables 2-3 and its claims). Errors: {sm.RULE}.",
        "The classic method is this project's re-implementation of the paper's pipeline "
        "(`sinkjax.estimate_classic`, default options); the soft method is "
        "`sinkjax.estimate_batch` with the default rig. Errors are against exact "
        "synthetic truth (Eqs. 1-3 on the true surface); the paper's own errors were against "
        "a displacement sensor and hand-measured angles on real images, so the paper column "
        "is context, not a like-for-like score.",
        "## Headline",
        report.md_table(
            ["quantity", "paper", "classic (paper's method)", "soft", "details"],
            headline(summaries),
        ),
    ]
    if failed:
        lines.append(f"**Failed in this run:** {', '.join(failed)} (see the log).")
    lines.append("## Experiments")
    items = []
    for i, name in enumerate(ORDER, start=1):
        title, figs = TITLES[name]
        s = summaries.get(name)
        took = f" ({s['seconds']:.0f} s)" if s else " (missing)"
        figs_md = ", ".join(f"[{f}]({f})" for f in figs)
        items.append(f"{i}. [{title}]({name}.md){took}: {figs_md}")
    lines.append("\n".join(items))
    lines.append(
        "Per-frame records (CSV) and summaries (JSON) of this run are in "
        f"`{os.path.relpath(setup.cache_dir, setup.out_dir)}` (not committed)."
    )
    for name in ORDER:
        title, figs = TITLES[name]
        if (setup.out_dir / figs[0]).is_file():
            lines.append(f"### {title}\n\n![{title}]({figs[0]})")
    path = setup.out_dir / "README.md"
    path.write_text("\n\n".join(lines) + "\n", encoding="utf-8")
    return path


if __name__ == "__main__":
    sys.exit(main())
