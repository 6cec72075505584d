"""Light and shadow (the paper's future work): error against shadow strength, light level,
colour cast and dust, for the classic (paper's) method, the soft method, and the soft method
calibrated on 6 labelled frames of each condition.

Every condition is the shared camera set-up (``common.paper_scene``: one lamp, the wheel's cast
shadow at factor 0.6) with ONE factor changed:

- shadow: how much the cast shadow darkens the soil (factor 1 = no shadow, 0.15 = deep shadow);
- light level: exposure gain with the sensor noise and black level that come with it;
- colour cast: per-channel gains towards blue (a low sun / sky fill), strength 0-0.4;
- dust: the lower wheel face blended towards the soil colour (fraction up to 0.9).

Test frames: flat terrain with slip bulldozing, sinkage 6-30 mm. ``soft-calibrated``: the soft
method with the rig from ``sinkjax.calibrate`` on 6 OTHER frames of the same
condition (labelled with their true z0, θ1, θ2), scored on the same test frames.

    python experiments/exp_lighting.py [--quick] [--out-dir DIR] [--cache-dir DIR]
"""

from __future__ import annotations

import colorsys
import dataclasses
import math
import sys
import time
from typing import Any

import numpy as np
from common import paper, records, report, runs, scenery

from sinkjax import metrics as sm, synth as S

NAME = "exp_lighting"
N_LABELLED = 6
CAL_STEPS = 20
CAST_HUE_DEG = 220.0
METHODS = ("classic", "soft", "calibrated")
# factor -> (axis label, levels (full), levels (quick)); the first level is the base scene.
FACTORS: dict[str, tuple[str, tuple[float, ...], tuple[float, ...]]] = {
    "shadow": ("shadow strength, 1 - shadow factor", (0.4, 0.0, 0.65, 0.85), (0.4, 0.85)),
    "light": (
        "exposure gain (noise and black level grow as it drops)",
        (1.0, 0.45, 0.25, 0.12),
        (1.0, 0.12),
    ),
    "cast": ("colour cast strength (towards blue)", (0.0, 0.2, 0.4), (0.0, 0.4)),
    "dust": ("dust on the lower wheel face (max. blend)", (0.0, 0.4, 0.7, 0.9), (0.0, 0.9)),
}


TITLES = {
    "shadow": "Cast shadow on the soil",
    "light": "Light level",
    "cast": "Colour cast",
    "dust": "Dust on the wheel",
}


def condition(base: S.Scene, factor: str, level: float) -> S.Scene:
    """``base`` with one lighting factor set to ``level``."""
    if factor == "shadow":
        return dataclasses.replace(base, shadow_factor=1.0 - level)
    if factor == "light":
        # Noise (8-bit units) and black level rise as the exposure drops (a lower-light frame).
        dark = (1.0 - level) / (1.0 - 0.12)
        return dataclasses.replace(
            base, gain=level, noise_std=2.0 + 6.0 * dark, black_level=14.0 * dark
        )
    if factor == "cast":
        c = np.asarray(colorsys.hsv_to_rgb(CAST_HUE_DEG / 360.0, 1.0, 1.0))
        d = 2 * c - 1
        gains = 1.0 + level * (d - d.mean())
        return dataclasses.replace(
            base, cast_rgb=(float(gains[0]), float(gains[1]), float(gains[2]))
        )
    if factor == "dust":
        return dataclasses.replace(base, dust=level, dust_top_frac=0.05)
    raise ValueError(f"unknown factor {factor!r}")


def _frames(
    setup: runs.Setup, scene: S.Scene, n: int, key: tuple[int, ...], tags: dict[str, Any]
) -> list[records.Frame]:
    rng = setup.rng(*key)
    scenes = []
    for _ in range(n):
        depth = float(rng.uniform(6.0, 30.0))
        slip = float(rng.uniform(0.0, 0.7))
        sc = scenery.place(
            scene,
            depth,
            phase_rad=float(rng.uniform(0, 2 * math.pi)),
            **scenery.bulldozing(scene, depth, slip, jitter=float(rng.uniform(-1, 1))),
        )
        if not scenery.valid_contact(sc):
            raise RuntimeError(f"{tags}: no clean two-point contact at {depth:.1f} mm")
        scenes.append((sc, tags | {"slip": slip, "sensor": depth}))
    seed = int(np.random.SeedSequence([setup.seed, *key]).generate_state(1)[0])
    return records.render_frames(scenes, seed, "light_")


def _calibrated_rig(
    setup: runs.Setup, labelled: list[records.Frame], rig: Any
) -> tuple[Any, dict[str, Any]]:
    from sinkjax.calibration import GRID, LabelledFrames, calibrate

    frames = LabelledFrames(
        images=np.stack([f.image for f in labelled]),
        targets=np.asarray(
            [[f.truth.sinkage_mm, f.truth.theta1_deg, f.truth.theta2_deg] for f in labelled]
        ),
        names=tuple(f.name for f in labelled),
    )
    # --quick (a smoke test): the grid's corners only (16 points, not 81) and no descent, so
    # that no gradient is compiled (test_calibration covers the descent).
    steps = setup.n(CAL_STEPS, 0)
    grid = {k: (v[0], v[-1]) for k, v in GRID.items()} if setup.quick else GRID
    res = calibrate(frames, rig, steps=steps, patience=max(2, steps // 2), grid=grid)
    info = {
        "steps": len(res.losses) - 1,
        "best_step": res.best_step,
        "loss_before": res.losses[0],
        "loss_after": res.losses[res.best_step],
        "seconds": res.seconds,
    }
    return res.rig, info


def run(setup: runs.Setup) -> dict[str, Any]:
    t0 = time.perf_counter()
    base = scenery.paper_scene(setup)
    rig = S.rig_for(base)
    per_cond = setup.n(16, 2)
    # Distinct conditions: the base scene once, then every other level of every factor.
    conds: list[tuple[str, float]] = [("base", 0.0)]
    for factor, (_, full, quick) in FACTORS.items():
        conds += [(factor, lv) for lv in (quick if setup.quick else full)[1:]]
    recs: list[dict[str, Any]] = []
    cal_info: dict[str, dict[str, Any]] = {}
    n_rendered = 0
    for ci, (factor, level) in enumerate(conds):
        scene = base if factor == "base" else condition(base, factor, level)
        label = f"{factor} {level:g}"
        runs.log(f"{NAME}: {label}: calibrating on {N_LABELLED} frames, measuring {per_cond}")
        tags = {"factor": factor, "level": level}
        labelled = _frames(setup, scene, N_LABELLED, (4, ci, 0), tags)
        test = _frames(setup, scene, per_cond, (4, ci, 1), tags)
        n_rendered += len(labelled) + len(test)
        cal_rig, cal_info[label] = _calibrated_rig(setup, labelled, rig)
        rr = records.measure(test, rig, extra_soft={"calibrated": cal_rig})
        for rec in rr:
            rec["experiment"] = NAME
        recs += rr
    info = {"seconds": time.perf_counter() - t0, "frames": n_rendered, "calibration": cal_info}
    records.save(setup, NAME, recs, info | {"per_condition": per_cond})
    return write_report(setup)


def write_report(setup: runs.Setup) -> dict[str, Any]:
    """The Markdown report, figure and summary from the saved records (``run``)."""
    recs, meta = records.load(setup, NAME)
    cal_info, per_cond, n_rendered = meta["calibration"], meta["per_condition"], meta["frames"]

    def cell(factor: str, level: float, m: str, stat: str) -> float:
        rr = [r for r in recs if _matches(r, factor, level, setup)]
        if stat == "rel":
            return sm.median(records.rel_errors_pct(rr, m, "sinkage"))
        if stat == "angle":
            both = records.abs_errors(rr, m, "theta1") + records.abs_errors(rr, m, "theta2")
            return sm.median(0.5 * both)
        return float(records.n_failed(rr, m))

    rows, curves = [], {}
    summary: dict[str, Any] = {"frames": n_rendered}
    for factor, (_, full, quick) in FACTORS.items():
        levels = quick if setup.quick else full
        curves[factor] = {
            (m, stat): [cell(factor, lv, m, stat) for lv in levels]
            for m in METHODS
            for stat in ("rel", "angle", "failed")
        }
        for i, lv in enumerate(levels):
            label = "base" if i == 0 else f"{factor} {lv:g}"
            info = cal_info["base 0" if i == 0 else label]
            rows.append(
                [factor, f"{lv:g}" + (" (base)" if i == 0 else "")]
                + [report.fmt(curves[factor][(m, "rel")][i]) for m in METHODS]
                + [report.fmt(curves[factor][(m, "angle")][i]) for m in METHODS]
                + ["/".join(f"{curves[factor][(m, 'failed')][i]:.0f}" for m in METHODS)]
                + [f"{info['loss_before']:.3g} → {info['loss_after']:.3g}"]
            )
        # The level where the soft method does worst: most failed frames, then largest error.
        soft_key = [
            (f, -1.0 if math.isnan(e) else e)
            for f, e in zip(
                curves[factor][("soft", "failed")], curves[factor][("soft", "rel")], strict=True
            )
        ]
        worst = max(range(len(levels)), key=lambda i: soft_key[i])
        for m in METHODS:
            summary[f"{factor}_worst_{m}_rel_pct"] = curves[factor][(m, "rel")][worst]
            summary[f"{factor}_worst_{m}_failed"] = curves[factor][(m, "failed")][worst]
            summary[f"{factor}_max_{m}_rel_pct"] = sm.maximum(curves[factor][(m, "rel")])
            summary[f"{factor}_max_{m}_failed"] = max(curves[factor][(m, "failed")])
        summary[f"{factor}_worst_level"] = levels[worst]
    for m in METHODS:
        summary[f"all_{m}_rel_pct"] = sm.median(records.rel_errors_pct(recs, m, "sinkage"))
        summary[f"all_{m}_failed"] = records.n_failed(recs, m)
    summary["test_frames"] = len(recs)
    _figure(setup, curves)
    text = "\n\n".join(
        [
            "# Light and shadow (the paper's future work)",
            report.generated_line(setup, f"{NAME}.py", meta["seconds"], n_rendered),
            "One factor at a time changed from the shared camera set-up (base: one lamp, cast "
            "shadow factor 0.6, gain 1, no cast, no dust). Per condition "
            f"{per_cond} test frames (flat terrain with slip bulldozing, 6-30 mm) and "
            f"{N_LABELLED} other labelled frames that `calibrate` tunes the soft method's "
            "segmentation on ("
            + (f"{CAL_STEPS} Adam steps at most" if not setup.quick else "its grid search alone")
            + f"). Medians over the test frames; {sm.RULE}.",
            report.md_table(
                ["factor", "level"]
                + [f"rel. z0 err {m} (%)" for m in METHODS]
                + [f"abs. angle err {m} (°)" for m in METHODS]
                + ["failed classic/soft/cal.", "calibration loss"],
                rows,
            ),
            "Over all "
            f"{len(recs)} test frames (median relative sinkage error): classic "
            f"{report.fmt(summary['all_classic_rel_pct'])} %, soft "
            f"{report.fmt(summary['all_soft_rel_pct'])} %, soft-calibrated "
            f"{report.fmt(summary['all_calibrated_rel_pct'])} %; failed frames "
            f"{summary['all_classic_failed']} / {summary['all_soft_failed']} / "
            f"{summary['all_calibrated_failed']}.",
            f"![light and shadow]({NAME}.png)",
        ]
    )
    report.write_md(setup, NAME, text)
    return summary


def _matches(rec: dict[str, Any], factor: str, level: float, setup: runs.Setup) -> bool:
    first = (FACTORS[factor][2] if setup.quick else FACTORS[factor][1])[0]
    if math.isclose(level, first):
        return rec["factor"] == "base"
    return rec["factor"] == factor and math.isclose(float(rec["level"]), level)


def _figure(setup: runs.Setup, curves: dict[str, dict[tuple[str, str], list[float]]]) -> None:
    fig, axes = report.figure(2, len(FACTORS), (16.0, 7.5))
    styles = {"classic": "o-", "soft": "s-", "calibrated": "D--"}
    names = {"classic": "classic (paper's method)", "soft": "soft", "calibrated": "soft-calibrated"}
    for j, (factor, (axis, full, quick)) in enumerate(FACTORS.items()):
        levels = np.asarray(quick if setup.quick else full)
        order = np.argsort(levels)
        for i, (stat, ylabel) in enumerate(
            (
                ("rel", "median relative sinkage error (%)"),
                ("angle", "median |θ error| (°), mean of θ1, θ2"),
            )
        ):
            ax = axes[i, j]
            for m in METHODS:
                y = np.maximum(np.asarray(curves[factor][(m, stat)]), 1e-2)
                ax.plot(
                    levels[order],
                    y[order],
                    styles[m],
                    color=report.METHOD_COLOURS[m],
                    label=names[m],
                )
            report.log_axis(ax)
            ax.set_xlabel(axis, fontsize=8)
            ax.set_ylabel(ylabel, fontsize=8)
            ax.grid(True, which="both", alpha=0.3)
            if i == 0:
                ax.set_title(TITLES[factor])
                ax.axhline(
                    paper.PAPER_CLAIM_SINKAGE_PCT, color="k", ls=":", lw=1, label="paper: ~10 %"
                )
            if j == 0:
                ax.legend(fontsize=7)
    fig.suptitle("Error against lighting: shadow, light level, colour cast, dust (z0 6-30 mm)")
    report.save_figure(setup, fig, NAME)


def main(argv: list[str] | None = None) -> int:
    setup, _ = runs.parse_args(__doc__.splitlines()[0], argv)
    runs.timed(run, setup, NAME)
    return 0


if __name__ == "__main__":
    sys.exit(main())
