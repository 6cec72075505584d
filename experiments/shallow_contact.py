"""Shallow contact (issue 14, item 2): sinkage of 0.5-2 px measured against the recording's rim.

Renders recordings of the ``full`` preset (lugs, holes, shadows, JPEG, noise) at two image sizes,
each a fixed camera set-up whose frames have a true sinkage drawn uniformly in 0.5-2 px (most
frames), some in 2-10 px, and some with no contact at all (the soil clears the rim). Every
recording goes through :class:`sinkjax.soft.batch.SoftRecording` on its own, as the CLI runs it
(the recording's rim from its first frames, then every frame measured with it). Reported per
band of true sinkage: the fraction measured ``ok``, the median absolute sinkage error (px and mm),
the coverage of +-1.96 sigma, and on the no-contact frames how many were wrongly given a contact.

The method was developed on seed 14; the reported numbers use seed 1402 (not looked at before).

    python experiments/shallow_contact.py                 # 6 recordings x 16 frames, seed 1402
    python experiments/shallow_contact.py --seed 14 --quick
    python experiments/shallow_contact.py --seed 14 --tilt 0.4  # sloping ground (mostly no contact)
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from sinkjax import FrameResult, Status, synth as S
from sinkjax.soft.batch import SoftRecording
from sinkjax.synth.presets import (
    TERRAINS,
    _ok_contact,
    _terrain_features,
    camera_setup,
    with_terrain,
)
from sinkjax.synth.recording import frame_seed
from sinkjax.synth.scene import Scene

RESULTS = Path(__file__).parent / "results"
EVAL_SEED = 1402
SIZES = ((640, 480), (800, 600))
SHALLOW_PX = (0.5, 2.0)
DEEP_PX = (2.0, 10.0)
BANDS = (("none", 0.0, 0.0), ("0.5-1 px", 0.5, 1.0), ("1-2 px", 1.0, 2.0), ("2-10 px", 2.0, 10.0))


def contact_scene(rng: np.random.Generator, base: Scene, kind: str, z0_px: float) -> Scene | None:
    """``base`` with a terrain of ``kind`` whose true sinkage is ``z0_px`` (None: none found)."""
    r, cy = base.radius_px, base.centre_y_px
    for attempt in range(30):
        feats = _terrain_features(rng, kind, r, z0_px) if attempt < 20 else {}
        scene = replace(
            base,
            terrain=kind if feats or kind == "flat" else "flat",
            phase_rad=float(rng.uniform(0, 2 * np.pi)),
            soil_level_px=cy + r - z0_px,
            **feats,  # type: ignore[arg-type]
        )
        # Lowering the surface by d lowers z0 by about d: a few Newton steps on the level.
        for _ in range(8):
            t = S.true_geometry(scene)
            step = t.sinkage_px - z0_px if t.contact else -max(0.5, z0_px)
            scene = replace(scene, soil_level_px=scene.soil_level_px + step)
            if abs(step) < 1e-4:
                break
        t = S.true_geometry(scene)
        if t.contact and abs(t.sinkage_px - z0_px) < 0.01 and _ok_contact(scene):
            return scene
    return None


def recording(
    rng: np.random.Generator, width: int, height: int, n_frames: int, tilt: float = 0.0
) -> list[Scene]:
    """One camera set-up; frames: 1/8 no contact, 1/4 deeper (2-10 px), the rest 0.5-2 px.
    ``tilt`` > 0: the ground slopes, dy/dx drawn per recording in +-tilt; the frames without
    contact, and those whose contact could not be drawn on the slope, stay on level ground."""
    level = base = camera_setup(rng, width, height, "full")
    if tilt > 0:
        base = replace(base, tilt=float(rng.uniform(-tilt, tilt)))
    n_none = max(1, n_frames // 8)
    n_deep = max(1, n_frames // 4)
    depths = [0.0] * n_none + list(rng.uniform(*DEEP_PX, n_deep))
    depths += list(rng.uniform(*SHALLOW_PX, n_frames - len(depths)))
    rng.shuffle(depths)
    scenes = []
    for i, z0 in enumerate(depths):
        kind = TERRAINS[i % len(TERRAINS)]
        scene = None if z0 == 0.0 else contact_scene(rng, base, kind, z0)
        if scene is None:
            scene = with_terrain(rng, level, kind, contact=False)
        scenes.append(scene)
    return scenes


def _render(scenes: list[Scene], key: int, cache: Path | None) -> list:
    # Rendering dominates a rerun while developing: keep the frames (and truth) if asked.
    path = None if cache is None else cache / f"shallow_{key}_{len(scenes)}.pkl"
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    rendered = [S.render(s, seed=frame_seed(key, i)) for i, s in enumerate(scenes)]
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(rendered))
    return rendered


def run(
    seed: int, n_rec: int, n_frames: int, cache: Path | None = None, tilt: float = 0.0
) -> list[dict]:
    rng = np.random.default_rng(seed)
    rows: list[dict] = []
    for rec in range(n_rec):
        width, height = SIZES[rec % len(SIZES)]
        scenes = recording(rng, width, height, n_frames, tilt)
        rig = S.rig_for(scenes[0])
        key = seed * 1000 + rec + (round(1000 * tilt) * 100 if tilt > 0 else 0)
        rendered = _render(scenes, key, cache)
        names = [f"rec{rec}_{i:02d}" for i in range(n_frames)]
        t0 = time.perf_counter()
        results = SoftRecording()([im for im, _ in rendered], rig, names)
        print(
            f"recording {rec} ({width}x{height}, r {scenes[0].radius_px:.0f} px): "
            f"{time.perf_counter() - t0:.1f} s",
            flush=True,
        )
        for (_, t), res, scene in zip(rendered, results, scenes, strict=True):
            rows.append(_row(rec, width, scene, t, res))
    return rows


def _row(rec: int, width: int, scene: Scene, t: S.Truth, res: FrameResult) -> dict:
    px_per_mm = scene.radius_px / scene.wheel_radius_mm
    has = res.sinkage_mm is not None
    return {
        "recording": rec,
        "width": width,
        "radius_px": scene.radius_px,
        "terrain": scene.terrain,
        "true_px": t.sinkage_px if t.contact else 0.0,
        "true_mm": t.sinkage_mm if t.contact else 0.0,
        "status": str(res.status),
        "sinkage_mm": res.sinkage_mm,
        "sinkage_std_mm": res.sinkage_std_mm,
        "sinkage_px": res.sinkage_mm * px_per_mm if has else None,
        "message": res.message,
    }


def summarise(rows: list[dict]) -> dict:
    out: dict = {}
    for name, lo, hi in BANDS:
        sel = [
            r
            for r in rows
            if (r["true_px"] == 0.0 if name == "none" else lo <= r["true_px"] < hi + 1e-9)
        ]
        ok = [r for r in sel if r["status"] == Status.OK]
        measured = [r for r in sel if r["status"] in (Status.OK, Status.NO_CONTACT)]
        err_px = np.array([abs(r["sinkage_px"] - r["true_px"]) for r in ok])
        err_mm = np.array([abs(r["sinkage_mm"] - r["true_mm"]) for r in ok])
        with_std = [r for r in measured if r["sinkage_std_mm"] is not None]
        covered = [
            abs(r["sinkage_mm"] - r["true_mm"]) <= 1.96 * r["sinkage_std_mm"] for r in with_std
        ]
        statuses: dict[str, int] = {}
        for r in sel:
            statuses[r["status"]] = statuses.get(r["status"], 0) + 1
        out[name] = {
            "frames": len(sel),
            "ok_fraction": len(ok) / len(sel) if sel else None,
            "median_abs_error_px": float(np.median(err_px)) if len(ok) else None,
            "p90_abs_error_px": float(np.percentile(err_px, 90)) if len(ok) else None,
            "median_abs_error_mm": float(np.median(err_mm)) if len(ok) else None,
            "coverage_1.96": float(np.mean(covered)) if covered else None,
            "statuses": statuses,
        }
    return out


def _fmt(v: float | None, nd: int = 3) -> str:
    return "-" if v is None else f"{v:.{nd}f}"


def write(
    rows: list[dict], summary: dict, seed: int, args: argparse.Namespace, secs: float
) -> None:
    RESULTS.mkdir(exist_ok=True)
    tag = (
        ""
        if seed == EVAL_SEED and not args.quick and not args.tilt
        else f"_seed{seed}{'_quick' if args.quick else ''}"
    ) + (f"_tilt{args.tilt:g}" if args.tilt else "")
    payload = {
        "seed": seed,
        "recordings": args.recordings,
        "frames": args.frames,
        "summary": summary,
        "rows": rows,
    }
    (RESULTS / f"shallow_contact{tag}.json").write_text(json.dumps(payload, indent=1))
    lines = [
        "# Shallow contact: sinkage of 0.5-2 px against the recording's rim",
        "",
        f"Generated by `python experiments/shallow_contact.py --seed {seed}"
        f"{' --quick' if args.quick else ''}{f' --tilt {args.tilt:g}' if args.tilt else ''}` "
        f"in {secs:.0f} s: {args.recordings} recordings x {args.frames} frames of the `full` preset"
        f"{f' on ground sloping by up to {args.tilt:g} (dy/dx)' if args.tilt else ''}"
        f" at {' and '.join(f'{w}x{h}' for w, h in SIZES)}"
        ", each through `SoftRecording` (recording rim on) on its own. Developed on seed 14; "
        f"seed {EVAL_SEED} is the held-out one.",
        "",
        "| true sinkage | frames | ok | median abs err px | p90 abs err px | median abs err mm "
        "| coverage ±1.96σ | statuses |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, s in summary.items():
        st = ", ".join(f"{k} {v}" for k, v in sorted(s["statuses"].items()))
        lines.append(
            f"| {name} | {s['frames']} | {_fmt(s['ok_fraction'], 2)} | "
            f"{_fmt(s['median_abs_error_px'])} | {_fmt(s['p90_abs_error_px'])} | "
            f"{_fmt(s['median_abs_error_mm'])} | {_fmt(s['coverage_1.96'], 2)} | {st} |"
        )
    none = summary["none"]
    fc = 1.0 - none["statuses"].get("no_contact", 0) / none["frames"] if none["frames"] else None
    lines += [
        "",
        "False contact on the true no-contact frames (any status but `no_contact`): "
        f"{_fmt(fc, 2)}. Coverage counts `ok` and `no_contact` rows (a `no_contact` row reports 0 "
        "with the sigma of the sinkage it could hide).",
        "",
    ]
    (RESULTS / f"shallow_contact{tag}.md").write_text("\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=EVAL_SEED)
    ap.add_argument("--recordings", type=int, default=6)
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--quick", action="store_true", help="2 recordings x 12 frames")
    ap.add_argument("--cache", type=Path, default=None, help="folder to keep rendered frames in")
    ap.add_argument(
        "--tilt", type=float, default=0.0, help="ground slope dy/dx drawn per recording in +-T"
    )
    args = ap.parse_args()
    if args.quick:
        args.recordings, args.frames = 2, 12
    t0 = time.perf_counter()
    rows = run(args.seed, args.recordings, args.frames, args.cache, args.tilt)
    summary = summarise(rows)
    write(rows, summary, args.seed, args, time.perf_counter() - t0)
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
