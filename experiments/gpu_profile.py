"""On a GPU: where a batch of frames spends its time (issue 13, items 4 and 5).

The four distinct 640x480 frames of ``make bench`` (``experiments/bench.py``), padded to one
batch, the recording's rim found first as the pipeline does. Three measurements, in one process:

1. The two compiled halves (mask stage ``prepare``, fit stage ``finish``) on the batch already on
   the device, timed apart (median of ``--repeats``), and together as frames/s.
2. Each stage of ``common.stages`` compiled alone under ``jax.vmap`` on the batch (one frame
   repeated), ms per batch.
3. A profiler trace of one prepare + finish (``jax.profiler``, CUPTI): the GPU kernels' time
   summed by compiled function and kernel, the top rows kept.

    python experiments/gpu_profile.py --batch 128 --out gpu_profile.json
    python experiments/gpu_profile.py --report before.json after.json --md gpu_profile.md

``experiments/results/gpu_profile.md`` compares the runs before and after the Hough and
histogram scatters stopped queueing on one address (one NVIDIA H200).

CPU runs work too (``--no-trace``), but the numbers that matter are the GPU's.
"""

from __future__ import annotations

import argparse
import glob
import gzip
import json
import shutil
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import bench
from common.stages import stage_times

from sinkjax import synth as S


def halves(images: list[np.ndarray], rig, repeats: int) -> tuple[dict, Callable[[], None]]:
    """ms per batch of each compiled half, frames on the device, results left there; and a
    function running both once (for the trace)."""
    import jax

    n = len(images)
    _, _, prepare, finish = bench.device_halves(images, rig)
    prepared = jax.block_until_ready(prepare())
    out = jax.block_until_ready(finish(prepared))
    times: dict[str, list[float]] = {"prepare": [], "finish": [], "both": []}
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(prepare())
        t1 = time.perf_counter()
        jax.block_until_ready(finish(prepared))
        t2 = time.perf_counter()
        jax.block_until_ready(finish(prepare()))
        t3 = time.perf_counter()
        times["prepare"].append(1000 * (t1 - t0))
        times["finish"].append(1000 * (t2 - t1))
        times["both"].append(1000 * (t3 - t2))
    ms = {k: round(statistics.median(v), 3) for k, v in times.items()}
    ms["frames_per_s"] = round(1000 * n / ms["both"], 1)
    ms["statuses_first4"] = np.asarray(out.status).tolist()[:4]
    ms["z0_mm_first4"] = [round(float(z), 4) for z in np.asarray(out.sinkage_mm)[:4]]
    ms["z0_mm_spread"] = [  # the same frame repeated in the batch: any spread is the device's
        round(float(np.ptp(np.asarray(out.sinkage_mm)[i::4])), 6) for i in range(min(4, n))
    ]
    return ms, lambda: jax.block_until_ready(finish(prepare()))


def trace_summary(call: Callable[[], None], top: int = 60, keep: str | None = None) -> dict:
    """Run ``call`` under the profiler; GPU kernel time summed by compiled function and kernel."""
    import jax

    with tempfile.TemporaryDirectory() as tmp:
        call()
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            call()
        found = glob.glob(f"{tmp}/**/perfetto_trace.json.gz", recursive=True)
        if not found:
            listing = glob.glob(tmp + "/**", recursive=True)
            return {"error": f"no perfetto trace under {tmp}: {listing}"}
        if keep:
            shutil.copy(found[0], keep)
        with gzip.open(found[0], "rt") as f:
            data = json.load(f)
    events = data["traceEvents"] if isinstance(data, dict) else data
    pname = {
        e["pid"]: e.get("args", {}).get("name", "")
        for e in events
        if e.get("ph") == "M" and e.get("name") == "process_name"
    }
    by_process: dict = defaultdict(float)
    by_kernel: dict = defaultdict(lambda: [0.0, 0])
    gpu_span = [float("inf"), 0.0]
    for e in events:
        if e.get("ph") != "X" or "dur" not in e:
            continue
        proc = pname.get(e.get("pid"), "")
        dur = float(e["dur"])
        by_process[proc] += dur
        if "GPU" not in proc.upper():
            continue
        gpu_span[0] = min(gpu_span[0], float(e["ts"]))
        gpu_span[1] = max(gpu_span[1], float(e["ts"]) + dur)
        module = e.get("args", {}).get("hlo_module", "")
        k = by_kernel[f"{module}: {e.get('name', '')}" if module else e.get("name", "")]
        k[0] += dur
        k[1] += 1
    kernels = sorted(by_kernel.items(), key=lambda kv: -kv[1][0])[:top]
    return {
        "processes_us": {k: round(v, 1) for k, v in by_process.items()},
        "gpu_kernel_us_total": round(sum(v[0] for v in by_kernel.values()), 1),
        "gpu_span_us": round(gpu_span[1] - gpu_span[0], 1) if gpu_span[1] else None,
        "kernels": [{"name": k[:300], "us": round(v[0], 1), "count": v[1]} for k, v in kernels],
    }


def report(paths: list[str]) -> str:
    """Markdown: each run's halves, its stages (if timed) and its top GPU kernels (if traced)."""
    runs = [(Path(p).stem, json.loads(Path(p).read_text(encoding="utf-8"))) for p in paths]
    lines = [
        "# The soft method on a GPU, stage by stage (`experiments/gpu_profile.py`)",
        "",
        "ms per batch (median); frames already on the device, results left there.",
        "",
        "| run | machine | image | batch | prepare [ms] | finish [ms] | both [ms] | frames/s "
        "| z0 of the 4 frames [mm] |",
        "|---|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for name, r in runs:
        h = r["halves_ms"]
        z0 = ", ".join(f"{z:.4f}" for z in h.get("z0_mm_first4", []))
        lines.append(
            f"| {name} | {r['machine']} | {r['size']} | {r['batch']} | {h['prepare']:.1f} | "
            f"{h['finish']:.1f} | {h['both']:.1f} | {h['frames_per_s']:.0f} | {z0} |"
        )
    staged = [(n, r) for n, r in runs if "stages_ms_per_batch" in r]
    if staged:
        lines += [
            "",
            "## Stages, each compiled alone under `jax.vmap` (ms per batch)",
            "",
            "| stage | " + " | ".join(n for n, _ in staged) + " |",
            "|---|" + "---:|" * len(staged),
        ]
        for i, row in enumerate(staged[0][1]["stages_ms_per_batch"]):
            cells = [f"{r['stages_ms_per_batch'][i]['ms']:.2f}" for _, r in staged]
            lines.append(f"| {row['stage']} | " + " | ".join(cells) + " |")
    for name, r in runs:
        if "kernels" not in r.get("trace", {}):
            continue
        tr = r["trace"]
        lines += [
            "",
            f"## {name}: the GPU's kernels in one prepare + finish",
            "",
            f"Kernel time {tr['gpu_kernel_us_total'] / 1000:.1f} ms over a span of "
            f"{tr['gpu_span_us'] / 1000:.1f} ms. The ten longest:",
            "",
            "| kernel | ms | launches |",
            "|---|---:|---:|",
            *(
                f"| `{k['name'][:60]}` | {k['us'] / 1000:.2f} | {k['count']} |"
                for k in tr["kernels"][:10]
            ),
        ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-stages", action="store_true")
    parser.add_argument("--no-trace", action="store_true")
    parser.add_argument("--out", default="gpu_profile.json")
    parser.add_argument("--keep-trace", help="also copy the perfetto trace (.json.gz) here")
    parser.add_argument("--report", nargs="+", metavar="JSON", help="tabulate saved runs")
    parser.add_argument("--md", default="gpu_profile.md", help="--report's Markdown file")
    args = parser.parse_args(argv)
    if args.report:
        text = report(args.report)
        Path(args.md).write_text(text, encoding="utf-8")
        print(text)
        return 0
    t_start = time.perf_counter()
    rng = np.random.default_rng(0)  # the frames of bench.py
    scenes = S.recording_scenes(rng, bench.N_DISTINCT, width=args.width, height=args.height)
    rig = S.rig_for(scenes[0])
    rendered = [S.render(scene, seed=i)[0] for i, scene in enumerate(scenes)]
    images = [rendered[i % len(rendered)] for i in range(args.batch)]
    out: dict = {"machine": bench._machine(), "batch": args.batch}
    out["size"] = f"{args.width}x{args.height}"

    def save() -> None:
        out["seconds"] = round(time.perf_counter() - t_start, 1)
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")

    t0 = time.perf_counter()
    out["halves_ms"], call = halves(images, rig, args.repeats)
    out["halves_first_s"] = round(time.perf_counter() - t0, 1)
    print("halves", out["halves_ms"], flush=True)
    save()
    if not args.no_trace:
        out["trace"] = trace_summary(call, keep=args.keep_trace)
        print("trace", {k: out["trace"].get(k) for k in ("gpu_kernel_us_total", "gpu_span_us")})
        save()
    if not args.no_stages:
        out["stages_ms_per_batch"] = stage_times(rendered[1], rig, args.repeats, args.batch)
        print("stages", out["stages_ms_per_batch"], flush=True)
        save()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
