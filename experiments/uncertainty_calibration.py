"""Fit the soft estimator's uncertainty model (UncertaintyModel defaults) on held-out data.

Renders synthetic recordings with a seed DISJOINT from the benchmark's, runs the soft method with
the raw delta-method sigma (no scale, no floor), and fits, per quantity, sigma^2 = (a sigma_raw)^2
+ f^2: the shape (a against f) by maximum likelihood of the errors under a Student-t (so a few
gross errors don't set it), then one common factor so that +-1.96 sigma covers 95% of this set
(the errors have heavier tails than a Gaussian). Prints the constants and their coverage.

    python experiments/uncertainty_calibration.py [--recordings 8 --frames-per 16]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from benchmark import make_frames

import sinkjax as sj


def fit(err: np.ndarray, raw: np.ndarray) -> tuple[float, float]:
    best = (np.inf, 1.0, 0.0)
    for a in np.linspace(0.5, 6.0, 56):
        for f in np.linspace(0.0, 2.0, 81):
            var = (a * raw) ** 2 + f**2 + 1e-12
            # Student-t (nu = 4) negative log likelihood: a few gross errors don't set the scale.
            nll = np.sum(0.5 * np.log(var) + 2.5 * np.log1p(err**2 / (4 * var)))
            if nll < best[0]:
                best = (nll, a, f)
    return best[1], best[2]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=7)  # the benchmark uses 2026
    ap.add_argument("--recordings", type=int, default=8)
    ap.add_argument("--frames-per", type=int, default=16)
    args = ap.parse_args(argv)
    frames = make_frames(args.seed, args.recordings, args.frames_per)
    rows = []
    recs: dict[int, list] = {}
    for f in frames:
        recs.setdefault(f.recording, []).append(f)
    for group in recs.values():
        for i in range(0, len(group), 8):
            chunk = group[i : i + 8]
            res = sj.estimate_batch(
                [f.image for f in chunk],
                chunk[0].rig,
                [f.name for f in chunk],
                pad_to=8,
                uncertainty=sj.UncertaintyModel.raw(),
            )
            rows += list(zip(chunk, res, strict=True))
    z_err, z_raw, a_err, a_raw = [], [], [], []
    for f, r in rows:
        t = f.truth
        if r.status != "ok" or not t.contact:
            continue
        px_per_mm = r.radius_px / f.rig.wheel_radius_mm
        z_err.append((r.sinkage_mm - t.sinkage_mm) * px_per_mm)
        z_raw.append(r.sinkage_std_mm * px_per_mm)
        a_err += [r.theta1_deg - t.theta1_deg, r.theta2_deg - t.theta2_deg]
        a_raw += [r.theta1_std_deg, r.theta2_std_deg]
    ze, zr, ae, ar = map(np.asarray, (z_err, z_raw, a_err, a_raw))
    sa, sf = fit(ze, zr)
    aa, af = fit(ae, ar)
    ks = np.quantile(np.abs(ze) / np.sqrt((sa * zr) ** 2 + sf**2), 0.95) / 1.96
    ka = np.quantile(np.abs(ae) / np.sqrt((aa * ar) ** 2 + af**2), 0.95) / 1.96
    sa, sf, aa, af = sa * ks, sf * ks, aa * ka, af * ka
    model = sj.UncertaintyModel(float(sa), float(aa), float(sf), float(af))
    zs = np.sqrt((sa * zr) ** 2 + sf**2)
    as_ = np.sqrt((aa * ar) ** 2 + af**2)
    print(f"{len(ze)} frames in contact")
    cz = 100 * np.mean(np.abs(ze) <= 1.96 * zs)
    ca = 100 * np.mean(np.abs(ae) <= 1.96 * as_)
    print(f"sinkage: scale {sa:.2f}, floor {sf:.3f} px -> coverage {cz:.1f}%")
    print(f"angles:  scale {aa:.2f}, floor {af:.3f} deg -> coverage {ca:.1f}%")
    print(model)
    return 0


if __name__ == "__main__":
    sys.exit(main())
