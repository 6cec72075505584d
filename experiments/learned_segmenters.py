"""Learned segmenters vs thresholds on the hard presets (issue 16, items 3-6).

For every hard preset (``sinkjax.synth.hard``: dust, cast, shading, low light, a mix) render
``--seen`` recordings whose first ``--labelled`` frames are labelled (z0, theta1, theta2 from the
exact truth; no masks) and whose next ``--test`` frames are held out, and ``--unseen``
recordings never trained on. Methods, each measured on the held-out frames by
``estimate_batch`` (the ``sinkjax estimate`` path):

- thresholds (default): the rig as rendered;
- thresholds calibrated per recording: ``sinkjax.calibrate`` on that recording's labelled frames
  (unseen recordings have no labels, so they keep the default);
- ColourMLP and ConvSegmenter: ONE model each, trained on the labelled frames of all seen
  recordings (a third of them held back to stop early on). Each is residual (the default
  segmenter's log-odds plus the network's correction, which starts at zero; ``--scratch``: the
  network alone, first fitted by pixel cross-entropy to the renderer's exact wheel masks of
  those labelled frames, ``sinkjax.learn.imitate``; ``--imitate-masks`` does that for the
  residual models too), trained through the fit on the frame labels alone, as ``sinkjax train``
  does (``sinkjax.learn.train``; ``--pixel-weight`` adds the exact masks' cross-entropy).

Also: training time, and inference time per 640x480 frame (the whole soft method, steady state)
with each segmenter relative to the thresholds. Developed on seed 7 (``--quick``); the committed
results use seed 20262.

    .venv/bin/python experiments/learned_segmenters.py [--quick] [--seed S]

Writes experiments/results/learned_segmenters.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from sinkjax import metrics as sm
from sinkjax.calibration import calibrate
from sinkjax.learn import (
    LabelledRecording,
    build,
    frame_batches,
    imitate,
    split,
    synthetic_recording,
    train,
)
from sinkjax.soft.batch import estimate_batch
from sinkjax.synth.hard import HARD_PRESETS

RESULTS = Path(__file__).parent / "results"
METHODS = ("thresholds", "calibrated", "mlp", "cnn")


def recordings(seed: int, n: int, frames: int, width: int, height: int, tag: int) -> list:
    return [
        synthetic_recording(
            frames,
            seed=seed * 1000 + tag * 100 + 10 * k + r,
            preset=preset,
            width=width,
            height=height,
        )
        for k, preset in enumerate(HARD_PRESETS)
        for r in range(n)
    ]


def measure(rec: LabelledRecording, segmenter=None, rig=None) -> dict:
    """Relative sinkage errors (contact frames) and statuses of ``rec``'s frames."""
    rows = estimate_batch(
        list(rec.frames.images),
        rig or rec.rig,
        list(rec.frames.names),
        segmenter=segmenter,
    )
    status = [str(r.status) for r in rows]
    est = [r.sinkage_mm for r in rows]
    truth = rec.frames.targets[:, 0]
    rel = sm.relative_error_pct(truth, est, status)
    return {"rel": [float(v) for v in rel[truth > 0]], "status": status}


def summarise(per_rec: dict[str, dict]) -> dict:
    rel = [v for r in per_rec.values() for v in r["rel"]]
    status = [s for r in per_rec.values() for s in r["status"]]
    return {
        "median_rel_sinkage_pct": sm.median(rel),
        "failed_pct": sm.failed_pct(status),
        # A recording whose every frame failed has no median: it counts as the worst (inf).
        "worst_recording_median_pct": max(
            sm.median(r["rel"]) if sm.count(r["rel"]) else float("inf") for r in per_rec.values()
        ),
        "frames": len(status),
    }


def time_per_frame(segmenter, repeats: int) -> float:
    """Steady-state seconds per 640x480 frame of the whole soft method."""
    rec = synthetic_recording(1, seed=99, preset="hard_mix", width=640, height=480)
    measure(rec, segmenter)  # compile
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        measure(rec, segmenter)
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=20262)
    ap.add_argument("--quick", action="store_true", help="development run: seed 7, fewer frames")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--seen", type=int, default=1, help="trained-on recordings per preset")
    ap.add_argument("--unseen", type=int, default=1, help="never-trained recordings per preset")
    ap.add_argument("--labelled", type=int, default=6)
    ap.add_argument("--test", type=int, default=6)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--calibration-steps", type=int, default=20)
    ap.add_argument(
        "--scratch",
        action="store_true",
        help="networks on their own, started by imitating the exact masks (default: residual "
        "models that correct the default segmenter, started where it is)",
    )
    ap.add_argument(
        "--imitate-masks",
        action="store_true",
        help="fit the residual models to the exact masks before training (--scratch always "
        "does; default: start where the default segmenter is, as sinkjax train does)",
    )
    ap.add_argument(
        "--pixel-weight",
        type=float,
        default=0.0,
        help="weight of the exact-mask cross-entropy in training (default 0: frame labels only)",
    )
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    args = ap.parse_args()
    if args.quick:
        args.seed, args.test, args.steps, args.calibration_steps = 7, 3, 10, 6
    cfg = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    t0 = time.perf_counter()
    n = args.labelled + args.test
    seen = recordings(args.seed, args.seen, n, args.width, args.height, tag=1)
    unseen = recordings(args.seed, args.unseen, args.test, args.width, args.height, tag=2)
    labelled = [r.subset(range(args.labelled)) for r in seen]
    held = [r.subset(range(args.labelled, n)) for r in seen]

    results: dict[str, dict[str, dict]] = {m: {} for m in METHODS}
    for lab, test in zip(labelled, held, strict=True):
        results["thresholds"][test.name] = measure(test)
        cal = calibrate(lab.frames, lab.rig, steps=args.calibration_steps)
        results["calibrated"][test.name] = measure(test, rig=cal.rig)
        print(f"{test.name}: thresholds and calibrated done", flush=True)
    for rec in unseen:
        results["thresholds"][rec.name] = results["calibrated"][rec.name] = measure(rec)

    fit, stop = split(labelled, 1 / 3, seed=args.seed)
    training: dict[str, dict] = {}
    models = {}
    for kind in ("mlp", "cnn"):
        t = time.perf_counter()
        batches = frame_batches(fit)
        seg = build(kind, key=args.seed, residual=int(not args.scratch))
        if args.scratch or args.imitate_masks:
            seg, _ = imitate(seg, batches, steps=150)
        res = train(
            seg,
            batches,
            frame_batches(stop),
            steps=args.steps,
            batch_size=6,
            eval_every=5,
            patience=3,
            pixel_weight=args.pixel_weight,
            seed=args.seed,
            progress=True,
        )
        models[kind] = res.segmenter
        training[kind] = res.report() | {"seconds_with_imitation": time.perf_counter() - t}
        print(res.summary(), flush=True)
        for rec in held + unseen:
            results[kind][rec.name] = measure(rec, res.segmenter)

    seen_names = {r.name for r in held}
    table = {}
    for m in METHODS:
        table[m] = {
            "seen_held_out": summarise({k: v for k, v in results[m].items() if k in seen_names}),
            "unseen": summarise({k: v for k, v in results[m].items() if k not in seen_names}),
            "per_recording_median_pct": {k: sm.median(v["rel"]) for k, v in results[m].items()},
            "per_recording_failed": {
                k: int(sm.failed(v["status"]).sum()) for k, v in results[m].items()
            },
        }
    base = time_per_frame(None, 5)
    cost = {"thresholds_s": base}
    for kind, seg in models.items():
        cost[f"{kind}_s"] = time_per_frame(seg, 5)
        cost[f"{kind}_relative"] = cost[f"{kind}_s"] / base
    out = {
        "config": cfg,
        "table": table,
        "training": training,
        "inference_640x480": cost,
        "seconds": time.perf_counter() - t0,
    }
    args.out_dir.mkdir(parents=True, exist_ok=True)
    stem = "learned_segmenters" + "".join(
        f"_{name}"
        for name, on in (
            ("quick", args.quick),
            ("scratch", args.scratch),
            ("masks", args.imitate_masks and not args.scratch),
        )
        if on
    )
    (args.out_dir / f"{stem}.json").write_text(json.dumps(out, indent=1, default=float))
    (args.out_dir / f"{stem}.md").write_text(report(out))
    print(report(out))


def _start(c: dict) -> str:
    if c.get("scratch"):
        return "networks alone, first fitted to the exact masks"
    if c.get("imitate_masks"):
        return "residual (default segmenter + correction), first fitted to the exact masks"
    return "residual (default segmenter + correction), started where the default is"


def _pixel(c: dict) -> str:
    w = c.get("pixel_weight", 0.0)
    return f" plus {w} x the exact masks' cross-entropy" if w else ""


def report(out: dict) -> str:
    c, t = out["config"], out["table"]
    lines = [
        "# Learned segmenters vs thresholds on the hard presets",
        "",
        f"Seed {c['seed']}; {c['width']}x{c['height']}; {len(HARD_PRESETS)} hard presets x "
        f"{c['seen']} seen recording(s) ({c['labelled']} labelled + {c['test']} held-out frames) "
        f"and x {c['unseen']} unseen recording(s) ({c['test']} frames). One MLP and one CNN for "
        f"all recordings, {_start(c)}, {c['steps']} Adam steps at most on the frame labels"
        f"{_pixel(c)}. Errors: median relative sinkage error "
        f"of contact frames; {sm.RULE}.",
        "",
        "| method | seen, held-out: median % | failed % | worst recording % | unseen: median % "
        "| failed % | worst recording % |",
        "|---|---|---|---|---|---|---|",
    ]
    for m in METHODS:
        s, u = t[m]["seen_held_out"], t[m]["unseen"]
        lines.append(
            f"| {m} | {s['median_rel_sinkage_pct']:.2f} | {s['failed_pct']:.1f} | "
            f"{s['worst_recording_median_pct']:.2f} | {u['median_rel_sinkage_pct']:.2f} | "
            f"{u['failed_pct']:.1f} | {u['worst_recording_median_pct']:.2f} |"
        )
    cost = out["inference_640x480"]
    lines += [
        "",
        "Unseen recordings have no labels: their `calibrated` row is the default thresholds.",
        "",
        f"Training (s, imitation included): "
        f"mlp {out['training']['mlp']['seconds_with_imitation']:.0f}, "
        f"cnn {out['training']['cnn']['seconds_with_imitation']:.0f}. Inference per 640x480 frame "
        f"(whole soft method, steady state, CPU shared with other jobs): thresholds "
        f"{1000 * cost['thresholds_s']:.0f} ms, mlp {1000 * cost['mlp_s']:.0f} ms "
        f"({cost['mlp_relative']:.2f}x), cnn {1000 * cost['cnn_s']:.0f} ms "
        f"({cost['cnn_relative']:.2f}x); target <= 1.5x.",
        "",
        "Per recording: median relative sinkage error % (failed frames):",
        "",
        "| recording | " + " | ".join(METHODS) + " |",
        "|---|" + "---|" * len(METHODS),
    ]
    for name in t["thresholds"]["per_recording_median_pct"]:
        cells = " | ".join(
            f"{t[m]['per_recording_median_pct'][name]:.2f} ({t[m]['per_recording_failed'][name]})"
            for m in METHODS
        )
        lines.append(f"| {name} | {cells} |")
    lines += ["", f"Run time {out['seconds']:.0f} s.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
