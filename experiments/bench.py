"""Throughput and peak memory of the classic and soft methods (``make bench``).

For each configuration -- classic at 640x480 and 1280x720, soft at both sizes with batch sizes 1,
4 and 8 -- a fresh Python process renders a few synthetic frames (``sinkjax.synth``, not timed),
compiles (soft; timed separately), then measures N frames through the pipeline's batching
(``iter_estimates``) and reports frames/s and its peak resident memory (``ru_maxrss``: the whole
process, JAX runtime and compiled code included). One process per configuration, so each peak is
its own. Writes ``experiments/results/bench.json`` (the numbers) and, from it, ``bench.md``.

    python experiments/bench.py            # all configurations (several minutes on 2 CPU cores)
    python experiments/bench.py --quick    # 640x480 only, soft batch 1 and 8, fewer frames

Where JAX's default device is a GPU, the soft rows take larger batches (8, 32, 128), and each also
reports the compiled method alone: frames already on the device, results left there
(``device``), and host images in, host arrays out (``+ transfers``); decoding is never timed.
The report then goes to ``bench_gpu.md`` (the CPU report stays). The rows are saved as each
configuration ends, so a run stopped part-way keeps what it measured.
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
GPU_BATCHES = (128, 32, 8)  # most telling first: a run cut short keeps those
DEVICE_REPS = 10  # timed calls of the compiled method per row (after one untimed)

GPU_PARAGRAPH = """\
## Running on a GPU

The soft estimator is plain JAX (`jit` + `vmap` over a batch of frames), so the same code runs on
an NVIDIA GPU once JAX's CUDA build is installed next to sinkjax (`pip install -U "jax[cuda13]"`,
or `jax[cuda12]` for a CUDA 12 driver; Linux). JAX then puts the estimator on the GPU by itself --
check with `python -c "import jax; print(jax.devices())"` -- and `JAX_PLATFORMS=cpu` forces the
CPU again. On a GPU raise `--batch-size` to 128: one compiled call then measures a whole batch
(frames are padded to 1, 8, 32 or 128), and compilation (once per image size and batch size,
about 35-40 s) is paid once per run. The classic method is OpenCV on the CPU and runs the same
everywhere. This project's CI has no GPU: the GPU path is not exercised by the test suite.
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
    rendered = [S.render(scene, seed=i) for i, scene in enumerate(scenes)]
    images = [image for image, _ in rendered]
    truths = [truth for _, truth in rendered]

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
    # Accuracy of the first frames against the renderer's truth: the same frames on every
    # device, so a GPU's numbers can be compared with a CPU's row for row.
    first = list(iter_estimates(frames(N_DISTINCT), rig, method=method, batch_size=batch))
    z0 = [r.sinkage_mm if r.status == "ok" else None for _, r in first]
    row = {
        "method": method,
        "size": f"{width}x{height}",
        "batch": batch if method == "soft" else 1,
        "frames": n_frames,
        "compile_s": compile_s,
        "seconds": seconds,
        "fps": n_frames / seconds,
        "statuses": statuses,
        "z0_mm": z0,
        "true_z0_mm": [t.sinkage_mm for t in truths],
    }
    if method == "soft" and _on_accelerator():
        row.update(_device_rates([images[i % len(images)] for i in range(batch)], rig))
    row["peak_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    return row


def _on_accelerator() -> bool:
    import jax

    return jax.default_backend() != "cpu"


def device_halves(images: list, rig) -> tuple:
    """The soft method's two compiled halves on one padded batch put on the device, the
    recording's rim found first as the pipeline does: ``(run, rim, prepare, finish)`` with
    ``prepare()`` the mask stage of the batch and ``finish(prepared)`` its fit stage, results
    left on the device. Batched (vmapped) functions, also on a CPU."""
    import jax
    import numpy as np

    from sinkjax.soft.batch import SoftRecording, _Run

    n = len(images)
    recording = SoftRecording()
    recording(images, rig, [f"d{i}" for i in range(n)], pad_to=n)  # finds the rim
    rim = recording.rim_for(*images[0].shape[:2])
    run = _Run(rig, None, n)
    run.vmap = True
    frames = jax.device_put(np.stack(images))
    prepare_fn = run._fn("prepare", (frames, run.segmenter, run.arrays, rim))
    prepared = prepare_fn(frames, run.segmenter, run.arrays, rim)
    finish_fn = run._fn("finish", (frames, prepared, run.arrays))

    def prepare() -> object:
        return prepare_fn(frames, run.segmenter, run.arrays, rim)

    def finish(prepared: object) -> object:
        return finish_fn(frames, prepared, run.arrays)

    return run, rim, prepare, finish


def _device_rates(images: list, rig) -> dict:
    """Frames/s of the soft method's compiled functions alone on one padded batch: frames
    already on the device with results left there, and host images in, host arrays out (what
    the pipeline does, without reading files or making rows)."""
    import jax

    n = len(images)
    run, rim, prepare, finish = device_halves(images, rig)

    run.finish(images, run.prepare(images, rim))
    t0 = time.perf_counter()
    for _ in range(DEVICE_REPS):
        run.finish(images, run.prepare(images, rim))
    host_s = (time.perf_counter() - t0) / DEVICE_REPS

    jax.block_until_ready(finish(prepare()))
    t0 = time.perf_counter()
    out = None
    for _ in range(DEVICE_REPS):
        out = finish(prepare())
    jax.block_until_ready(out)
    device_s = (time.perf_counter() - t0) / DEVICE_REPS
    return {"device_fps": n / device_s, "transfer_fps": n / host_s}


def _configs(quick: bool, gpu: bool = False) -> list[tuple[str, int, int, int, int]]:
    sizes = SIZES[:1] if quick else SIZES
    out = []
    if gpu:  # batch by batch, largest first: a run cut short has both sizes' best rows
        out += [("classic", w, h, 1, 8) for w, h in sizes]
        for b in GPU_BATCHES[:1] if quick else GPU_BATCHES:
            out += [("soft", w, h, b, 4 * b) for w, h in sizes]
        return out
    for width, height in sizes:
        out.append(("classic", width, height, 1, 4 if quick else 8))
        for b in (1, 8) if quick else BATCHES:
            out.append(("soft", width, height, b, 8 if quick else 24))
    return out


def _default_backend() -> str:
    """JAX's default backend, asked in a child process (this one never imports JAX)."""
    code = "import jax; print(jax.default_backend())"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    return proc.stdout.strip().splitlines()[-1] if proc.returncode == 0 else "cpu"


def _machine() -> str:
    import jax

    devices = ", ".join(
        str(d) if d.platform == "cpu" else f"{d} ({d.device_kind})" for d in jax.devices()
    )
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


def _gpu_table(rows: list[dict]) -> str:
    lines = [
        "| method | image | batch | compile [s] | pipeline frames/s | + transfers frames/s "
        "| device frames/s | device ms/frame | frames not ok | z0 error, first 4 frames [mm] |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in rows:
        device = r.get("device_fps")
        cells = [
            r["method"],
            r["size"],
            str(r["batch"]),
            f"{r['compile_s']:.1f}" if r["method"] == "soft" else "-",
            f"{r['fps']:.1f}",
            f"{r['transfer_fps']:.0f}" if device else "-",
            f"{device:.0f}" if device else "-",
            f"{1000 / device:.2f}" if device else "-",
            _not_ok(r),
            _errors(r),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _not_ok(row: dict) -> str:
    bad = {k: v for k, v in row.get("statuses", {}).items() if k != "ok"}
    n = sum(row.get("statuses", {}).values())
    return ", ".join(f"{v} of {n} {k}" for k, v in bad.items()) or "0"


def _errors(row: dict) -> str:
    pairs = zip(row.get("z0_mm", []), row.get("true_z0_mm", []), strict=False)
    return ", ".join("failed" if z is None else f"{z - t:+.3f}" for z, t in pairs) or "-"


def report(data: dict) -> str:
    """The Markdown report from the saved JSON (``bench.json`` / ``bench_gpu.json``)."""
    rows = data["rows"]
    gpu = data.get("backend", "cpu") != "cpu"
    classic = {r["size"]: r["fps"] for r in rows if r["method"] == "classic"}
    key = "device_fps" if gpu else "fps"
    best_soft: dict[str, dict] = {}
    for r in rows:
        if r["method"] == "soft" and r.get(key, 0) > best_soft.get(r["size"], {key: 0})[key]:
            best_soft[r["size"]] = r
    summary = [
        f"- {size}: soft {s[key]:.2f} frames/s (batch {s['batch']}"
        + (", on the device" if gpu else "")
        + f") vs classic {classic[size]:.2f} frames/s: soft is {s[key] / classic[size]:.1f}x "
        "classic"
        for size, s in best_soft.items()
        if size in classic
    ]
    about = (
        "Frames/s exclude start-up and the soft method's compilation (its own column; paid "
        "once per image size and batch size). "
    )
    if gpu:
        about += (
            "Pipeline: `iter_estimates` on a recording of 4 batches (the first batch is measured "
            "twice: once to find the recording's rim), rows made in Python. + transfers: the "
            "compiled method on one batch of host images, results back as NumPy arrays. "
            "Device: the same with the frames already on the GPU and the results left there. "
            "Classic is OpenCV on the host CPU. The last column is each of the four distinct "
            "frames' z0 minus the renderer's truth (a CPU run's `bench.json` keeps the same "
            "numbers for the same frames)."
        )
    else:
        about += (
            "Peak RSS is the whole process (one per row). Load average at the end (1/5/15 "
            f"min): {'/'.join(f'{x:.1f}' for x in data['load_average'])} on "
            f"{data['cpu_count']} cores; on a shared machine the figures move by up to ~2x "
            "between runs, so compare the rows of one run."
        )
    return "\n".join(
        [
            "# Throughput benchmark (`make bench`)",
            "",
            GPU_PARAGRAPH,
            "## GPU numbers" if gpu else "## CPU numbers",
            "",
            f"{machine_line(data)} {about}",
            "",
            _gpu_table(rows) if gpu else _table(rows),
            "",
            *summary,
            "",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="640x480 only, fewer frames")
    parser.add_argument(
        "--out", help="Markdown report (default: results/bench.md, or bench_gpu.md on a GPU)"
    )
    parser.add_argument(
        "--one", nargs=5, metavar=("METHOD", "W", "H", "BATCH", "N"), help="(internal)"
    )
    args = parser.parse_args(argv)
    if args.one:
        method, w, h, b, n = args.one
        print(json.dumps(_one(method, int(w), int(h), int(b), int(n))))
        return 0

    backend = _default_backend()
    gpu = backend != "cpu"
    out = Path(args.out or RESULTS / ("bench_gpu.md" if gpu else "bench.md"))
    out.parent.mkdir(parents=True, exist_ok=True)
    data: dict = {
        "quick": args.quick,
        "backend": backend,
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": "",
        "cpu_count": os.cpu_count(),
        "rows": [],
    }
    started = time.perf_counter()
    for method, w, h, b, n in _configs(args.quick, gpu):
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
        data["rows"].append(row)
        extra = "".join(
            f", {key} {row[key]:.0f}" for key in ("device_fps", "transfer_fps") if key in row
        )
        print(
            f"bench: {label}: {row['fps']:.2f} frames/s{extra}, peak {row['peak_mib']:.0f} "
            f"MiB, compile {row['compile_s']:.1f} s, statuses {row['statuses']}",
            file=sys.stderr,
            flush=True,
        )
        # Saved after every configuration: a run stopped part-way keeps its rows.
        data["seconds"] = time.perf_counter() - started
        data["load_average"] = list(os.getloadavg())
        out.with_suffix(".json").write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    data["machine"] = _machine()
    out.with_suffix(".json").write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    text = report(json.loads(out.with_suffix(".json").read_text(encoding="utf-8")))
    out.write_text(text, encoding="utf-8")
    print(text)
    print(f"-> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
