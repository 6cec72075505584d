"""Frames per second of the synthetic renderer on ONE core (not a unit test).

Usage: python experiments/synth_speed.py [--frames 40] [--preset full] [--width 640 --height 480]

Pins numpy's BLAS and OpenCV to one thread, renders ``--frames`` random scenes (noise, blur and,
for "full" and the hard-lighting presets, JPEG included) and prints frames/s from wall-clock time
and from this process's CPU time (the latter is what to quote on a shared, loaded machine).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import time

import cv2
import numpy as np

from sinkjax.synth import PRESETS, random_scene, render


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--preset", default="full", choices=PRESETS)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    scenes = [
        random_scene(rng, width=args.width, height=args.height, preset=args.preset)
        for _ in range(args.frames)
    ]
    t_scenes = time.perf_counter() - t0
    render(scenes[0], seed=0)  # warm-up (imports, first allocations)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for i, scene in enumerate(scenes):
        render(scene, seed=i)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    n = len(scenes)
    print(
        f"{args.preset} {args.width}x{args.height}: render {n / wall:.1f} frames/s wall, "
        f"{n / cpu:.1f} frames/s CPU ({1000 * cpu / n:.0f} ms/frame); "
        f"random_scene {1000 * t_scenes / n:.1f} ms/scene"
    )


if __name__ == "__main__":
    main()
