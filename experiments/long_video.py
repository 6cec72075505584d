"""A long recording, streamed: 2000 frames of 640x480 video through ``sinkjax estimate``.

Writes a synthetic video (a few frames rendered with ``sinkjax.synth.render()``, cycled with small
shifts of sensor noise, so it is quick to make), then runs ``sinkjax estimate`` on it in a
subprocess per method and reports the subprocess's peak memory (must stay under 2 GB: frames are
streamed, never held), how its memory moved during the run, and frames/s. Rerunnable: the video
is kept in ``experiments/_cache/long_video`` and reused when it matches. Not part of the tests.

    python experiments/long_video.py                       # classic and soft, 2000 frames
    python experiments/long_video.py --methods soft --frames 500
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).parent
CACHE = HERE / "_cache" / "long_video"
RESULTS = HERE / "results"
LIMIT_MIB = 2048
N_DISTINCT = 6


def make_video(path: Path, n_frames: int, width: int, height: int, fps: float = 10.0) -> Path:
    """The synthetic video and its ``rig.toml`` next to it; reused if already there."""
    from sinkjax import save_rig, synth as S

    meta = path.with_suffix(".json")
    wanted = {"frames": n_frames, "width": width, "height": height, "distinct": N_DISTINCT}
    if path.is_file() and meta.is_file() and json.loads(meta.read_text()) == wanted:
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(2000)
    scenes = S.recording_scenes(rng, N_DISTINCT, width=width, height=height)
    save_rig(S.rig_for(scenes[0]), path.parent / "rig.toml", comment="long_video.py")
    frames = [S.render(scene, seed=i)[0] for i, scene in enumerate(scenes)]
    noise = rng.integers(-3, 4, (height + 8, width + 8, 3), dtype=np.int16)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height))
    if not writer.isOpened():
        raise SystemExit(f"cannot write {path} with mp4v")
    for i in range(n_frames):
        dy, dx = rng.integers(0, 8, 2)
        shifted = noise[dy : dy + height, dx : dx + width]
        frame = np.clip(frames[i % N_DISTINCT].astype(np.int16) + shifted, 0, 255)
        writer.write(cv2.cvtColor(frame.astype(np.uint8), cv2.COLOR_RGB2BGR))
    writer.release()
    meta.write_text(json.dumps(wanted))
    return path


def _rss_mib(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def run_estimate(video: Path, method: str, out_csv: Path, batch: int) -> dict:
    """``sinkjax estimate`` in a subprocess: peak RSS (wait4), RSS samples, rows, frames/s."""
    cmd = [
        sys.executable, "-m", "sinkjax.app.cli", "estimate", str(video),
        "--rig", str(video.parent / "rig.toml"), "--method", method,
        "--batch-size", str(batch), "--out", str(out_csv),
    ]  # fmt: skip
    log = out_csv.with_suffix(".log")
    started = time.perf_counter()
    with open(log, "w") as log_file:
        proc = subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT)
    samples: list[tuple[float, float, int]] = []  # (seconds, RSS MiB, rows written)
    while True:
        # wait4 reaps the child and gives ITS OWN peak RSS (ru_maxrss, KiB on Linux).
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            proc.returncode = os.waitstatus_to_exitcode(status)
            break
        rss = _rss_mib(proc.pid)
        rows = out_csv.read_bytes().count(b"\n") - 1 if out_csv.exists() else 0
        if rss is not None:
            samples.append((time.perf_counter() - started, rss, max(rows, 0)))
        time.sleep(1.0)
    wall = time.perf_counter() - started
    peak_mib = usage.ru_maxrss / 1024
    output = log.read_text()
    if proc.returncode != 0:
        raise SystemExit(f"estimate --method {method} failed:\n{output[-3000:]}")
    rows = out_csv.read_bytes().count(b"\n") - 1
    summary = [line for line in output.splitlines() if " frames: " in line][-1]
    match = re.search(r"\(([\d.]+) frames/s\)", summary)
    # Memory growth: RSS once the first tenth of the rows are out vs at the end.
    steady = [s for s in samples if s[2] >= rows / 10]
    return {
        "method": method,
        "batch": batch,
        "rows": rows,
        "wall_s": wall,
        "pipeline_fps": float(match.group(1)) if match else float("nan"),
        "wall_fps": rows / wall,
        "peak_mib": peak_mib,
        "max_sampled_mib": max((s[1] for s in samples), default=float("nan")),
        "rss_early_mib": steady[0][1] if steady else float("nan"),
        "rss_late_mib": steady[-1][1] if steady else float("nan"),
        "summary": summary,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--methods", nargs="+", default=["classic", "soft"])
    parser.add_argument("--batch-size", type=int, default=8, help="soft batch size (8)")
    parser.add_argument("--out", default=str(RESULTS / "long_video.md"))
    args = parser.parse_args(argv)

    video = CACHE / f"synthetic_{args.frames}_{args.width}x{args.height}.mp4"
    t0 = time.perf_counter()
    make_video(video, args.frames, args.width, args.height)
    print(f"video: {video} ({video.stat().st_size / 2**20:.0f} MiB, "
          f"{time.perf_counter() - t0:.0f} s to make or reuse)", file=sys.stderr)  # fmt: skip
    runs = []
    for method in args.methods:
        print(f"estimate --method {method} ...", file=sys.stderr, flush=True)
        run = run_estimate(video, method, CACHE / f"results_{method}.csv", args.batch_size)
        runs.append(run)
        print(json.dumps(run), file=sys.stderr)

    lines = [
        "# Long video, streamed",
        "",
        f"{args.frames} frames of {args.width}x{args.height} synthetic mp4v video "
        f"(`experiments/long_video.py`, {os.cpu_count()} CPU cores visible, "
        f"{time.strftime('%Y-%m-%d %H:%M')}). Each method is one `sinkjax estimate` process; "
        "peak RSS is that process's `ru_maxrss`; 'RSS early/late' are sampled once a tenth of "
        "the rows is written and at the end (flat = constant memory). frames/s: the pipeline's "
        "own figure (compilation included) and rows / wall time (start-up included).",
        "",
        "| method | batch | rows | peak RSS [MiB] | RSS early -> late [MiB] | frames/s | "
        "frames/s (wall) | < 2 GB |",
        "|---|---:|---:|---:|---|---:|---:|---|",
    ]
    for r in runs:
        batch = r["batch"] if r["method"] == "soft" else "-"
        ok = "yes" if r["peak_mib"] < LIMIT_MIB and r["rows"] == args.frames else "NO"
        lines.append(
            f"| {r['method']} | {batch} | {r['rows']} | {r['peak_mib']:.0f} | "
            f"{r['rss_early_mib']:.0f} -> {r['rss_late_mib']:.0f} | {r['pipeline_fps']:.2f} | "
            f"{r['wall_fps']:.2f} | {ok} |"
        )
    lines.append("")
    lines += [f"- {r['method']}: `{r['summary']}`" for r in runs]
    lines.append("")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines), encoding="utf-8")
    print("\n".join(lines))
    bad = [r for r in runs if r["peak_mib"] >= LIMIT_MIB or r["rows"] != args.frames]
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
