"""Does the soft method need the paper's clean-up steps? And do large sigmas flag wrong frames?

Runs the soft estimator on the benchmark's frames (same seed) with the default clean-up (the
outline's sigma ~ 1 px smoothing of the soft mask) and with an added grey-level opening
(min then max filter, radius 1 and 2 px: the paper's erosion/dilation, differentiable), and
reports accuracy for each; then, for the default, how the error grows with the reported sigma.
Writes experiments/results/ablation_cleanup.md.

    python experiments/ablation_cleanup.py [--quick]
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from benchmark import RESULTS, make_frames, metrics
from tqdm import tqdm

import sinkjax as sj


def _result(est: sj.SoftEstimate, name: str) -> sj.FrameResult:
    """The numbers of one estimate as a results row (no overlay): what ``metrics`` reads."""
    status = sj.Status.from_code(int(est.status))
    if status == sj.Status.OK and not np.all(np.isfinite(est.params)):
        status = sj.Status.FIT_FAILED  # as estimate_batch reports a non-finite fit
    if not status.measured:
        return sj.FrameResult(image=name, status=status)
    return sj.FrameResult(
        image=name,
        status=status,
        sinkage_mm=float(est.sinkage_mm),
        sinkage_std_mm=float(est.sinkage_std_mm),
        theta1_deg=float(np.degrees(est.theta1_rad)),
        theta1_std_deg=float(np.degrees(est.theta1_std_rad)),
        theta2_deg=float(np.degrees(est.theta2_rad)),
        theta2_std_deg=float(np.degrees(est.theta2_std_rad)),
    )


def run(frames: list, open_radius_px: int) -> list:
    out = []
    cache: dict = {}
    for f in tqdm(frames, desc=f"open {open_radius_px}", leave=False):
        rig = f.rig
        key = (f.image.shape, rig.confidence_rect, rig.travel, rig.wheel_radius_mm)
        if key not in cache:
            cache[key] = jax.jit(
                functools.partial(
                    sj.measure,
                    rect=rig.confidence_rect,
                    travel=rig.travel,
                    wheel_radius_mm=rig.wheel_radius_mm,
                    open_radius_px=open_radius_px,
                )
            )
        est = cache[key](jnp.asarray(f.image, jnp.float32) / 255.0, rig.segmentation)
        out.append(_result(jax.tree_util.tree_map(np.asarray, est), f.name))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=RESULTS / "ablation_cleanup.md")
    args = ap.parse_args(argv)
    n_rec, per = (3, 8) if args.quick else (10, 16)
    sizes = ((640, 480),) if args.quick else ((640, 480), (800, 600), (480, 360), (1280, 720))
    frames = make_frames(2026, n_rec, per, sizes=sizes, progress=False)
    lines = [
        f"Soft method, {len(frames)} benchmark frames (seed 2026).",
        "",
        "| clean-up | median rel. sinkage err (%) | p90 (%) | median θ1 err (deg) |"
        " median θ2 err (deg) | failed (%) |",
        "|---|---|---|---|---|---|",
    ]
    default_rows = None
    for radius in (0, 1, 2):
        rows = run(frames, radius)
        m = metrics(frames, rows)
        name = "smoothing only (default)" if radius == 0 else f"+ opening, radius {radius} px"
        lines.append(
            f"| {name} | {m['median_rel_sinkage_pct']:.2f} | {m['p90_rel_sinkage_pct']:.2f} | "
            f"{m['median_theta1_err_deg']:.2f} | {m['median_theta2_err_deg']:.2f} | "
            f"{m['failed_pct']:.1f} |"
        )
        if radius == 0:
            default_rows = rows
    # Error against reported sigma (default clean-up): quartiles of sigma.
    assert default_rows is not None
    err, sig = [], []
    for f, r in zip(frames, default_rows, strict=True):
        if r.status == "ok" and f.truth.contact:
            err.append(abs(r.sinkage_mm - f.truth.sinkage_mm))
            sig.append(r.sinkage_std_mm)
    err_a, sig_a = np.asarray(err), np.asarray(sig)
    order = np.argsort(sig_a)
    lines += [
        "",
        "Sinkage error against the reported sigma (default), frames in contact split into "
        "quarters by sigma:",
        "",
        "| sigma quarter | sigma range (mm) | median abs error (mm) | max abs error (mm) |",
        "|---|---|---|---|",
    ]
    for q, idx in enumerate(np.array_split(order, 4)):
        lines.append(
            f"| {q + 1} | {sig_a[idx].min():.2f}-{sig_a[idx].max():.2f} | "
            f"{np.median(err_a[idx]):.2f} | {err_a[idx].max():.2f} |"
        )
    rank = np.corrcoef(np.argsort(np.argsort(sig_a)), np.argsort(np.argsort(err_a)))[0, 1]
    lines.append(f"\nSpearman rank correlation of sigma and |error|: {rank:.2f}.")
    text = "\n".join(lines) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
