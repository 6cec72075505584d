"""Entry and exit angles (issue 14, item 1): the soft method's curved end tangents, ablated.

θ1 and θ2 come from where the soil surface meets the rim (A, B). The soft method fits each end
with a short curve (the tangent at the end plus a bend, ``sinkjax.soft.model``) over a window of
boundary next to the rim. This script renders full-mix recordings (lugs, holes, shadows, all five
terrains, four image sizes), prepares every frame once (mask, outline, the recording's rim, as
``sinkjax estimate`` does) and finishes it with three end models:

- ``curved`` the defaults;
- ``straight`` the same settings with the bend held at 0 (a straight tangent over the window);
- ``former`` the straight tangent with the settings before the curved ends (3.5 px clearance,
  a 0.12 r window of at most 30 px, a strong pull towards the equivalent line's angle, no robust
  loss), for the record;

and the classic method with sub-pixel refinement (``estimate_classic(refine=True)``) as a
reference. Reported: median and 90th percentile of |θ1|, |θ2| error over the frames with true
contact, per terrain and overall, and the share of frames measured (``ok``).

The settings were tuned on seeds 777 and 778; the default seed (2027) was not looked at before.

    python experiments/end_tangents.py                   # 10 recordings x 8 frames, seed 2027
    python experiments/end_tangents.py --seed 777 --quick
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from benchmark import SIZES, make_frames
from common import runs
from tqdm import tqdm

import sinkjax as sj
from sinkjax.soft.adaptive import default_segmenter
from sinkjax.soft.batch import SoftRecording, _float
from sinkjax.soft.estimator import finish, prepare, rig_arrays
from sinkjax.soft.settings import SoftSettings

RESULTS = Path(__file__).parent / "results"
VARIANTS: dict[str, dict[str, float]] = {
    "curved": {},
    "straight": {"end_bend_prior_points": 1e8},
    "former": {
        "end_bend_prior_points": 1e8,
        "end_clearance_px": 3.5,
        "end_window_fraction": 0.12,
        "end_window_max_px": 30.0,
        "end_angle_prior_points": 2.0,
        "end_loss_scale_px": 1e6,
    },
}


def settings_for(changes: dict[str, float]) -> SoftSettings:
    s = SoftSettings()
    for name, value in changes.items():
        s = eqx.tree_at(lambda t, n=name: getattr(t, n), s, jnp.asarray(value))
    return s


@jax.jit
def _prepare(image, seg, rig, rim):  # type: ignore[no-untyped-def]
    return prepare(image, default_segmenter(seg)(image, rig.rect_px), rim, None, rig.rim_range_px)


@jax.jit
def _finish(image, prepared, rig, settings):  # type: ignore[no-untyped-def]
    return finish(
        image,
        prepared,
        travel=rig.travel_sign,
        wheel_radius_mm=rig.wheel_radius_mm,
        uncertainty=rig.uncertainty,
        settings=settings,
    )


def measure(frames: list, progress: bool = True) -> dict[str, list[tuple[int, float, float]]]:
    """(status code, θ1 deg, θ2 deg) per frame for each variant, and for classic + refinement."""
    out: dict[str, list[tuple[int, float, float]]] = {name: [] for name in VARIANTS}
    out["classic + refinement"] = []
    settings = {name: settings_for(changes) for name, changes in VARIANTS.items()}
    recordings: dict[int, list] = {}
    for f in frames:
        recordings.setdefault(f.recording, []).append(f)
    bar = tqdm(total=len(frames), desc="frames", disable=not progress)
    for group in recordings.values():
        # The recording's rim from its first frames, as `sinkjax estimate` finds it.
        recording = SoftRecording()
        first = group[:8]
        recording([f.image for f in first], first[0].rig, [f.name for f in first])
        height, width = group[0].image.shape[:2]
        rim = recording.rim_for(height, width)
        rig = rig_arrays(group[0].rig)
        for f in group:
            image = _float(jnp.asarray(f.image))
            prepared = _prepare(image, f.rig.segmentation, rig, rim)
            for name in VARIANTS:
                e = _finish(image, prepared, rig, settings[name])
                t1, t2 = np.degrees(float(e.theta1_rad)), np.degrees(float(e.theta2_rad))
                out[name].append((int(e.status), t1, t2))
            c = sj.estimate_classic(f.image, f.rig, f.name, refine=True)
            out["classic + refinement"].append(
                (sj.Status(c.status).code, c.theta1_deg, c.theta2_deg)
            )
            bar.update()
    bar.close()
    return out


def summarise(frames: list, rows: list[tuple[int, float, float]]) -> dict:
    ok = sj.Status.OK.code
    contact = [f.truth.contact for f in frames]
    err: dict[str, list[tuple[float, float]]] = {}
    for f, c, (status, t1, t2) in zip(frames, contact, rows, strict=True):
        if c and status == ok:
            e = (abs(t1 - f.truth.theta1_deg), abs(t2 - f.truth.theta2_deg))
            err.setdefault("all", []).append(e)
            err.setdefault(f.truth.terrain, []).append(e)
    stats = {}
    for key, values in err.items():
        a = np.asarray(values)
        stats[key] = {
            "frames": len(a),
            "median_theta1_deg": float(np.median(a[:, 0])),
            "median_theta2_deg": float(np.median(a[:, 1])),
            "p90_theta1_deg": float(np.percentile(a[:, 0], 90)),
            "p90_theta2_deg": float(np.percentile(a[:, 1], 90)),
        }
    measured = sum(1 for c, r in zip(contact, rows, strict=True) if c and r[0] == ok)
    stats["all"]["measured_pct"] = 100.0 * measured / max(sum(contact), 1)
    return stats


def report(data: dict) -> str:
    lines = [
        "# Entry and exit angles: curved end tangents, ablated",
        "",
        f"Generated by `python experiments/end_tangents.py{data['args']}` in "
        f"{data['seconds']:.0f} s on {data['machine']}: {data['frames']} frames of the full "
        f"mix ({data['recordings']} recordings, sizes {', '.join(data['sizes'])}), seed "
        f"{data['seed']} (the settings were tuned on seeds 777 and 778). Errors over the "
        "frames with true contact measured `ok`. "
        "Targets (issue 14): median |θ| error <= 0.3°, 90th percentile <= 1.0°.",
        "",
        "| end model | frames ok (% of contact) | median |θ1| (deg) | median |θ2| (deg) "
        "| p90 |θ1| (deg) | p90 |θ2| (deg) |",
        "|---|---|---|---|---|---|",
    ]
    for name, stats in data["methods"].items():
        a = stats["all"]
        lines.append(
            f"| {name} | {a['frames']} ({a['measured_pct']:.1f}) | {a['median_theta1_deg']:.2f} "
            f"| {a['median_theta2_deg']:.2f} | {a['p90_theta1_deg']:.2f} "
            f"| {a['p90_theta2_deg']:.2f} |"
        )
    terrains = sorted(k for k in data["methods"]["curved"] if k != "all")
    lines += [
        "",
        "Median |θ1| / |θ2| error (deg) per terrain:",
        "",
        "| end model | " + " | ".join(terrains) + " |",
        "|---" * (len(terrains) + 1) + "|",
    ]
    for name, stats in data["methods"].items():
        cells = [
            f"{stats[t]['median_theta1_deg']:.2f} / {stats[t]['median_theta2_deg']:.2f}"
            if t in stats
            else "—"
            for t in terrains
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seed", type=int, default=2027)
    ap.add_argument("--recordings", type=int, default=10)
    ap.add_argument("--frames-per", type=int, default=8)
    ap.add_argument("--quick", action="store_true", help="4 recordings x 4 frames")
    ap.add_argument("--out", type=Path, default=RESULTS / "end_tangents.md")
    args = ap.parse_args(argv)
    n_rec, per = (4, 4) if args.quick else (args.recordings, args.frames_per)
    t0 = time.perf_counter()
    frames = make_frames(args.seed, n_rec, per)
    measured = measure(frames)
    data = {
        "seed": args.seed,
        "frames": len(frames),
        "recordings": n_rec,
        "sizes": [f"{w}x{h}" for w, h in SIZES],
        "args": "" if argv is None else " " + " ".join(argv),
        "seconds": time.perf_counter() - t0,
        "machine": runs.machine(),
        "methods": {name: summarise(frames, rows) for name, rows in measured.items()},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(data, indent=1))
    args.out.write_text(report(data))
    print(report(data))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
