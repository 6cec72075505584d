"""Entry and exit angles (issue 14, item 1): the soft method's end tangents, ablated.

θ1 and θ2 come from where the soil surface meets the rim (A, B). The soft method fits each end
with a short curve (the tangent at the end plus a bend, ``sinkjax.soft.model``) over a window of
boundary next to the rim, its points down-weighted with their distance from the end (a biweight
taper, ``SoftSettings.end_taper``). This script prepares every frame once (mask, outline, the
recording's rim, as ``sinkjax estimate`` does) and finishes it with four end models:

- ``curved, tapered, chosen window`` the defaults: each end's window length chosen per frame
  by intersecting confidence intervals (``sinkjax.soft.ends.chosen_window``);
- ``curved, tapered`` the same with the longest window always (the defaults before the chosen
  window);
- ``curved, uniform`` that with every window point weighted alike and the former 2 px
  clearance from the rim (the defaults before the taper);
- ``straight`` the defaults with the bend held at 0 (a straight tangent over the chosen
  window);
- ``former`` the straight tangent with the settings before the curved ends (3.5 px clearance,
  a 0.12 r window of at most 30 px, a strong pull towards the equivalent line's angle, no robust
  loss, no taper), for the record;

and the classic method with sub-pixel refinement (``estimate_classic(refine=True)``) as a
reference. Two frame sets:

- the full mix: full-mix recordings (lugs, holes, shadows, all five terrains, four image
  sizes);
- the paper rig: the paper experiments' camera set-up (28 lugs 15 mm high, a lamp's cast
  shadow) on flat soil bulldozed by slip as in ``paper_precision.py`` (a pile ahead, a rut
  behind whose edge lies inside the exit end's window), 30 N and 90 N, slips 0-0.7.

Reported: median and 90th percentile of |θ1|, |θ2| error and the median signed error over the
frames with true contact, per terrain and overall, and the share of frames measured (``ok``).

The taper and clearance were tuned on full-mix seeds 777 and 778 and paper-rig seed 5; the
default seed (2027, and 2028 for the paper rig) was not looked at before. The chosen window's
rule (two standard errors, the usual choice) was compared with one and three on full-mix seed
777 and paper-rig seed 5 only.

    python experiments/end_tangents.py                   # 10 recordings x 8 frames, seed 2027
    python experiments/end_tangents.py --seed 777 --quick
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from benchmark import Frame, make_frames
from common import paper, runs, scenery
from tqdm import tqdm

import sinkjax as sj
from sinkjax import synth as S
from sinkjax.soft.adaptive import default_segmenter
from sinkjax.soft.batch import SoftRecording, _float
from sinkjax.soft.estimator import finish, prepare, rig_arrays
from sinkjax.soft.settings import SoftSettings

RESULTS = Path(__file__).parent / "results"
VARIANTS: dict[str, dict[str, float]] = {
    "curved, tapered, chosen window": {},
    "curved, tapered": {"end_window_z": math.inf},
    "curved, uniform": {"end_taper": 0.0, "end_clearance_px": 2.0, "end_window_z": math.inf},
    "straight": {"end_bend_prior_points": 1e8},
    "former": {
        "end_bend_prior_points": 1e8,
        "end_clearance_px": 3.5,
        "end_window_fraction": 0.12,
        "end_window_max_px": 30.0,
        "end_angle_prior_points": 2.0,
        "end_loss_scale_px": 1e6,
        "end_taper": 0.0,
        "end_window_z": math.inf,
    },
}


def settings_for(changes: dict[str, float]) -> SoftSettings:
    s = SoftSettings()
    for name, value in changes.items():
        s = eqx.tree_at(lambda t, n=name: getattr(t, n), s, jnp.asarray(value))
    return s


def paper_frames(seed: int, per_cell: int = 3) -> list[Frame]:
    """The paper rig's bulldozed frames (``paper_precision.py``'s scenes): per load (30, 90 N)
    and slip (0-0.7) ``per_cell`` frames with their own wheel phase and feature jitter; one
    recording (the camera set-up is fixed)."""
    setup = runs.Setup(quick=False, out_dir=RESULTS, cache_dir=RESULTS, seed=seed)
    base = scenery.paper_scene(setup)
    rig = S.rig_for(base)
    rng = np.random.default_rng(seed)
    frames: list[Frame] = []
    for load in (30, 90):
        for slip in paper.PAPER_SLIPS:
            depth = paper.sinkage_for(load, slip)
            for _ in range(per_cell):
                jitter = float(rng.uniform(-1, 1))
                scene = scenery.place(
                    base,
                    depth,
                    phase_rad=float(rng.uniform(0, 2 * math.pi)),
                    **scenery.bulldozing(base, depth, slip, jitter=jitter),
                )
                image, truth = S.render(scene, seed=seed * 1000 + len(frames))
                frames.append(Frame(image, truth, rig, 0, f"paper_{load}N_{slip:.1f}_{_}"))
    return frames


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
            e = (t1 - f.truth.theta1_deg, t2 - f.truth.theta2_deg)
            err.setdefault("all", []).append(e)
            err.setdefault(f.truth.terrain, []).append(e)
    stats = {}
    for key, values in err.items():
        signed = np.asarray(values)
        a = np.abs(signed)
        stats[key] = {
            "frames": len(a),
            "bias_theta1_deg": float(np.median(signed[:, 0])),
            "bias_theta2_deg": float(np.median(signed[:, 1])),
            "median_theta1_deg": float(np.median(a[:, 0])),
            "median_theta2_deg": float(np.median(a[:, 1])),
            "p90_theta1_deg": float(np.percentile(a[:, 0], 90)),
            "p90_theta2_deg": float(np.percentile(a[:, 1], 90)),
        }
    measured = sum(1 for c, r in zip(contact, rows, strict=True) if c and r[0] == ok)
    stats["all"]["measured_pct"] = 100.0 * measured / max(sum(contact), 1)
    return stats


def _table(methods: dict) -> list[str]:
    lines = [
        "| end model | frames ok (% of contact) | median |θ1| (deg) | median |θ2| (deg) "
        "| p90 |θ1| (deg) | p90 |θ2| (deg) | median signed θ1 / θ2 (deg) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, stats in methods.items():
        a = stats["all"]
        lines.append(
            f"| {name} | {a['frames']} ({a['measured_pct']:.1f}) | {a['median_theta1_deg']:.2f} "
            f"| {a['median_theta2_deg']:.2f} | {a['p90_theta1_deg']:.2f} "
            f"| {a['p90_theta2_deg']:.2f} "
            f"| {a['bias_theta1_deg']:+.2f} / {a['bias_theta2_deg']:+.2f} |"
        )
    return lines


def report(data: dict) -> str:
    mix, rig = data["mix"], data["paper_rig"]
    lines = [
        "# Entry and exit angles: end tangents, ablated",
        "",
        f"Generated by `python experiments/end_tangents.py{data['args']}` in "
        f"{data['seconds']:.0f} s on {data['machine']}. Errors over the frames with true "
        "contact measured `ok`; signed error = measured - true. The taper and clearance were "
        "tuned on full-mix seeds 777 and 778 and paper-rig seed 5; the chosen window's rule (two "
        "standard errors) was compared with one and three on seeds 777 and 5 only. "
        "Targets (issue 14, full mix): median |θ| error <= 0.3°, 90th percentile <= 1.0°.",
        "",
        f"## Full mix: {mix['frames']} frames ({mix['recordings']} recordings, sizes "
        f"{', '.join(mix['sizes'])}), seed {mix['seed']}",
        "",
        *_table(mix["methods"]),
    ]
    terrains = sorted(k for k in next(iter(mix["methods"].values())) if k != "all")
    lines += [
        "",
        "Median |θ1| / |θ2| error (deg) per terrain:",
        "",
        "| end model | " + " | ".join(terrains) + " |",
        "|---" * (len(terrains) + 1) + "|",
    ]
    for name, stats in mix["methods"].items():
        cells = [
            f"{stats[t]['median_theta1_deg']:.2f} / {stats[t]['median_theta2_deg']:.2f}"
            if t in stats
            else "—"
            for t in terrains
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"## Paper rig, bulldozed: {rig['frames']} frames (30 N and 90 N, slips 0-0.7, "
        f"640x480), seed {rig['seed']}",
        "",
        "A rut's edge lies inside the exit end's window: a uniformly weighted window reads its "
        "slope as the surface's direction at B, and θ2 comes out too small on nearly every "
        "frame. The chosen window stops short of it where the crossings of longer windows "
        "drift by more than their errors. What is left is in the edges themselves: on this "
        "rig's wheel (a rim band 9 px wide, darker than the face) boundary points 6-8 px "
        "inside the rim lie 0.15-0.25 px above the true surface (median, paper-rig seed 5), "
        "where the band's inner edge falls within the sub-pixel edge profile, and the "
        "window's far side tilts the tangent at B by as much.",
        "",
        *_table(rig["methods"]),
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seed", type=int, default=2027, help="full mix (paper rig: seed + 1)")
    ap.add_argument("--recordings", type=int, default=10)
    ap.add_argument("--frames-per", type=int, default=8)
    ap.add_argument("--quick", action="store_true", help="4 recordings x 4 frames; 1 per cell")
    ap.add_argument("--out", type=Path, default=RESULTS / "end_tangents.md")
    args = ap.parse_args(argv)
    n_rec, per = (4, 4) if args.quick else (args.recordings, args.frames_per)
    t0 = time.perf_counter()
    sets = {
        "mix": (args.seed, make_frames(args.seed, n_rec, per)),
        "paper_rig": (args.seed + 1, paper_frames(args.seed + 1, 1 if args.quick else 3)),
    }
    data: dict = {
        "args": "" if argv is None else " " + " ".join(argv),
        "machine": runs.machine(),
    }
    for key, (seed, frames) in sets.items():
        measured = measure(frames)
        data[key] = {
            "seed": seed,
            "frames": len(frames),
            "recordings": len({f.recording for f in frames}),
            "sizes": sorted({f"{f.image.shape[1]}x{f.image.shape[0]}" for f in frames}),
            "methods": {name: summarise(frames, rows) for name, rows in measured.items()},
        }
    data["seconds"] = time.perf_counter() - t0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(data, indent=1))
    args.out.write_text(report(data))
    print(report(data))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
