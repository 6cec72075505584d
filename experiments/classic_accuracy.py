"""Accuracy of the classic pipeline (``sinkjax.estimate_classic``) on synthetic frames with truth.

Renders several synthetic recordings (one camera set-up and rig each, all terrain kinds, some
travelling left) of preset "clean" and of the "full" mix (lugs, shadows, specular highlights,
JPEG), runs :func:`sinkjax.estimate_classic` on every frame in both modes, the paper's
method (``refine=False``, the default and ``sinkjax estimate --method classic``) and the
sub-pixel refinement (``refine=True``), on the same frames, and reports per mode and preset:

- median relative sinkage error over contact frames with true z0 > 5 mm (the paper's regime),
- median |theta1| and |theta2| errors in degrees over the same frames,
- the failed-frame fraction (any status other than ok / no_contact), and contact mix-ups,
- 90th percentiles, the median signed errors (bias), and the mean time per frame,

all by the rule of :mod:`sinkjax.metrics` (failed frames left out of the errors and counted,
``no_contact`` a measurement of 0). Target for the paper's method on "clean", the least it must
do to be a fair baseline: median relative sinkage error <= 5 %, median angle errors <= 1 deg,
at most 5 % failed frames. Writes every frame to ``classic_accuracy.csv``, the summaries to
``classic_accuracy.json``, and the report, made from the JSON, to ``classic_accuracy.md``.

    .venv/bin/python experiments/classic_accuracy.py [--n 120] [--quick] [--out FILE.md]
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import pathlib
import sys
import time
from dataclasses import dataclass

import numpy as np
from common import runs

import sinkjax as sj
from sinkjax import metrics as sm
from sinkjax.synth import recording_scenes, render, rig_for

FRAMES_PER_RECORDING = 10  # two cycles of the five terrain kinds
SEED = 20240531
DEFAULT_OUT = pathlib.Path(__file__).parent / "results" / "classic_accuracy.md"
# Table label -> estimate_classic's refine flag.
METHODS = {"classic (paper)": False, "classic + sub-pixel refinement": True}
TARGET_REL_PCT = 5.0
TARGET_DEG = 1.0
TARGET_FAILED_PCT = 5.0
SHALLOW_MM = 5.0


@dataclass
class Row:
    method: str
    preset: str
    recording: int
    terrain: str
    contact: bool
    true_mm: float
    true_t1: float
    true_t2: float
    status: str
    mm: float | None
    t1: float | None
    t2: float | None
    seconds: float
    cpu_seconds: float
    message: str


def run_preset(preset: str, n_frames: int, seed: int, verbose: bool) -> dict[str, list[Row]]:
    """Render ``n_frames`` frames of ``preset`` in recordings of 10; estimate each in every mode."""
    rows: dict[str, list[Row]] = {method: [] for method in METHODS}
    n_rec = math.ceil(n_frames / FRAMES_PER_RECORDING)
    for rec in range(n_rec):
        rng = np.random.default_rng([seed, rec, sum(map(ord, preset))])
        travel = "left" if rec % 3 == 2 else "right"
        n = min(FRAMES_PER_RECORDING, n_frames - rec * FRAMES_PER_RECORDING)
        scenes = recording_scenes(rng, n, preset=preset, width=640, height=480, travel=travel)
        rig = rig_for(scenes[0])
        for i, scene in enumerate(scenes):
            img, truth = render(scene, seed=int(rng.integers(2**31)))
            for method, refine in METHODS.items():
                t0, c0 = time.perf_counter(), time.process_time()
                res = sj.estimate_classic(img, rig, name=f"{preset}/{rec}/{i}", refine=refine)
                dt, dc = time.perf_counter() - t0, time.process_time() - c0
                r = Row(
                    method=method,
                    preset=preset,
                    recording=rec,
                    terrain=truth.terrain,
                    contact=truth.contact,
                    true_mm=truth.sinkage_mm,
                    true_t1=truth.theta1_deg,
                    true_t2=truth.theta2_deg,
                    status=res.status,
                    mm=res.sinkage_mm,
                    t1=res.theta1_deg,
                    t2=res.theta2_deg,
                    seconds=dt,
                    cpu_seconds=dc,
                    message=res.message,
                )
                rows[method].append(r)
                if verbose:
                    err = "" if r.mm is None else f"{r.mm - r.true_mm:+7.2f} mm"
                    e1 = (
                        ""
                        if r.t1 is None or r.t2 is None
                        else f"{r.t1 - r.true_t1:+6.2f} {r.t2 - r.true_t2:+6.2f} deg"
                    )
                    print(
                        f"{'refine' if refine else 'paper':6s} {res.image:14s} {r.terrain:9s} "
                        f"z0 {r.true_mm:6.2f} {r.status:10s} {err} {e1} {r.message}",
                        file=sys.stderr,
                    )
    return rows


def summarise(rows: list[Row]) -> dict[str, float]:
    """The table's numbers for one mode on one preset (``sinkjax.metrics``: see its RULE)."""
    n = len(rows)
    status = [r.status for r in rows]
    measured = sm.measured(status)
    contact = np.array([r.contact for r in rows], dtype=bool)
    true_mm = np.array([r.true_mm for r in rows])
    deep = contact & (true_mm > SHALLOW_MM)
    shallow = contact & ~deep
    rel = sm.relative_error_pct(true_mm, [r.mm for r in rows], status)
    dz = sm.signed_error(true_mm, [r.mm for r in rows], status)
    d1 = sm.signed_error([r.true_t1 for r in rows], [r.t1 for r in rows], status)
    d2 = sm.signed_error([r.true_t2 for r in rows], [r.t2 for r in rows], status)
    mixups = measured & ((np.array(status) == sj.Status.OK.value) != contact)
    # The first frame pays the jit compile of Eqs. 1-3; later ones only new padding buckets.
    timed = rows[1:] if n > 1 else rows
    times = np.array([r.seconds for r in timed])
    cpu = np.array([r.cpu_seconds for r in timed])
    return {
        "frames": n,
        "deep": sm.count(rel[deep]),
        "deep_all": int(deep.sum()),
        "rel_med": sm.median(rel[deep]),
        "rel_p90": sm.percentile(rel[deep], 90),
        "t1_med": sm.median(np.abs(d1[deep])),
        "t1_p90": sm.percentile(np.abs(d1[deep]), 90),
        "t2_med": sm.median(np.abs(d2[deep])),
        "t2_p90": sm.percentile(np.abs(d2[deep]), 90),
        "z_bias": sm.median(dz[deep]),
        "t1_bias": sm.median(d1[deep]),
        "t2_bias": sm.median(d2[deep]),
        "shallow_abs_med": sm.median(np.abs(dz[shallow])),
        "failed": sm.failed_pct(status),
        "mixups": 100 * int(mixups.sum()) / n,
        "ms": 1000 * float(times.mean()),
        "cpu_ms": 1000 * float(cpu.mean()),
    }


Results = dict[tuple[str, str], dict[str, float]]  # (method, preset) -> summary


def table(results: list[dict]) -> str:
    lines = [
        "| method | preset | frames | z0 > 5 mm (measured / all) | median rel. sinkage err | p90 | "
        "median abs θ1 err (deg) | p90 | median abs θ2 err (deg) | p90 | "
        "median abs err z0 <= 5 mm (mm) | failed | contact mix-ups | ms/frame (wall) | "
        "ms/frame (CPU) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for res in results:
        method, preset, s = res["method"], res["preset"], _nan(res["summary"])
        lines.append(
            f"| {method} | {preset} | {s['frames']} | {s['deep']} / {s['deep_all']} | "
            f"{s['rel_med']:.2f} % | {s['rel_p90']:.2f} % | "
            f"{s['t1_med']:.2f} | {s['t1_p90']:.2f} | {s['t2_med']:.2f} | {s['t2_p90']:.2f} | "
            f"{s['shallow_abs_med']:.2f} | {s['failed']:.1f} % | {s['mixups']:.1f} % | "
            f"{s['ms']:.1f} | {s['cpu_ms']:.1f} |"
        )
    return "\n".join(lines)


def bias_table(results: list[dict]) -> str:
    lines = [
        "| method | preset | median signed z0 err (mm) | median signed θ1 err (deg) | "
        "median signed θ2 err (deg) |",
        "|---|---|---|---|---|",
    ]
    for res in results:
        method, preset, s = res["method"], res["preset"], _nan(res["summary"])
        lines.append(
            f"| {method} | {preset} | {s['z_bias']:+.3f} | {s['t1_bias']:+.2f} | "
            f"{s['t2_bias']:+.2f} |"
        )
    return "\n".join(lines)


def _nan(summary: dict) -> dict:
    """A summary read back from JSON: null (a statistic over no frames) as NaN."""
    return {k: math.nan if v is None else v for k, v in summary.items()}


def verdict(s: dict[str, float]) -> str:
    """Whether one summary meets the targets, and by how much it misses if not."""
    checks = [
        ("median rel. sinkage err", s["rel_med"], TARGET_REL_PCT, "%"),
        ("median θ1 err", s["t1_med"], TARGET_DEG, "deg"),
        ("median θ2 err", s["t2_med"], TARGET_DEG, "deg"),
        ("failed", s["failed"], TARGET_FAILED_PCT, "%"),
    ]
    misses = [
        f"{name} {value:.2f} {unit} > {limit:g} {unit} (by {value - limit:.2f} {unit})"
        for name, value, limit, unit in checks
        if not value <= limit
    ]
    if misses:
        return "MISSES: " + "; ".join(misses)
    return "meets it (" + ", ".join(f"{n} {v:.2f} {u} <= {lim:g}" for n, v, lim, u in checks) + ")"


def write_frames(path: pathlib.Path, per_preset: dict[str, dict[str, list[Row]]]) -> None:
    """Every frame of every mode and preset as CSV (one row per frame and mode)."""
    fields = [f.name for f in dataclasses.fields(Row)]
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=fields, lineterminator="\n")
        w.writeheader()
        for rows in per_preset.values():
            for method_rows in rows.values():
                w.writerows(dataclasses.asdict(r) for r in method_rows)


def report(data: dict) -> str:
    """The Markdown report from the saved JSON."""
    n, results = data["n"], data["results"]
    verdicts = [
        f"- {r['method']} on clean: {verdict(_nan(r['summary']))}"
        for r in results
        if r["preset"] == "clean"
    ]
    return (
        "# Classic pipeline accuracy on synthetic frames (640x480)\n\n"
        f"`experiments/classic_accuracy.py --n {n} --seed {data['seed']}`: "
        f"{math.ceil(n / FRAMES_PER_RECORDING)} recordings of up to {FRAMES_PER_RECORDING} "
        "frames per preset (one rig each, all terrain kinds, every third travelling left); both "
        "modes run on the same frames. Sinkage and angle errors over the frames with true "
        f"contact and z0 > 5 mm; {sm.RULE}; z0 > 5 mm (measured / all) counts the frames these "
        "errors are over; mix-up = ok vs no_contact disagreeing with the truth. ms/frame: mean "
        "wall and process-CPU time of `estimate_classic` per 640x480 frame (first call "
        "excluded: jit compile); wall time depends on machine load, CPU time less.\n\n"
        f"Target for the paper's method on clean: median rel. sinkage err <= "
        f"{TARGET_REL_PCT:g} %, median θ errors <= {TARGET_DEG:g} deg, <= "
        f"{TARGET_FAILED_PCT:g} % failed.\n\n"
        + "\n".join(verdicts)
        + "\n\n"
        + table(results)
        + "\n\nBias (median signed error, estimate - truth, same frames):\n\n"
        + bias_table(results)
        + "\n\n"
        + NOTES
    )


NOTES = """\
What the two modes do (same clean-up and rim search):

- **classic (paper)**, `estimate_classic(image, rig)`, the default and `sinkjax estimate --method
  classic`: binary image -> dilation, erosion, area filtering, enclosed holes filled -> external
  outline at integer pixel centres -> 3-D Hough rim (inner envelope, least-squares polish) ->
  boundary = outline points closer to O than r - margin -> Eq. 1 as plain least squares -> A and
  B = the boundary's extreme points -> Eqs. 2-3. The margin (4 x the rim outline's scatter, at
  least 0.75 px, at most 3 px; about 1.3-1.4 px here) keeps the rim's pixel staircase between
  lugs out of the boundary. It is also why this mode's angles are biased low: A and B are the
  last boundary points before that margin, not where the soil meets the rim, and at the shallow
  angle between soil and rim a margin of m px moves them along the boundary by about
  m cot(θ) / r rad (0.5-1.2 deg per px for r = 130-200 px and θ = 20-30 deg). The sinkage
  itself is nearly unbiased: rim and soil outline points both sit about half a pixel inside
  their edges, and the two half pixels cancel in z0 = r - |b| / sqrt(k^2 + 1). On "full" (blur
  up to 1 px, JPEG, shadows, highlights) they cancel less well: the hard thresholds cut the
  wheel/background edge deeper than the wheel/soil edge, so z0 comes out short by a fraction of
  a pixel; and lightening holes cut open by the soil, left open, can read as boundary.
  Contact shallower than about the margin reads as no contact.
- **classic + sub-pixel refinement**, `estimate_classic(image, rig, refine=True)`: the same, plus
  lightening holes cut open by the soil filled from the intact holes' pattern, edges located
  to sub-pixel precision on the colour profile and the rim refitted there, boundary points
  weighted by their x-extent in Eq. 1, A and B carried along the boundary's end direction onto
  the rim, and a loud `fit_failed` when the outline dips inside the rim above O.
"""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=120, help="frames per preset (default 120)")
    p.add_argument("--quick", action="store_true", help="30 frames per preset")
    p.add_argument("--seed", type=int, default=SEED)
    p.add_argument("--presets", default="clean,full", help="comma-separated presets")
    p.add_argument(
        "--out", type=pathlib.Path, default=DEFAULT_OUT, help="Markdown report (+ .json, .csv)"
    )
    p.add_argument("-v", "--verbose", action="store_true", help="one line per frame on stderr")
    args = p.parse_args(argv)
    n = 30 if args.quick else args.n
    per_preset = {
        preset: run_preset(preset, n, args.seed, args.verbose) for preset in args.presets.split(",")
    }
    results = [
        {"method": method, "preset": preset, "summary": summarise(rows[method])}
        for method in METHODS
        for preset, rows in per_preset.items()
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_frames(args.out.with_suffix(".csv"), per_preset)
    data = {"n": n, "seed": args.seed, "results": results}
    json_path = args.out.with_suffix(".json")
    runs.write_json(json_path, data)
    text = report(json.loads(json_path.read_text(encoding="utf-8")))
    args.out.write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
