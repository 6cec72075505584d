"""Throughput and peak memory of the classic and soft methods (``make bench``).

For each configuration -- classic at 640x480 and 1280x720, soft at both sizes with batch sizes 1,
4 and 8 -- a fresh Python process renders a few synthetic frames (``sinkjax.synth``, not timed),
compiles (soft; timed separately), then measures N frames through the pipeline's batching
(``iter_estimates``) and reports frames/s and its peak resident memory (``ru_maxrss``: the whole
process, JAX runtime and compiled code included). One process per configuration, so each peak is
its own. Writes ``experiments/results/bench.json`` (the numbers) and, from it, ``bench.md``.

    python experiments/bench.py            # all configurations (several minutes on 2 CPU cores)
    python experiments/bench.py --quick    # 640x480 only, soft batch 1 and 8, fewer frames
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).parent / "results"
SIZES = ((640, 480), (1280, 720))
BATCHES = (1, 4, 8)
N_DISTINCT = 4  # rendered frames, cycled (rendering is slower than measuring)

GPU_PARAGRAPH = """\
## Running on a GPU

The soft estimator is plain JAX (`jit` + `vmap` over a batch of frames), so the same code runs on
an NVIDIA GPU once JAX's CUDA build is installed next to sinkjax: `pip install -U "jax[cuda12]"`
(Linux, CUDA 12 driver). JAX then puts the estimator on the GPU by itself -- check with
`python -c "import jax; print(jax.devices())"` -- and `JAX_PLATFORMS=cpu` forces the CPU again.
On a GPU raise `--batch-size` (e.g. 32-64): one compiled call then measures a whole batch, and
compilation (once per image size and batch size) is paid once per run. The classic method is
OpenCV on the CPU and runs the same everywhere. This project's CI has no GPU: the numbers below
are CPU numbers, and the GPU path is not exercised by the test suite.
"""


def _one(method: str, width: int, height: int, batch: int, n_frames: int) -> dict:
    """Run one configuration in this process; returns its measurements."""
    import numpy as np

    from sinkjax import synth as S
    from sinkjax.app.frames import Frame
    from sinkjax.app.pipeline import iter_estimates

    rng = np.random.default_rng(0)
    scenes = S.recording_scenes(rng, N_DISTINCT, width=width, height=height)
    rig = S.rig_for(scenes[0])
    images = [S.render(scene, seed=i)[0] for i, scene in enumerate(scenes)]

    def frames(n: int, offset: int = 0):
        for i in range(n):
            yield Frame(f"f{offset + i:06d}", images[(offset + i) % len(images)])

    compile_s = 0.0
    if method == "soft":
        t0 = time.perf_counter()
        # A full batch: the compiled function for this (size, batch) is then reused.
        list(iter_estimates(frames(batch, 10_000), rig, method="soft", batch_size=batch))
        compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    statuses: dict[str, int] = {}
    for _, result in iter_estimates(frames(n_frames), rig, method=method, batch_size=batch):
        statuses[result.status] = statuses.get(result.status, 0) + 1
    seconds = time.perf_counter() - t0
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return {
        "method": method,
        "size": f"{width}x{height}",
        "batch": batch if method == "soft" else 1,
        "frames": n_frames,
        "compile_s": compile_s,
        "seconds": seconds,
        "fps": n_frames / seconds,
        "peak_mib": peak_kib / 1024,
        "statuses": statuses,
    }


def _configs(quick: bool) -> list[tuple[str, int, int, int, int]]:
    sizes = SIZES[:1] if quick else SIZES
    batches = (1, 8) if quick else BATCHES
    out = []
    for width, height in sizes:
        out.append(("classic", width, height, 1, 4 if quick else 8))
        for b in batches:
            out.append(("soft", width, height, b, 8 if quick else 24))
    return out


def _machine() -> str:
    import jax

    devices = ", ".join(str(d) for d in jax.devices())
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores visible, "
        f"Python {platform.python_version()}, jax {jax.__version__} on {devices}"
    )


def _table(rows: list[dict]) -> str:
    lines = [
        "| method | image | batch | frames | compile [s] | frames/s | ms/frame | peak RSS [MiB] |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        compile_s = f"{r['compile_s']:.1f}" if r["method"] == "soft" else "-"
        lines.append(
            f"| {r['method']} | {r['size']} | {r['batch']} | {r['frames']} | {compile_s} | "
            f"{r['fps']:.2f} | {1000 / r['fps']:.0f} | {r['peak_mib']:.0f} |"
        )
    return "\n".join(lines)


def machine_line(data: dict) -> str:
    """The report's "Machine:" sentence from the saved JSON."""
    return (
        f"Machine: {data['machine']}. Run {'--quick' if data['quick'] else '(full)'} in "
        f"{data['seconds']:.0f} s, {data['date']}."
    )


def report(data: dict) -> str:
    """The Markdown report from the saved JSON (``bench.json``)."""
    rows = data["rows"]
    classic = {r["size"]: r["fps"] for r in rows if r["method"] == "classic"}
    best_soft: dict[str, dict] = {}
    for r in rows:
        if r["method"] == "soft" and r["fps"] > best_soft.get(r["size"], {"fps": 0})["fps"]:
            best_soft[r["size"]] = r
    summary = [
        f"- {size}: soft {s['fps']:.2f} frames/s (batch {s['batch']}) vs classic "
        f"{classic[size]:.2f} frames/s: soft is {s['fps'] / classic[size]:.1f}x classic"
        for size, s in best_soft.items()
        if size in classic
    ]
    return "\n".join(
        [
            "# Throughput benchmark (`make bench`)",
            "",
            GPU_PARAGRAPH,
            "## CPU numbers",
            "",
            f"{machine_line(data)} Frames/s exclude start-up and the soft "
            "method's compilation (its own column; paid once per image size and batch size). "
            "Peak RSS is the whole process (one per row). Load average at the end (1/5/15 "
            f"min): {'/'.join(f'{x:.1f}' for x in data['load_average'])} on "
            f"{data['cpu_count']} cores; on a shared machine the figures move by up to ~2x "
            "between runs, so compare the rows of one run.",
            "",
            _table(rows),
            "",
            *summary,
            "",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="640x480 only, fewer frames")
    parser.add_argument("--out", default=str(RESULTS / "bench.md"), help="Markdown report")
    parser.add_argument(
        "--one", nargs=5, metavar=("METHOD", "W", "H", "BATCH", "N"), help="(internal)"
    )
    args = parser.parse_args(argv)
    if args.one:
        method, w, h, b, n = args.one
        print(json.dumps(_one(method, int(w), int(h), int(b), int(n))))
        return 0

    rows = []
    started = time.perf_counter()
    for method, w, h, b, n in _configs(args.quick):
        label = f"{method} {w}x{h} batch {b}"
        print(f"bench: {label} ...", file=sys.stderr, flush=True)
        proc = subprocess.run(
            [sys.executable, __file__, "--one", method, str(w), str(h), str(b), str(n)],
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            print(proc.stderr[-3000:], file=sys.stderr)
            raise SystemExit(f"bench: {label} failed")
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(
            f"bench: {label}: {row['fps']:.2f} frames/s, peak {row['peak_mib']:.0f} MiB, "
            f"compile {row['compile_s']:.1f} s, statuses {row['statuses']}",
            file=sys.stderr,
        )
    data = {
        "quick": args.quick,
        "seconds": time.perf_counter() - started,
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": _machine(),
        "load_average": list(os.getloadavg()),
        "cpu_count": os.cpu_count(),
        "rows": rows,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    text = report(json.loads(out.with_suffix(".json").read_text(encoding="utf-8")))
    out.write_text(text, encoding="utf-8")
    print(text)
    print(f"-> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
