"""Wheels without hue (issue 16, item 2): the default segmenter on black and bare-metal wheels.

Renders seeded recordings of the ``synth.materials`` presets (black and metal wheels, lugs, cast
shadows, grey and brown soils), runs the soft method with :class:`AdaptiveSegmenter` at its
default settings and the classic method, and checks on coloured presets that the adaptive
segmenter gives the same numbers as the paper's H/S mask (to float rounding; frames it blurs
for noise first, ``soft.denoise``, are counted apart). Each recording
is measured as ``sinkjax estimate`` does: one ``SoftRecording``, its rim from its first
frames. Writes
``experiments/results/black_wheels.json`` and ``black_wheels.md``.

Developed on seeds 7 and 5; the reported run uses seed 8, and 9 and 10 are further seeds not
tuned on. A black wheel's shading-corrected threshold (``soft.dark_face``) was developed on seeds
16-18 (``--seed 16``) and is reported on 8, 9 and the never-seen 20-23. A metal wheel's highest
clear valley inside the rim and texture test beyond it were developed on seeds 12 and 16-20 and
are reported on 8, 9, 21-23 and the never-seen 24 and 25. The chromaticity test for metal
wheels and the pooled texture beyond the rim (``soft.grey_features``) were developed on seeds 24,
36, 37, 8, 9 and 20 and are reported on all eighteen (8, 9, 20-25, 30-39) and the never-seen 40+.
A black wheel's tighter chroma floor (its shadow on grey soil, tinted by the sky) was developed on
seeds 8, 20, 30, 31 and 38 and is reported on all twenty (8, 9, 20-25, 30-41) and the never-seen
42 and 43.

    python experiments/black_wheels.py                 # 4 presets x 3 recordings x 8 frames
    python experiments/black_wheels.py --quick         # 4 presets x 1 recording x 3 frames
    python experiments/black_wheels.py --seed 9        # another unseen seed: ..._seed9.md
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sinkjax import Status, metrics as sm, synth as S
from sinkjax.classic.estimator import estimate_classic
from sinkjax.soft.adaptive import AdaptiveSegmenter
from sinkjax.soft.batch import SoftRecording
from sinkjax.soft.denoise import applied_blur_px
from sinkjax.soft.estimator import rig_arrays
from sinkjax.soft.segmenter import FEATURE_CHOICES, Segmenter, ThresholdSegmenter
from sinkjax.synth.materials import MATERIAL_PRESETS

RESULTS = Path(__file__).parent / "results"
EVAL_SEED = 8
COLOURED = ("full", "hard_shading", "hard_mix")


@jax.jit
def _features(image_u8: jax.Array, rect: jax.Array) -> jax.Array:
    """Which features the default segmenter reads this frame with (soft.segmenter codes)."""
    return AdaptiveSegmenter().features(image_u8.astype(jnp.float32) / 255.0, rect)


def _measure(images: list[np.ndarray], rig, segmenter: Segmenter | None = None) -> list:
    """One recording, as ``sinkjax estimate`` measures it (its rim from its first frames)."""
    names = [f"{i}" for i in range(len(images))]
    return SoftRecording(segmenter=segmenter)(images, rig, names)


def _row(preset: str, rec: int, i: int, truth: S.Truth, soft, feats, classic) -> dict:
    return {
        "preset": preset,
        "recording": rec,
        "frame": i,
        "truth_mm": truth.sinkage_mm,
        "contact": bool(truth.contact),
        "soft_status": str(soft.status),
        "soft_mm": soft.sinkage_mm,
        "soft_std_mm": soft.sinkage_std_mm,
        "features": FEATURE_CHOICES.get(int(feats), "none"),
        "classic_status": str(classic.status),
        "classic_mm": classic.sinkage_mm,
        "classic_message": classic.message,
    }


def run(seed: int, n_rec: int, n_frames: int, width: int, height: int) -> list[dict]:
    rows = []
    for preset in MATERIAL_PRESETS:
        for rec in range(n_rec):
            rng = np.random.default_rng(seed * 1000 + rec)
            scenes = S.recording_scenes(rng, n_frames, preset=preset, width=width, height=height)
            rig = S.rig_for(scenes[0])
            rect = jnp.asarray(rig_arrays(rig).rect_px)
            rendered = [S.render(sc, seed * 100_000 + rec * 100 + i) for i, sc in enumerate(scenes)]
            soft = _measure([img for img, _ in rendered], rig)
            for i, ((img, truth), est) in enumerate(zip(rendered, soft, strict=True)):
                feats = _features(jnp.asarray(img), rect)
                classic = estimate_classic(img, rig, f"{i}")
                rows.append(_row(preset, rec, i, truth, est, feats, classic))
    return rows


def coloured_identical(seed: int, n: int, width: int, height: int) -> dict[str, object]:
    """Coloured presets: the default (adaptive) segmenter's rows equal the H/S mask's, to float
    rounding (the same computation in a lax.cond), except on frames it blurs first because
    their noise drowns a dim wheel's hue (soft.denoise), counted apart."""
    checked, same, chose_hue, worst, blurred, worst_blurred = 0, 0, 0, 0.0, 0, 0.0
    for preset in COLOURED:
        rng = np.random.default_rng(seed)
        scenes = S.recording_scenes(rng, n, preset=preset, width=width, height=height)
        rig = S.rig_for(scenes[0])
        rect = jnp.asarray(rig_arrays(rig).rect_px)
        images = [S.render(sc, seed * 100 + i)[0] for i, sc in enumerate(scenes)]
        a = _measure(images, rig, ThresholdSegmenter(rig.segmentation))
        b = _measure(images, rig)
        for img, x, y in zip(images, a, b, strict=True):
            vx = np.array([x.sinkage_mm, x.theta1_deg, x.theta2_deg], dtype=float)
            vy = np.array([y.sinkage_mm, y.theta1_deg, y.theta2_deg], dtype=float)
            diff = float(np.nanmax(np.abs(vx - vy), initial=0.0))
            if float(applied_blur_px(jnp.asarray(img, jnp.float32) / 255.0, rect)) > 0.0:
                blurred += 1
                worst_blurred = max(worst_blurred, diff)
                continue
            equal = x.status == y.status and np.allclose(
                vx, vy, rtol=1e-5, atol=1e-3, equal_nan=True
            )
            checked += 1
            same += int(equal)
            if x.status == y.status:
                worst = max(worst, diff)
            chose_hue += int(int(_features(jnp.asarray(img), rect)) == 0)
    return {
        "frames": checked,
        "bit_identical": same,
        "hue_saturation_chosen": chose_hue,
        "largest_difference": worst,
        "blurred": blurred,
        "largest_difference_blurred": worst_blurred,
    }


def summarise(rows: list[dict]) -> dict[str, dict[str, float]]:
    out = {}
    for method in ("soft", "classic"):
        for preset in (*MATERIAL_PRESETS, "all"):
            sel = [r for r in rows if preset in ("all", r["preset"]) and r["contact"]]
            truth = np.array([r["truth_mm"] for r in sel])
            est = [r[f"{method}_mm"] for r in sel]
            status = [r[f"{method}_status"] for r in sel]
            std = [r.get("soft_std_mm") if method == "soft" else None for r in sel]
            out[f"{method}/{preset}"] = {
                "frames": len(sel),
                "median_rel_err_pct": sm.median(sm.relative_error_pct(truth, est, status)),
                "failed_pct": sm.failed_pct(status),
                "ok_pct": 100.0 * float(np.mean([s == Status.OK.value for s in status])),
                # Reported as a measurement (ok, or no_contact = 0 mm) yet more than 10 % off
                # and outside its own ±1.96σ: confidently wrong.
                "confidently_wrong": int(
                    sum(
                        s in (Status.OK.value, Status.NO_CONTACT.value)
                        and e is not None
                        and abs(e - t) > max(0.1 * t, 1.96 * (sd or 0.0))
                        for s, e, t, sd in zip(status, est, truth, std, strict=True)
                    )
                ),
                "coverage_pct": sm.coverage_pct(truth, est, std, status)
                if method == "soft"
                else float("nan"),
            }
    return out


def markdown(summary: dict, coloured: dict, args: argparse.Namespace, secs: float) -> str:
    lines = [
        "# Black and bare-metal wheels: the default segmenter (issue 16, item 2)",
        "",
        f"Seed {args.seed}, {args.recordings} recordings x {args.frames} frames per preset, "
        f"{args.width}x{args.height}, default settings; contact frames only; {sm.RULE}; "
        f"{sm.RULE_COVERAGE}. Run time {secs:.0f} s.",
        "",
        "| method/preset | frames | median rel. sinkage error % | failed % | ok % | "
        "±1.96σ coverage % | confidently wrong |",
        "|---|---|---|---|---|---|---|",
    ]
    for k, v in summary.items():
        lines.append(
            f"| {k} | {v['frames']} | {v['median_rel_err_pct']:.1f} | {v['failed_pct']:.1f} | "
            f"{v['ok_pct']:.1f} | {v['coverage_pct']:.1f} | {v['confidently_wrong']} |"
        )
    lines += [
        "",
        "Confidently wrong: reported `ok` (or `no_contact`, read as 0 mm) on a contact frame, "
        "more than 10 % off the true sinkage and outside its own ±1.96σ.",
        "",
        f"Coloured presets {COLOURED}: {coloured['bit_identical']} of {coloured['frames']} "
        f"frames equal to the H/S mask's (float32 rounding: within 1e-3 mm and deg; the largest "
        f"difference of any frame {coloured['largest_difference']:.4f} mm or deg, the same "
        "status); hue+saturation chosen on "
        f"{coloured['hue_saturation_chosen']}. Besides those, "
        f"{coloured.get('blurred', 0)} frames blurred first because their noise drowns the "
        "wheel's hue (`soft.denoise`, so not the H/S mask's numbers; largest difference "
        f"{coloured.get('largest_difference_blurred', 0.0):.2f} mm or deg).",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=EVAL_SEED)
    ap.add_argument("--recordings", type=int, default=3)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument(
        "--out", type=Path, default=RESULTS, help="folder for black_wheels[_seedN].json and .md"
    )
    args = ap.parse_args()
    if args.quick:
        args.recordings, args.frames = 1, 3
    t0 = time.perf_counter()
    rows = run(args.seed, args.recordings, args.frames, args.width, args.height)
    coloured = coloured_identical(args.seed, 3, args.width, args.height)
    summary = summarise(rows)
    secs = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "black_wheels" if args.seed == EVAL_SEED else f"black_wheels_seed{args.seed}"
    settings = {**vars(args), "out": str(args.out)}
    payload = {"args": settings, "summary": summary, "coloured": coloured, "rows": rows}
    (args.out / f"{stem}.json").write_text(json.dumps(payload, indent=1, default=float))
    md = markdown(summary, coloured, args, secs)
    (args.out / f"{stem}.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
