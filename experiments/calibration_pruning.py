"""Calibration with its grid and polish pruned, against measuring every point on every frame.

Calibration's loss is a sum of per-frame losses >= 0, so a grid point (or a polish step) whose
frames measured so far already sum to more than the lowest it would have to beat cannot be
chosen: ``calibrate(..., prune=True)`` (the default) stops measuring it there, frames whose loss
was highest at the rig's own point first (``compiled.loss_value``'s ``bound``). The result must
be the same; only the time and the number of frames measured change.

This renders one recording per preset (18 frames, 640x480; every third labelled with the
renderer's truth; the rim from the first 8 frames, as ``sinkjax calibrate`` of a LABELS.csv in
the recording's folder), compiles once (a first calibration, reported apart), then calibrates
each recording without and with pruning in one process, and writes
``experiments/results/calibration_pruning.{json,md}``.

    python experiments/calibration_pruning.py                  # hard_dust, hard_mix, hard_lowlight
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from common import runs
from loss_mask_once import N_FRAMES, recording

from sinkjax.calibration import calibrate, compiled as CL

RESULTS = Path(__file__).parent / "results"


def _loo(res: object) -> str:
    checks = res.checks  # type: ignore[attr-defined]
    return f"{100 * checks.loo_median_rel:.1f} % ({checks.loo_failed} not ok)"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=20266)
    p.add_argument("--presets", default="hard_dust,hard_mix,hard_lowlight")
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    t_start = time.perf_counter()
    measured: list[int] = []  # one entry per frame the compiled loss measured

    class Counted:
        def __init__(self, real: object) -> None:
            self.real = real

        def __call__(self, *a: object, **k: object) -> object:
            measured.append(1)
            return self.real(*a, **k)  # type: ignore[operator]

        def __getattr__(self, name: str) -> object:  # lower(), for the background compile
            return getattr(self.real, name)

    CL._loss_value = Counted(CL._loss_value)  # type: ignore[assignment]
    recs = {}
    for preset in args.presets.split(","):
        rec = recording(preset, args.seed)  # as loss_mask_once.py: every third of 18 labelled
        recs[preset] = (rec["frames"], rec["rig"])
    first = next(iter(recs))
    t0 = time.perf_counter()
    calibrate(*recs[first], steps=args.steps, seed=args.seed)
    cold = time.perf_counter() - t0
    runs.log(f"first calibration (compiles): {cold:.0f} s")
    rows = []
    for preset, (frames, rig) in recs.items():
        row: dict = {"preset": preset}
        results = {}
        for prune in (False, True):
            measured.clear()
            t0 = time.perf_counter()
            results[prune] = calibrate(frames, rig, steps=args.steps, seed=args.seed, prune=prune)
            name = "pruned" if prune else "whole"
            row[f"{name}_s"] = time.perf_counter() - t0
            row[f"{name}_frames"] = sum(measured)
        whole, pruned = results[False], results[True]
        row.update(
            ratio=row["pruned_s"] / row["whole_s"],
            frames_ratio=row["pruned_frames"] / row["whole_frames"],
            same_rig=bool(whole.rig == pruned.rig),
            loss_whole=whole.loss_after,
            loss_pruned=pruned.loss_after,
            # The leave-one-out check sees only the points measured on every frame.
            loo_whole=_loo(whole),
            loo_pruned=_loo(pruned),
        )
        rows.append(row)
        runs.log(
            f"{preset}: {row['whole_s']:.0f} s -> {row['pruned_s']:.0f} s, same {row['same_rig']}"
        )
    data = {"seed": args.seed, "steps": args.steps, "cold_s": cold, "rows": rows,
            "machine": runs.machine(), "seconds": time.perf_counter() - t_start}  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    runs.write_json(args.out / "calibration_pruning.json", data)
    lines = [
        "# Calibration with its grid and polish pruned (issue 12: calibration time)",
        "",
        f"Seed {args.seed}, one recording of {N_FRAMES} frames (640x480) per preset, 6 labelled, "
        f"{args.steps} Adam steps, on {data['machine']}; the first calibration, which compiles, "
        f"took {cold:.0f} s and is not in the table. Each recording calibrated without pruning "
        "(every point on every labelled frame), then with it, in one process.",
        "",
        "| preset | whole [s] | pruned [s] | ratio | frames measured, whole | pruned | ratio "
        "| same rig | loss | leave-one-out, whole | pruned |",
        "|---|---:|---:|---:|---:|---:|---:|---|---:|---|---|",
    ]
    lines += [
        f"| {r['preset']} | {r['whole_s']:.0f} | {r['pruned_s']:.0f} | {r['ratio']:.2f} | "
        f"{r['whole_frames']} | {r['pruned_frames']} | {r['frames_ratio']:.2f} | "
        f"{'yes' if r['same_rig'] else '**no**'} | {r['loss_pruned']:.4g} | {r['loo_whole']} | "
        f"{r['loo_pruned']} |"
        for r in rows
    ]
    lines += [
        "",
        "Leave-one-out: the median relative sinkage error of each labelled frame at the point "
        "the other frames choose, among the points measured on every frame (pruned: the grid "
        "points dropped early are not among them).",
    ]
    text = "\n".join(lines) + "\n"
    (args.out / "calibration_pruning.md").write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
