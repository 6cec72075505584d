"""Frames one after another (``lax.map``) against one vmapped batch, for calibration on a CPU.

``sinkjax.xla.map_frames`` takes a stack of labelled frames through the calibration loss (and
the learned segmenters' training loss) one frame after another on a CPU and as one vmapped
batch on an accelerator. This measures what that choice buys on this machine: for each mode a
fresh Python process (the two take turns, ``--rounds`` times) renders one recording of the
given preset (seed fixed, not timed), writes its truth as LABELS.csv, then times lowering,
compiling and running :func:`sinkjax.calibration.loss_value` and
:func:`sinkjax.calibration.loss_and_grad` on all its frames, keeps their outputs (which must
agree between the modes to float rounding), and times a whole ``calibrate()`` of the frames
(``--steps`` Adam steps after the grid; compiles included, as a user's first calibration of
an image size). Writes ``experiments/results/frame_map.{json,md}``.

    python experiments/frame_map.py                  # 640x480, 6 frames, 2 rounds
    python experiments/frame_map.py --quick          # 320x240, 3 frames, 1 round
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results"
MODES = ("vmap", "map")


def child(mode: str, width: int, height: int, n: int, seed: int, preset: str, steps: int) -> dict:
    """One process's measurements; ``mode`` vmap forces the accelerators' batch on the CPU."""
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import sinkjax.calibration as C
    from sinkjax import xla
    from sinkjax.rig import load_rig
    from sinkjax.synth import write_recording

    if mode == "vmap":
        xla.frames_in_lockstep = lambda: True  # type: ignore[assignment]
    with tempfile.TemporaryDirectory() as tmp:
        out = write_recording(
            Path(tmp) / "rec", n_frames=n, seed=seed, preset=preset, width=width, height=height,
            progress=False,
        )  # fmt: skip
        rows = list(csv.DictReader((out / "truth.csv").open(encoding="utf-8")))
        with (out / "LABELS.csv").open("w", encoding="utf-8", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(C.LABEL_COLUMNS)
            writer.writerows([[r[c] for c in C.LABEL_COLUMNS] for r in rows])
        rig = load_rig(out / "rig.toml")
        frames = C.read_labels(out / "LABELS.csv", rig)
    images, targets = jnp.asarray(frames.images), jnp.asarray(frames.targets)
    numbers = dict(
        rect=rig.confidence_rect, travel=rig.travel, wheel_radius_mm=float(rig.wheel_radius_mm),
        encoding=rig.encoding,
    )  # fmt: skip
    raw = C.to_raw(rig.segmentation)
    key = jax.random.key(0)
    result: dict = {"mode": mode, "frames": int(images.shape[0])}
    with C.compiled.solve_failures_as_nan():
        calls = {
            "loss": (C.compiled._loss_value, (raw, images, targets, None)),
            "gradient": (C.compiled._loss_and_grad, (raw, images, targets, key, None)),
        }
        rig_arrays = C.compiled.loss_rig(
            numbers["rect"], numbers["travel"], numbers["wheel_radius_mm"], images.shape,
            numbers["encoding"],
        )  # fmt: skip
        for name, (fn, args) in calls.items():
            full = (*args, rig_arrays) + ((False, C.DEFAULT_CONFIG) if name == "gradient" else ())
            t0 = time.perf_counter()
            lowered = fn.lower(*full)
            t1 = time.perf_counter()
            compiled = lowered.compile()
            t2 = time.perf_counter()
            full = full[:6]  # the compiled gradient takes its static arguments no more
            out_ = jax.block_until_ready(compiled(*full))
            times = []
            for _ in range(5):
                t = time.perf_counter()
                jax.block_until_ready(compiled(*full))
                times.append(time.perf_counter() - t)
            result[name] = {
                "lower_s": t1 - t0,
                "compile_s": t2 - t1,
                "run_s": float(np.median(times)),
                "loss": float(out_.loss),
                "grad": [float(g) for g in out_.grad],
                "values": np.asarray(out_.frames.values).tolist(),
            }
    t0 = time.perf_counter()
    res = C.calibrate(frames, rig, steps=steps)
    result["calibrate"] = {
        "seconds": time.perf_counter() - t0,
        "loss_before": res.loss_before,
        "loss_after": res.after_loss,
        "thresholds": res.rig.segmentation.as_dict(),
    }
    return result


def run_child(mode: str, a: argparse.Namespace) -> dict:
    cmd = [sys.executable, __file__, "--child", mode, "--size", a.size, "--frames", str(a.frames)]
    cmd += ["--seed", str(a.seed), "--preset", a.preset, "--steps", str(a.steps)]
    env = {**os.environ, "SINKJAX_CACHE_DIR": "off"}
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr[-3000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])


def report(res: dict) -> str:
    med = res["medians"]
    lines = [
        "# Calibration on a CPU: frames one after another or vmapped (`sinkjax.xla.map_frames`)",
        "",
        f"Generated by `python experiments/frame_map.py{' --quick' if res['quick'] else ''}` on "
        f"{res['machine']}: one '{res['preset']}' recording of {res['frames']} frames at "
        f"{res['size']} (seed {res['seed']}), its truth as labels, float64, XLA's default threads; "
        f"a fresh process per mode, the modes taking turns, {res['rounds']} round(s), medians. "
        "`vmap` is what calibration did before (and still does on an accelerator); `map` is "
        "lax.map, frame by frame, what it does on a CPU now.",
        "",
        "| mode | loss lower [s] | loss compile [s] | loss run [s] | gradient lower [s] | "
        "gradient compile [s] | gradient run [s] | calibrate, cold [s] |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for mode in MODES:
        m = med[mode]
        lines.append(
            f"| {mode} | {m['loss_lower_s']:.2f} | {m['loss_compile_s']:.2f} | "
            f"{m['loss_run_s']:.3f} | {m['gradient_lower_s']:.2f} | "
            f"{m['gradient_compile_s']:.2f} | {m['gradient_run_s']:.3f} | "
            f"{m['calibrate_s']:.1f} |"
        )
    r = res["ratios"]
    lines += [
        "",
        f"map / vmap: loss run **{r['loss_run']:.2f}x**, "
        f"gradient run **{r['gradient_run']:.2f}x**, "
        f"compile (loss + gradient, lower included) {r['compile']:.2f}x, a whole first "
        f"calibration ({res['steps']} steps after the grid) **{r['calibrate']:.2f}x**.",
        "",
        f"Numbers: largest difference between the modes in the loss {res['diff']['loss']:.1e}, "
        f"in the gradient {res['diff']['grad']:.1e}, in the frames' values "
        f"{res['diff']['values']:.1e}; in the calibrated thresholds "
        f"{res['diff']['thresholds']:.1e}.",
        "",
        "Why: under vmap the fit's Levenberg-Marquardt loops of all frames run in lockstep "
        "until the slowest frame converges, and every branch runs both sides; one frame after "
        "another, each loop stops when its own frame converges. An accelerator wants the whole "
        "batch, so there the frames stay vmapped.",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--size", default=None, help="WxH (640x480; --quick 320x240)")
    ap.add_argument("--frames", type=int, default=None, help="labelled frames (6; --quick 3)")
    ap.add_argument("--seed", type=int, default=31)
    ap.add_argument("--preset", default="hard_dust")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=None, help="(2; --quick 1)")
    ap.add_argument("--child", choices=MODES, help=argparse.SUPPRESS)
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    a = ap.parse_args()
    a.size = a.size or ("320x240" if a.quick else "640x480")
    a.frames = a.frames or (3 if a.quick else 6)
    rounds = a.rounds or (1 if a.quick else 2)
    if a.child:
        w, h = (int(v) for v in a.size.split("x"))
        print(json.dumps(child(a.child, w, h, a.frames, a.seed, a.preset, a.steps)))
        return
    t0 = time.perf_counter()
    runs: dict[str, list[dict]] = {m: [] for m in MODES}
    for _ in range(rounds):
        for mode in MODES:
            r = run_child(mode, a)
            runs[mode].append(r)
            print(f"{mode}: gradient run {r['gradient']['run_s']:.3f} s, calibrate "
                  f"{r['calibrate']['seconds']:.1f} s", flush=True)  # fmt: skip
    med: dict = {}
    for mode, rs in runs.items():
        med[mode] = {
            f"{part}_{key}": float(np.median([r[part][key] for r in rs]))
            for part in ("loss", "gradient")
            for key in ("lower_s", "compile_s", "run_s")
        }
        med[mode]["calibrate_s"] = float(np.median([r["calibrate"]["seconds"] for r in rs]))
    v, m = med["vmap"], med["map"]
    compile_keys = ("loss_lower_s", "loss_compile_s", "gradient_lower_s", "gradient_compile_s")
    rv, rm = runs["vmap"][0], runs["map"][0]
    tv, tm = rv["calibrate"]["thresholds"], rm["calibrate"]["thresholds"]
    res = {
        "quick": a.quick, "seed": a.seed, "preset": a.preset, "size": a.size,
        "frames": rv["frames"], "steps": a.steps, "rounds": rounds,
        "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores visible, Python "
        f"{platform.python_version()}", "runs": runs, "medians": med,
        "ratios": {
            "loss_run": m["loss_run_s"] / v["loss_run_s"],
            "gradient_run": m["gradient_run_s"] / v["gradient_run_s"],
            "compile": sum(m[k] for k in compile_keys) / sum(v[k] for k in compile_keys),
            "calibrate": m["calibrate_s"] / v["calibrate_s"],
        },
        "diff": {
            "loss": abs(rv["gradient"]["loss"] - rm["gradient"]["loss"]),
            "grad": float(np.max(np.abs(np.subtract(rv["gradient"]["grad"],
                                                    rm["gradient"]["grad"])))),
            "values": float(np.nanmax(np.abs(np.subtract(rv["loss"]["values"],
                                                         rm["loss"]["values"])))),
            "thresholds": max(abs(float(tv[k]) - float(tm[k])) for k in tv),
        },
        "seconds": time.perf_counter() - t0,
    }  # fmt: skip
    a.out_dir.mkdir(parents=True, exist_ok=True)
    stem = "frame_map_quick" if a.quick else "frame_map"
    (a.out_dir / f"{stem}.json").write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")
    (a.out_dir / f"{stem}.md").write_text(report(res), encoding="utf-8")
    print(report(res))


if __name__ == "__main__":
    main()
