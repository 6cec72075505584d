"""Soft vs classic on the project's synthetic benchmark (issue acceptance numbers).

Renders a seeded benchmark (recordings of several rigs: all terrains, lugs, holes, shadows,
specular highlights, several wheel and soil colours, several image sizes), runs both methods on
the same frames, and writes ``experiments/results/benchmark.md`` (+ a CSV of every frame).

    python experiments/benchmark.py            # 160 frames
    python experiments/benchmark.py --quick    # 24 frames, for the test suite
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from sinkjax.app.results import FrameResult
from sinkjax.classic.estimator import estimate_classic
from sinkjax.rig import Rig
from sinkjax.soft.estimator import estimate_batch
from sinkjax import synth as S

SIZES = ((640, 480), (800, 600), (480, 360), (1280, 720))
RESULTS = Path(__file__).parent / "results"


@dataclass
class Frame:
    image: np.ndarray
    truth: S.Truth
    rig: Rig
    recording: int
    name: str


def make_frames(
    seed: int,
    n_recordings: int,
    frames_per: int,
    presets: tuple[str, ...] = ("full",),
    sizes: tuple[tuple[int, int], ...] = SIZES,
    progress: bool = True,
) -> list[Frame]:
    """Seeded synthetic frames grouped in recordings (one rig each)."""
    rng = np.random.default_rng(seed)
    frames: list[Frame] = []
    bar = tqdm(total=n_recordings * frames_per, desc="render", disable=not progress)
    for rec in range(n_recordings):
        width, height = sizes[rec % len(sizes)]
        preset = presets[rec % len(presets)]
        scenes = S.recording_scenes(rng, frames_per, preset=preset, width=width, height=height)
        rig = S.rig_for(scenes[0])
        for i, scene in enumerate(scenes):
            image, truth = S.render(scene, seed=seed * 100_003 + rec * 1000 + i)
            frames.append(Frame(image, truth, rig, rec, f"r{rec:02d}_{preset}_{i:03d}"))
            bar.update()
    bar.close()
    return frames


def run_soft(
    frames: list[Frame], batch: int = 8, progress: bool = True
) -> tuple[list[FrameResult], float]:
    """Soft results in frame order, and the steady-state seconds per frame (compile excluded)."""
    out: list[FrameResult] = []
    timed = 0.0
    n_timed = 0
    seen: set[tuple] = set()
    recs: dict[int, list[Frame]] = {}
    for f in frames:
        recs.setdefault(f.recording, []).append(f)
    bar = tqdm(total=len(frames), desc="soft", disable=not progress)
    for group in recs.values():
        for i in range(0, len(group), batch):
            chunk = group[i : i + batch]
            key = (chunk[0].image.shape, chunk[0].rig.confidence_rect, chunk[0].rig.travel)
            if key not in seen:  # compile outside the timing
                estimate_batch(
                    [f.image for f in chunk], chunk[0].rig, [f.name for f in chunk], pad_to=batch
                )
                seen.add(key)
            t0 = time.perf_counter()
            out += estimate_batch(
                [f.image for f in chunk], chunk[0].rig, [f.name for f in chunk], pad_to=batch
            )
            timed += time.perf_counter() - t0
            n_timed += len(chunk)
            bar.update(len(chunk))
    bar.close()
    return out, timed / max(n_timed, 1)


def run_classic(
    frames: list[Frame], progress: bool = True, refine: bool = False
) -> tuple[list[FrameResult], float]:
    """The paper's pipeline (``refine=False``) or with sub-pixel refinement, in frame order."""
    out = []
    if frames:  # warm-up (jit of Eq. 1)
        estimate_classic(frames[0].image, frames[0].rig, frames[0].name, refine=refine)
    t0 = time.perf_counter()
    desc = "classic+refine" if refine else "classic"
    for f in tqdm(frames, desc=desc, disable=not progress):
        out.append(estimate_classic(f.image, f.rig, f.name, refine=refine))
    return out, (time.perf_counter() - t0) / max(len(frames), 1)


def metrics(frames: list[Frame], results: list[FrameResult]) -> dict[str, float]:
    """The issue's acceptance numbers for one method."""
    deep_rel, shallow_abs, t1, t2, cov = [], [], [], [], {"z": [], "t1": [], "t2": []}
    failed = 0
    for f, r in zip(frames, results, strict=True):
        t = f.truth
        if r.status not in ("ok", "no_contact"):
            failed += 1
            continue
        z = r.sinkage_mm if r.sinkage_mm is not None else 0.0
        a1 = r.theta1_deg if r.theta1_deg is not None else 0.0
        a2 = r.theta2_deg if r.theta2_deg is not None else 0.0
        if t.contact and t.sinkage_mm > 5.0:
            deep_rel.append(abs(z - t.sinkage_mm) / t.sinkage_mm)
        elif t.contact:
            shallow_abs.append(abs(z - t.sinkage_mm))
        if t.contact:
            t1.append(abs(a1 - t.theta1_deg))
            t2.append(abs(a2 - t.theta2_deg))
        if r.status == "ok" and r.sinkage_std_mm:
            cov["z"].append(abs(z - t.sinkage_mm) <= 1.96 * r.sinkage_std_mm)
            cov["t1"].append(abs(a1 - t.theta1_deg) <= 1.96 * (r.theta1_std_deg or 0.0))
            cov["t2"].append(abs(a2 - t.theta2_deg) <= 1.96 * (r.theta2_std_deg or 0.0))

    def q(a: list[float], p: float) -> float:
        return float(np.percentile(a, p)) if a else float("nan")

    def m(a: list) -> float:
        return float(np.mean(a)) if a else float("nan")

    return {
        "frames": len(frames),
        "median_rel_sinkage_pct": 100 * q(deep_rel, 50),
        "p90_rel_sinkage_pct": 100 * q(deep_rel, 90),
        "median_theta1_err_deg": q(t1, 50),
        "median_theta2_err_deg": q(t2, 50),
        "shallow_median_abs_mm": q(shallow_abs, 50),
        "failed_pct": 100 * failed / max(len(frames), 1),
        "coverage_sinkage_pct": 100 * m(cov["z"]),
        "coverage_theta1_pct": 100 * m(cov["t1"]),
        "coverage_theta2_pct": 100 * m(cov["t2"]),
    }


ROWS = (
    ("median relative sinkage error, z0 > 5 mm (%)", "median_rel_sinkage_pct", "<= 2"),
    ("90th percentile relative sinkage error, z0 > 5 mm (%)", "p90_rel_sinkage_pct", "<= 8"),
    ("median abs θ1 error (deg)", "median_theta1_err_deg", "<= 0.5"),
    ("median abs θ2 error (deg)", "median_theta2_err_deg", "<= 0.5"),
    ("shallow (z0 <= 5 mm): median abs sinkage error (mm)", "shallow_median_abs_mm", "<= 0.5"),
    ("failed frames (%)", "failed_pct", "<= 2"),
    ("±1.96σ coverage, sinkage (%)", "coverage_sinkage_pct", "90-98"),
    ("±1.96σ coverage, θ1 (%)", "coverage_theta1_pct", "90-98"),
    ("±1.96σ coverage, θ2 (%)", "coverage_theta2_pct", "90-98"),
)


def table(columns: list[tuple[str, dict, float]]) -> str:
    """Rows of ROWS plus time per frame; one column per (name, metrics, seconds per frame)."""
    names = " | ".join(name for name, _, _ in columns)
    lines = [f"| quantity | {names} | target (soft) |", "|---" * (len(columns) + 2) + "|"]

    def fmt(v: float) -> str:
        return "—" if v != v else f"{v:.2f}"

    for label, key, target in ROWS:
        cells = " | ".join(fmt(m[key]) for _, m, _ in columns)
        lines.append(f"| {label} | {cells} | {target} |")
    times = " | ".join(f"{1000 * s:.1f}" for _, _, s in columns)
    lines.append(f"| time per frame, steady state (ms) | {times} | soft <= 1.5x classic |")
    return "\n".join(lines)


def write_csv(
    path: Path, frames: list[Frame], soft: list[FrameResult], classic: list[FrameResult]
) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            [
                "frame",
                "terrain",
                "true_sinkage_mm",
                "true_theta1_deg",
                "true_theta2_deg",
                "soft_status",
                "soft_sinkage_mm",
                "soft_sinkage_std_mm",
                "soft_theta1_deg",
                "soft_theta1_std_deg",
                "soft_theta2_deg",
                "soft_theta2_std_deg",
                "classic_status",
                "classic_sinkage_mm",
                "classic_theta1_deg",
                "classic_theta2_deg",
            ]
        )
        for f, s, c in zip(frames, soft, classic, strict=True):
            t = f.truth
            w.writerow(
                [
                    f.name,
                    t.terrain,
                    t.sinkage_mm,
                    t.theta1_deg,
                    t.theta2_deg,
                    s.status,
                    s.sinkage_mm,
                    s.sinkage_std_mm,
                    s.theta1_deg,
                    s.theta1_std_deg,
                    s.theta2_deg,
                    s.theta2_std_deg,
                    c.status,
                    c.sinkage_mm,
                    c.theta1_deg,
                    c.theta2_deg,
                ]
            )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--recordings", type=int, default=10)
    ap.add_argument("--frames-per", type=int, default=16)
    ap.add_argument("--quick", action="store_true", help="24 frames, 640x480 only")
    ap.add_argument("--out", type=Path, default=RESULTS / "benchmark.md")
    args = ap.parse_args(argv)
    sizes = SIZES
    if args.quick:
        args.recordings, args.frames_per, sizes = 3, 8, ((640, 480),)
    frames = make_frames(args.seed, args.recordings, args.frames_per, sizes=sizes)
    soft, soft_s = run_soft(frames)
    classic, classic_s = run_classic(frames)
    refined, refined_s = run_classic(frames, refine=True)
    columns = [
        ("soft", metrics(frames, soft), soft_s),
        ("classic (the paper)", metrics(frames, classic), classic_s),
        ("classic + sub-pixel refinement", metrics(frames, refined), refined_s),
    ]
    text = (
        f"Benchmark: {len(frames)} synthetic frames, {args.recordings} rigs, sizes "
        f"{', '.join(f'{w}x{h}' for w, h in sizes)}, preset 'full', seed {args.seed}. "
        "Times are wall-clock on the machine that ran it, measured in one run.\n\n"
        + table(columns)
        + "\n"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    write_csv(args.out.with_suffix(".csv"), frames, soft, classic)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
