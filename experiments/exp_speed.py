"""Speed: frames per second of the classic and soft methods by image size and batch size.

Does not re-measure by itself: ``experiments/bench.py`` (``make bench``) does that, one fresh
process per configuration. This script plots the numbers it saved: ``bench.json`` in the output
folder when present (e.g. written by ``--run`` or ``run_all.py --bench``), else
``experiments/results/bench.json``. ``--run`` first runs ``bench.py`` (``--quick`` in quick mode)
with its report written into the output folder; run it alone, as timings are its point.

    python experiments/exp_speed.py [--quick] [--run] [--out-dir DIR] [--cache-dir DIR]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import bench
import numpy as np
from common import report, runs

NAME = "exp_speed"
SCRIPT = runs.HERE / "bench.py"


def source(out_dir: Path) -> Path | None:
    for path in (out_dir / "bench.json", runs.RESULTS / "bench.json"):
        if path.is_file():
            return path
    return None


def run_external(setup: runs.Setup) -> None:
    cmd = [sys.executable, str(SCRIPT), "--out", str(setup.out_dir / "bench.md")]  # + bench.json
    cmd += ["--quick"] if setup.quick else []
    runs.log(f"{NAME}: running {' '.join(cmd[1:])}")
    subprocess.run(cmd, check=True)


def run(setup: runs.Setup, *, refresh: bool = False) -> dict[str, Any]:
    t0 = time.perf_counter()
    if refresh or source(setup.out_dir) is None:
        run_external(setup)
    src = source(setup.out_dir)
    assert src is not None, "bench.py saved no numbers"
    data = json.loads(src.read_text(encoding="utf-8"))
    rows = data["rows"]
    if not rows:
        raise RuntimeError(f"{src}: no configurations")
    sizes = list(dict.fromkeys(r["size"] for r in rows))
    configs = list(dict.fromkeys((r["method"], str(r["batch"])) for r in rows))
    fps = {(r["method"], str(r["batch"]), r["size"]): float(r["fps"]) for r in rows}
    comp = {
        (r["method"], str(r["batch"]), r["size"]): float(r["compile_s"])
        if r["method"] == "soft"
        else np.nan
        for r in rows
    }
    _figure(setup, sizes, configs, fps, comp, src)
    origin = bench.machine_line(data)
    table_rows = []
    summary: dict[str, Any] = {"source": src.with_suffix(".md").name}
    for size in sizes:
        cl = fps.get(("classic", "1", size), np.nan)
        soft = {b: v for (m, b, s), v in fps.items() if m == "soft" and s == size}
        best_b = max(soft, key=lambda b: soft[b]) if soft else ""
        best = soft.get(best_b, np.nan)
        summary[f"{size}_classic_fps"] = cl
        summary[f"{size}_soft_fps"] = best
        summary[f"{size}_soft_batch"] = best_b
        table_rows.append(
            [
                size,
                report.fmt(cl),
                report.fmt(best),
                best_b,
                report.fmt(best / cl if cl else np.nan, 1) + "x",
            ]
        )
    link = os.path.relpath(src.with_suffix(".md"), setup.out_dir)
    doc = "\n\n".join(
        [
            "# Speed: classic vs soft",
            f"Figure by `python experiments/{NAME}.py` from the numbers of "
            f"[`{src.with_suffix('.md').name}`]({link}) (saved in `{src.name}` by "
            f"`experiments/bench.py`; {time.perf_counter() - t0:.0f} s). {origin}",
            report.md_table(
                [
                    "image",
                    "classic (frames/s)",
                    "soft, best batch (frames/s)",
                    "batch",
                    "soft / classic",
                ],
                table_rows,
            ),
            f"![speed]({NAME}.png)",
        ]
    )
    report.write_md(setup, NAME, doc)
    return summary


def _figure(
    setup: runs.Setup,
    sizes: list[str],
    configs: list[tuple[str, str]],
    fps: dict[tuple[str, str, str], float],
    comp: dict[tuple[str, str, str], float],
    src: Path,
) -> None:
    fig, axes = report.figure(1, 2, (12.0, 4.5))
    ax, ax2 = axes[0, 0], axes[0, 1]
    x = np.arange(len(sizes))
    width = 0.8 / len(configs)
    shades = ["#dd8452", "#c4692f", "#9c4f1f", "#6e3512"]
    k = 0
    for j, (method, batch) in enumerate(configs):
        if method == "classic":
            colour = report.METHOD_COLOURS["classic"]
            label = "classic (paper's method)"
        else:
            colour, k = shades[k % len(shades)], k + 1
            label = f"soft, batch {batch}"
        vals = [fps.get((method, batch, s), np.nan) for s in sizes]
        ax.bar(x + (j - (len(configs) - 1) / 2) * width, vals, width, color=colour, label=label)
        if method == "soft":
            cs = [comp.get((method, batch, s), np.nan) for s in sizes]
            ax2.bar(x + (j - (len(configs) - 1) / 2) * width, cs, width, color=colour, label=label)
    for a in (ax, ax2):
        a.set_xticks(x, sizes)
        a.set_xlabel("image size (px)")
        a.legend(fontsize=8)
    ax.set_ylabel("throughput (frames/s, steady state)")
    ax.set_title("Frames per second by image and batch size")
    ax2.set_ylabel("compile time (s, once per image and batch size)")
    ax2.set_title("Soft method: one-off compilation")
    fig.suptitle(f"Speed on the CPU (numbers from {src.name})")
    report.save_figure(setup, fig, NAME)


def main(argv: list[str] | None = None) -> int:
    setup, args = runs.parse_args(
        __doc__.splitlines()[0], argv, run_help="first rerun bench.py (minutes; run it alone)"
    )
    runs.timed(lambda s: run(s, refresh=args.run), setup, NAME)
    return 0


if __name__ == "__main__":
    sys.exit(main())
