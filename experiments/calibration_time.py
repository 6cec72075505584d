"""Calibration's wall time as a user runs it, on both cores against one (issue 12: under 2 min).

Writes a recording with ``sinkjax synth`` (18 frames at 640x480, a hard preset), labels every
third frame with the renderer's truth, and times ``sinkjax calibrate LABELS.csv`` in fresh
processes, as a user runs it: once with an empty compile cache (cold), then warm, taking turns
with ``SINKJAX_FRAME_THREADS=1`` (calibration's candidate points, descents and polish steps one
after another) and the default (side by side on the machine's cores,
``sinkjax.xla.side_by_side``). Both must write the same rig file. Writes
``experiments/results/calibration_time[_seedN].{json,md}``.

    python experiments/calibration_time.py                    # hard_dust, seed 20267, 2 rounds
    python experiments/calibration_time.py --seed 20265 --rounds 3
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import runs

RESULTS = Path(__file__).parent / "results"


def _sinkjax(args: list[str], cwd: Path, **env: str) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "sinkjax.app.cli", *args],
        cwd=cwd,
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"sinkjax {' '.join(args)} failed:\n{proc.stderr[-2000:]}")
    return time.perf_counter() - t0


def _label_every_third(rec: Path) -> Path:
    with (rec / "truth.csv").open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    out = rec / "labels.csv"
    with out.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["image", "sinkage_mm", "theta1_deg", "theta2_deg"])
        for r in rows[::3]:
            w.writerow([r["image"], r["sinkage_mm"], r["theta1_deg"], r["theta2_deg"]])
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=20267)
    p.add_argument("--preset", default="hard_dust")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="sinkjax-caltime-") as tmp:
        root = Path(tmp)
        cache = str(root / "cache")
        _sinkjax(["synth", "rec", "--preset", args.preset, "--seed", str(args.seed),
                  "--frames", "18"], root)  # fmt: skip
        labels = _label_every_third(root / "rec")

        def calibrate(out: str, **env: str) -> float:
            seconds = _sinkjax(["calibrate", str(labels), "--out", out], root,
                               SINKJAX_CACHE_DIR=cache, **env)  # fmt: skip
            runs.log(f"calibrate -> {out}: {seconds:.1f} s")
            return seconds

        cold = calibrate("cold.toml")
        times: dict[str, list[float]] = {"one": [], "both": []}
        for k in range(args.rounds):
            times["one"].append(calibrate(f"one{k}.toml", SINKJAX_FRAME_THREADS="1"))
            times["both"].append(calibrate(f"both{k}.toml"))
        rigs = {(root / f).read_bytes() for f in ["cold.toml"] + [
            f"{v}{k}.toml" for v in ("one", "both") for k in range(args.rounds)]}  # fmt: skip
        shutil.rmtree(cache, ignore_errors=True)
    med = {k: statistics.median(v) for k, v in times.items()}
    data = {
        "seed": args.seed, "preset": args.preset, "rounds": args.rounds, "cold_s": cold,
        "warm_s": times, "median_s": med, "ratio_both_to_one": med["both"] / med["one"],
        "same_rig_file": len(rigs) == 1, "machine": runs.machine(),
        "seconds": time.perf_counter() - t_start,
    }  # fmt: skip
    suffix = "" if args.seed == 20267 and args.preset == "hard_dust" else f"_seed{args.seed}"
    args.out.mkdir(parents=True, exist_ok=True)
    runs.write_json(args.out / f"calibration_time{suffix}.json", data)

    def secs(v: list[float]) -> str:
        return ", ".join(f"{x:.1f}" for x in v)

    text = "\n".join(
        [
            "# Calibration's wall time as a user runs it (issue 12: under 2 minutes)",
            "",
            f"`sinkjax synth rec --preset {args.preset} --seed {args.seed} --frames 18` (640x480), "
            "every third frame labelled with the renderer's truth, then `sinkjax calibrate "
            f"rec/labels.csv` in a fresh process each time, on {data['machine']}.",
            "",
            "| run | wall [s] |",
            "|---|---:|",
            f"| empty compile cache (cold), both cores | {cold:.1f} |",
            f"| warm, `SINKJAX_FRAME_THREADS=1` (one after another) | {secs(times['one'])} |",
            f"| warm, default (side by side) | {secs(times['both'])} |",
            "",
            f"Warm medians: one after another {med['one']:.1f} s, side by side {med['both']:.1f} s "
            f"(**{data['ratio_both_to_one']:.2f}x**); the same rig file from every run: "
            f"{'yes' if data['same_rig_file'] else '**no**'}.",
            "",
        ]
    )
    (args.out / f"calibration_time{suffix}.md").write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
