"""The calibration loss with the frame's mask made once, against making it twice (issue 12).

Calibration's loss of one labelled frame measures it (which makes the soft wheel mask) and, for a
frame labelled with contact that does not measure, looks at the mask again for a surrogate
gradient. Until this change the loss made that mask a second time (the default segmenter without
the recording's rim) and computed the surrogate's full-image strips on every frame, used or not.
Now ``soft.estimator.measure_and_mask`` hands the loss the mask the frame was measured with, and a
``lax.cond`` skips the strips on frames that measure.

This renders one recording per preset (seed fixed, every third of 18 frames labelled with the
renderer's truth, 640x480), finds the recording's rim as calibration does, and times both
forms of one frame's loss, compiled alike, taking turns (``--rounds``) in one process; the
losses must agree (a coloured wheel's mask does not depend on the rim). Writes
``experiments/results/loss_mask_once.{json,md}``.

    python experiments/loss_mask_once.py                 # hard_dust and hard_mix, seed 20265
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from common import runs

from sinkjax import synth as S
from sinkjax.calibration import LabelledFrames, loss as L
from sinkjax.calibration.compiled import loss_rig
from sinkjax.calibration.optimise import labelled_rim
from sinkjax.soft.adaptive import default_segmenter
from sinkjax.soft.estimator import measure
from sinkjax.synth.recording import frame_seed

RESULTS = Path(__file__).parent / "results"
N_FRAMES = 18


def twice(raw, image, target, *, rect, travel, wheel_radius_mm, rim):  # the loss before
    seg = L.from_raw(raw)
    est = measure(image, seg, rect=rect, travel=travel, wheel_radius_mm=wheel_radius_mm, rim=rim)
    mask = default_segmenter(seg)(image, rect)
    values = jnp.stack([est.sinkage_mm, jnp.degrees(est.theta1_rad), jnp.degrees(est.theta2_rad)])
    ok = est.status == 0
    used = jnp.where(ok & jnp.isfinite(values), values, 0.0)
    measured = jnp.isfinite(target)
    loss = jnp.sum(jnp.where(measured, L.pseudo_huber(used - jnp.where(measured, target, 0.0)), 0))
    contact = measured[0] & (jnp.where(measured[0], target[0], 0.0) > 0)
    deficit = jax.nn.relu(L.BOUNDARY_TARGET - jnp.sum(est.boundary_weight)) / L.BOUNDARY_TARGET
    loss = loss + jnp.where(contact, L.pseudo_huber(deficit), 0.0)
    circle = jax.lax.stop_gradient(est.params[:3])
    usable = contact & ~ok & jnp.all(jnp.isfinite(circle)) & (circle[2] > 1.0)
    safe = jnp.where(usable, circle, jnp.asarray([0.0, 0.0, 2.0], circle.dtype))
    sign = travel
    contrast = L.boundary_contrast(mask, safe, target, sign=sign, wheel_radius_mm=wheel_radius_mm)
    return loss + jnp.where(usable, L.CONTRAST_WEIGHT * contrast, 0.0)


def once(raw, image, target, *, rect, travel, wheel_radius_mm, rim):  # the loss now
    return L.frame_loss(
        raw, image, target, rect=rect, travel=travel, wheel_radius_mm=wheel_radius_mm, rim=rim
    )[0]


def recording(preset: str, seed: int) -> dict:
    rng = np.random.default_rng([seed, 0])
    scenes = S.recording_scenes(rng, N_FRAMES, preset=preset, width=640, height=480)
    rig = S.rig_for(scenes[0])
    rendered = [S.render(s, seed=frame_seed(seed, i)) for i, s in enumerate(scenes)]
    images = np.stack([im for im, _ in rendered])
    truth = np.array([[t.sinkage_mm, t.theta1_deg, t.theta2_deg] for _, t in rendered])
    lab = list(range(0, N_FRAMES, 3))
    frames = LabelledFrames(images[lab], truth[lab], tuple(map(str, lab)), rim_images=images[:8])
    return {"rig": rig, "frames": frames, "rim": labelled_rim(frames, rig, "recording")}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=20265)
    p.add_argument("--presets", default="hard_dust,hard_mix")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    t_start = time.perf_counter()
    rows = []
    for preset in args.presets.split(","):
        rec = recording(preset, args.seed)
        rig, frames = rec["rig"], rec["frames"]
        lr = loss_rig(rig.confidence_rect, rig.travel, rig.wheel_radius_mm)
        kw = dict(rect=lr.rect_px, travel=lr.travel_sign, wheel_radius_mm=lr.wheel_radius_mm)
        raw = L.to_raw(rig.segmentation)
        images = jnp.asarray(frames.images).astype(jnp.result_type(float)) / 255.0
        targets = jnp.asarray(frames.targets)
        fns = {
            name: jax.jit(lambda r, im, t, rim, f=f, kw=kw: f(r, im, t, rim=rim, **kw))
            for name, f in (("twice", twice), ("once", once))
        }
        losses = {
            n: [float(f(raw, im, t, rec["rim"])) for im, t in zip(images, targets, strict=True)]
            for n, f in fns.items()
        }  # fmt: skip (compiles)
        times: dict[str, list[float]] = {n: [] for n in fns}
        for _ in range(args.rounds):
            for n, f in fns.items():
                t0 = time.perf_counter()
                for im, t in zip(images, targets, strict=True):
                    jax.block_until_ready(f(raw, im, t, rec["rim"]))
                times[n].append((time.perf_counter() - t0) / len(images))
        ms = {n: 1000 * float(np.median(v)) for n, v in times.items()}
        diff = np.abs(np.subtract(losses["once"], losses["twice"]))
        rows.append({
            "preset": preset, "ms_twice": ms["twice"], "ms_once": ms["once"],
            "ratio": ms["once"] / ms["twice"], "max_abs_loss_diff": float(np.max(diff)),
        })  # fmt: skip
        runs.log(f"{preset}: {ms['twice']:.0f} ms -> {ms['once']:.0f} ms per frame")
    data = {"seed": args.seed, "rounds": args.rounds, "rows": rows, "machine": runs.machine(),
            "seconds": time.perf_counter() - t_start}  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    runs.write_json(args.out / "loss_mask_once.json", data)
    lines = [
        "# The calibration loss with the frame's mask made once (issue 12)",
        "",
        f"Seed {args.seed}, 6 labelled 640x480 frames per preset, median over {args.rounds} "
        f"rounds taken in turn in one process, on {data['machine']}. Loss of one frame, "
        "measured with the recording's rim, compiled alike.",
        "",
        "| preset | mask made twice [ms/frame] | once [ms/frame] | ratio | max loss difference |",
        "|---|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {r['preset']} | {r['ms_twice']:.0f} | {r['ms_once']:.0f} | {r['ratio']:.2f} | "
        f"{r['max_abs_loss_diff']:.1e} |"
        for r in rows
    ]
    text = "\n".join(lines) + "\n"
    (args.out / "loss_mask_once.md").write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
