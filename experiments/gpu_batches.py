"""On a GPU: the same four frames measured at several batch sizes, twice each (issue 13).

The four distinct 640x480 frames of ``make bench`` (``experiments/bench.py``) are measured as one
recording, padded to each batch size (by repeating the first frame), twice in one process: their
statuses, messages, z0 and rims, to compare batch sizes, runs and devices (a CPU run measures
them frame by frame). With ``--speed`` also the compiled method's frames/s at each batch size
(``bench._device_rates``). Run it again under ``XLA_FLAGS=--xla_gpu_deterministic_ops=true`` to
see what XLA's deterministic GPU kernels change.

    python experiments/gpu_batches.py --batches 32,8 --out status.json
    python experiments/gpu_batches.py --batches 256,512 --speed --out speed.json
    XLA_FLAGS=--xla_gpu_deterministic_ops=true python experiments/gpu_batches.py --batches 32

``experiments/results/gpu_batches.json`` holds the three runs above, made on one NVIDIA H200.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import bench

from sinkjax import synth as S
from sinkjax.soft.batch import SoftRecording


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batches", default="32,8", help="comma-separated batch sizes")
    parser.add_argument("--speed", action="store_true", help="also time the compiled method")
    parser.add_argument("--out", default="gpu_batches.json")
    args = parser.parse_args(argv)
    if args.speed and not bench._on_accelerator():
        parser.error(
            "--speed times batched calls, which run on an accelerator only (JAX's "
            "default backend here is the CPU)"
        )
    rng = np.random.default_rng(0)  # the frames of bench.py
    scenes = S.recording_scenes(rng, bench.N_DISTINCT, width=640, height=480)
    rig = S.rig_for(scenes[0])
    rendered = [S.render(scene, seed=i) for i, scene in enumerate(scenes)]
    images = [image for image, _ in rendered]
    names = [f"f{i}" for i in range(len(images))]
    out: dict = {
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "machine": bench._machine(),
        "true_z0_mm": [truth.sinkage_mm for _, truth in rendered],
        "rows": [],
    }
    for batch in (int(b) for b in args.batches.split(",")):
        for rep in range(2):
            started = time.perf_counter()
            rows = SoftRecording()(images, rig, names, pad_to=batch)
            row = {
                "batch": batch,
                "rep": rep,
                "seconds": time.perf_counter() - started,
                "status": [str(r.status) for r in rows],
                "z0": [r.sinkage_mm for r in rows],
                "msg": [r.message for r in rows],
                "rim": [(r.center_x_px, r.center_y_px, r.radius_px) for r in rows],
            }
            out["rows"].append(row)
            print(json.dumps(row), flush=True)
        if args.speed:
            stack = [images[i % len(images)] for i in range(batch)]
            rates = {"batch": batch, **bench._device_rates(stack, rig)}
            out["rows"].append(rates)
            print(json.dumps(rates), flush=True)
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
