"""Shared pieces of the paper-reproduction experiments (``paper_*.py``, ``exp_*.py``, ``run_all``).

- :class:`Setup`: quick or full, image size, output and cache folders, seed; ``parse_args``.
- :func:`paper_scene`: ONE synthetic camera set-up modelled on the paper's rig (R = 140 mm, 28 lugs
  15 mm high, a single lamp with its cast shadow), so every experiment shares one confidence
  rectangle and the soft method compiles once per image size.
- The soil model: Bekker's static sinkage for the paper's Table 1 soil, a slip-sinkage factor,
  and slip bulldozing (a pile ahead of the wheel, a rut behind it) as :class:`~sinkjax.synth.Scene`
  terrain fields.
- :func:`measure`: the classic (paper) and soft methods on rendered frames -> :class:`Record` rows,
  saved as CSV in the cache folder (``exp_uncertainty`` pools them).
- Error statistics, Markdown and figure helpers.

Units: millimetres for sinkage, degrees for angles, pixels only inside scene construction.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sinkjax.rig import Rig
from sinkjax import synth as S

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
QUICK_RESULTS = RESULTS / "quick"
CACHE = HERE / "_cache" / "paper_experiments"

# ----------------------------------------------------------------------------- the paper's numbers

PAPER_SLIPS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)
# Tables 2 and 3 of the paper, copied: relative errors (%) of sinkage (REDS), entry angle (REEA)
# and exit angle (REDA) per slip ratio, 30 N and 90 N vertical load.
PAPER_TABLES: dict[int, dict[str, tuple[float, ...]]] = {
    30: {
        "sinkage": (2.54, 0.27, 2.29, 2.13, 1.35, 4.03, 2.89, 8.70),
        "theta1": (19.74, 11.81, 1.14, 3.47, 4.06, 0.18, 2.44, 1.84),
        "theta2": (4.83, 2.33, 1.09, 0.42, 0.44, 1.61, 1.60, 1.15),
    },
    90: {
        "sinkage": (2.70, 0.48, 1.76, 3.33, 5.75, 4.10, 9.13, 2.48),
        "theta1": (0.73, 3.61, 2.53, 0.67, 0.36, 3.65, 2.93, 2.35),
        "theta2": (3.14, 4.11, 2.75, 1.20, 0.47, 1.70, 3.77, 3.82),
    },
}
# The paper's claims: ~10 % sinkage and ~5 % angle relative error above 5 mm sinkage.
PAPER_CLAIM_SINKAGE_PCT = 10.0
PAPER_CLAIM_ANGLE_PCT = 5.0
PAPER_SHALLOW_MM = 5.0

# Table 1 soil and the paper's wheel (radius 140 mm, width 150 mm).
SOIL_KC = -20.7e3  # Pa / m^(n+1)
SOIL_KPHI = 1594.8e3  # Pa / m^n
SOIL_N = 0.79
WHEEL_RADIUS_MM = 140.0
WHEEL_WIDTH_MM = 150.0
# Bekker's formula is for a smooth rigid rim; the paper's wheel has 28 lugs 15 mm high, which dig
# it in deeper. We ASSUME the lugged wheel's static rim sinkage is twice the smooth-rim value
# (an assumption, not a measurement: it puts 30 N at 4-11 mm and 90 N at 10-26 mm over slips
# 0-0.7, the shallow and deep ranges the paper contrasts).
LUG_SINKAGE_FACTOR = 2.0

QUANTITIES = ("sinkage", "theta1", "theta2")
LABELS = {"sinkage": "sinkage z0", "theta1": "entry angle θ1", "theta2": "exit angle θ2"}
UNITS = {"sinkage": "mm", "theta1": "deg", "theta2": "deg"}
METHOD_COLOURS = {
    "paper": "#555555",
    "classic": "#4c72b0",
    "soft": "#dd8452",
    "calibrated": "#55a868",
    "sensor": "#8172b2",
    "truth": "#000000",
}


def bekker_static_sinkage_mm(load_n: float) -> float:
    """Static sinkage (mm) of the paper's wheel on its Table 1 soil (Bekker, rigid wheel).

    z = [3 W / ((3 - n) b (k_c / b + k_phi) sqrt(D))]^(2 / (2 n + 1)), W in N, b and D in m;
    times :data:`LUG_SINKAGE_FACTOR` for the lugs.
    """
    b = WHEEL_WIDTH_MM / 1000.0
    d = 2.0 * WHEEL_RADIUS_MM / 1000.0
    k = SOIL_KC / b + SOIL_KPHI
    z_m = (3.0 * load_n / ((3.0 - SOIL_N) * b * k * math.sqrt(d))) ** (2.0 / (2.0 * SOIL_N + 1.0))
    return 1000.0 * z_m * LUG_SINKAGE_FACTOR


def slip_sinkage_factor(slip: float) -> float:
    """Slip sinkage: z(s) = z_static (1 + s) / (1 - s / 2) (Lyasko's slip-sinkage relation)."""
    return (1.0 + slip) / (1.0 - 0.5 * slip)


def sinkage_for(load_n: float, slip: float) -> float:
    """Depth (mm) of the wheel's lowest point below the flat soil level at this load and slip."""
    return bekker_static_sinkage_mm(load_n) * slip_sinkage_factor(slip)


# ----------------------------------------------------------------------------- set-up


@dataclasses.dataclass(frozen=True)
class Setup:
    """How an experiment runs: quick (320x240, few frames) or full (640x480)."""

    quick: bool
    out_dir: Path
    cache_dir: Path
    seed: int = 2024

    @property
    def width(self) -> int:
        return 320 if self.quick else 640

    @property
    def height(self) -> int:
        return 240 if self.quick else 480

    @property
    def mode(self) -> str:
        return "quick" if self.quick else "full"

    def n(self, full: int, quick: int) -> int:
        """A count for this mode."""
        return quick if self.quick else full

    def rng(self, *key: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([self.seed, *key]))


def parse_args(
    description: str, argv: Sequence[str] | None = None, *, run_help: str | None = None
) -> tuple[Setup, argparse.Namespace]:
    """The command line every experiment script shares (``run_help``: also a ``--run`` flag)."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--quick", action="store_true", help="320x240 and few frames (a smoke run)")
    p.add_argument(
        "--out-dir",
        type=Path,
        default=None,
        help=f"where the .md and .png go (default {RESULTS.relative_to(HERE.parent)}, or "
        f"{QUICK_RESULTS.relative_to(HERE.parent)} with --quick)",
    )
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="where per-frame records (CSV) and summaries (JSON) go (default "
        f"{CACHE.relative_to(HERE.parent)}[/quick])",
    )
    p.add_argument("--seed", type=int, default=2024, help="base seed (2024)")
    if run_help:
        p.add_argument("--run", action="store_true", help=run_help)
    a = p.parse_args(argv)
    return make_setup(a.quick, a.out_dir, a.cache_dir, a.seed), a


def make_setup(
    quick: bool, out_dir: Path | None = None, cache_dir: Path | None = None, seed: int = 2024
) -> Setup:
    out = out_dir or (QUICK_RESULTS if quick else RESULTS)
    cache = cache_dir or (CACHE / "quick" if quick else CACHE)
    out.mkdir(parents=True, exist_ok=True)
    cache.mkdir(parents=True, exist_ok=True)
    return Setup(quick=quick, out_dir=out, cache_dir=cache, seed=seed)


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def machine() -> str:
    load = "/".join(f"{x:.1f}" for x in os.getloadavg())
    return (
        f"{platform.machine()}, {os.cpu_count()} CPU cores visible, load average {load} "
        f"(1/5/15 min) at the end"
    )


# ----------------------------------------------------------------------------- scenes


def _hsv(h_deg: float, s: float, v: float) -> tuple[float, float, float]:
    import colorsys

    r, g, b = colorsys.hsv_to_rgb((h_deg % 360.0) / 360.0, s, v)
    return (r, g, b)


def paper_scene(setup: Setup) -> S.Scene:
    """The experiments' camera set-up (wheel on flat soil at 10 mm sinkage).

    The paper's wheel: R = 140 mm, 28 lugs 15 mm high; a single lamp above-left with the wheel's
    cast shadow on the soil, mild sensor noise, blur and JPEG. At 640x480 the rim radius is 140 px
    (1 px = 1 mm); at 320x240 everything is halved. Every experiment varies only the terrain,
    wheel phase and lighting of this scene, so :func:`sinkjax.synth.rig_for` gives one rig.
    """
    f = setup.width / 640.0
    r = 140.0 * f
    lamp = (-0.6, -0.8)
    base = S.Scene(
        width=setup.width,
        height=setup.height,
        centre_x_px=320.0 * f,
        centre_y_px=190.0 * f,
        radius_px=r,
        wheel_radius_mm=WHEEL_RADIUS_MM,
        wheel_rgb=_hsv(44, 0.85, 0.85),
        rim_rgb=_hsv(44, 0.85, 0.68),
        rim_width_px=9.0 * f,
        lug_rgb=_hsv(45, 0.8, 0.78),
        n_lugs=28,
        lug_height_px=15.0 * f,
        lug_width_px=6.0 * f,
        hub_radius_px=20.0 * f,
        hub_rgb=_hsv(40, 0.2, 0.45),
        n_holes=6,
        hole_radius_px=14.0 * f,
        hole_ring_px=85.0 * f,
        soil_rgb=_hsv(28, 0.32, 0.60),
        soil_rgb2=_hsv(24, 0.36, 0.55),
        soil_texture=0.12,
        pebbles=int(150 * f * f),
        wall_rgb=_hsv(210, 0.05, 0.55),
        light_dir=lamp,
        shading=0.25,
        shadow_factor=0.6,
        shadow_offset_px=(-lamp[0] * 0.2 * r, -lamp[1] * 0.2 * r),
        shadow_soft_px=5.0 * f,
        noise_std=2.0,
        blur_sigma_px=0.5 * f,
        jpeg_quality=90,
    )
    return place(base, 10.0)


def px_per_mm(scene: S.Scene) -> float:
    return scene.radius_px / scene.wheel_radius_mm


def place(scene: S.Scene, depth_mm: float, **terrain: Any) -> S.Scene:
    """``scene`` with the wheel's lowest point ``depth_mm`` below the FLAT soil level, plus the
    given terrain fields (bumps, ruts, roughness; see :class:`sinkjax.synth.Scene`). The flat
    level is what the paper's displacement sensor measured sinkage from."""
    level = scene.centre_y_px + scene.radius_px - depth_mm * px_per_mm(scene)
    return dataclasses.replace(scene, soil_level_px=level, **terrain)


def half_chord_px(scene: S.Scene, depth_mm: float) -> float:
    """Half the contact chord on flat soil at this depth (px)."""
    z = depth_mm * px_per_mm(scene)
    return math.sqrt(max(2.0 * scene.radius_px * z - z * z, 1.0))


def bulldozing(
    scene: S.Scene, depth_mm: float, slip: float, *, pile: bool = True, jitter: float = 0.0
) -> dict[str, Any]:
    """Slip bulldozing as terrain fields: a pile pushed up ahead of the wheel and a rut left behind
    it, both growing with slip (pile height (0.1 + 0.4 s) z, rut depth (0.2 + 0.5 s) z for
    sinkage z). ``pile=False`` leaves the scene's Gaussian bump free for a terrain feature.
    ``jitter`` in [-1, 1] shifts the features a little (frames of one run differ)."""
    r = scene.radius_px
    z = depth_mm * px_per_mm(scene)
    half = half_chord_px(scene, depth_mm)
    out: dict[str, Any] = {
        "rut_depth_px": (0.2 + 0.5 * slip) * z,
        "rut_dx_px": -(0.5 + 0.1 * jitter) * half,
        "rut_width_px": 0.06 * r,
        "rut_side": -1.0,
    }
    if pile:
        sigma = 0.12 * r
        out |= {
            "bump_height_px": (0.1 + 0.4 * slip) * z,
            "bump_dx_px": half + (0.5 + 0.2 * jitter) * sigma,
            "bump_sigma_px": sigma,
        }
    return out


def valid_contact(scene: S.Scene) -> bool:
    """Two rim crossings, with the entry end A ahead of and the exit end B behind the wheel's
    lowest point (Eqs. 2-3 assume x_A > 0 > x_B)."""
    if S.n_rim_crossings(scene) != 2:
        return False
    t = S.true_geometry(scene)
    return t.a_px[0] > 0.02 * scene.radius_px and t.b_end_px[0] < -0.02 * scene.radius_px


# ----------------------------------------------------------------------------- measuring


@dataclasses.dataclass
class Frame:
    """One rendered frame, its truth and what the experiment varied (``tags``)."""

    name: str
    image: np.ndarray
    truth: S.Truth
    tags: dict[str, Any]


def render_frames(
    scenes: Iterable[tuple[S.Scene, dict[str, Any]]], seed: int, prefix: str
) -> list[Frame]:
    """Render (scene, tags) pairs; frame i uses seed (seed, i)."""
    out = []
    for i, (scene, tags) in enumerate(scenes):
        fseed = int(np.random.SeedSequence([seed, i]).generate_state(1)[0])
        image, truth = S.render(scene, fseed)
        out.append(Frame(f"{prefix}{i:04d}", image, truth, tags))
    return out


SOFT_BATCH = 8  # every soft call has this batch size: one compiled function per image size


def _soft(frames: Sequence[Frame], rig: Rig) -> list[Any]:
    from sinkjax.soft.estimator import estimate_batch

    rows: list[Any] = []
    for i in range(0, len(frames), SOFT_BATCH):
        chunk = frames[i : i + SOFT_BATCH]
        rows += estimate_batch(
            [f.image for f in chunk], rig, [f.name for f in chunk], pad_to=SOFT_BATCH
        )
    return rows


def _classic(frames: Sequence[Frame], rig: Rig) -> list[Any]:
    from sinkjax.classic.estimator import estimate_classic

    return [estimate_classic(f.image, rig, f.name) for f in frames]


def _fields(prefix: str, res: Any, with_std: bool) -> dict[str, Any]:
    out: dict[str, Any] = {f"{prefix}_status": res.status}
    for q, attr in (("sinkage", "sinkage_mm"), ("theta1", "theta1_deg"), ("theta2", "theta2_deg")):
        v = getattr(res, attr)
        out[f"{prefix}_{q}"] = math.nan if v is None else float(v)
        if with_std:
            sd = getattr(res, attr.replace("_mm", "_std_mm").replace("_deg", "_std_deg"))
            out[f"{prefix}_{q}_std"] = math.nan if sd is None else float(sd)
    return out


def measure(
    frames: Sequence[Frame],
    rig: Rig,
    *,
    classic: bool = True,
    soft: bool = True,
    extra_soft: dict[str, Rig] | None = None,
) -> list[dict[str, Any]]:
    """Run the methods on ``frames``: one record (flat dict) per frame.

    Keys: ``name``, the frame's tags, ``true_{sinkage,theta1,theta2}`` (mm, deg), and per method
    ``{method}_status``, ``{method}_{q}`` (NaN when not measured) and, for soft methods,
    ``{method}_{q}_std``. ``extra_soft`` maps a method name to another rig for the soft method
    (e.g. a calibrated one).
    """
    recs: list[dict[str, Any]] = []
    for f in frames:
        t = f.truth
        recs.append(
            {
                "name": f.name,
                **f.tags,
                "true_contact": t.contact,
                "true_sinkage": t.sinkage_mm,
                "true_theta1": t.theta1_deg,
                "true_theta2": t.theta2_deg,
            }
        )
    if classic:
        for rec, res in zip(recs, _classic(frames, rig), strict=True):
            rec |= _fields("classic", res, with_std=False)
    if soft:
        for rec, res in zip(recs, _soft(frames, rig), strict=True):
            rec |= _fields("soft", res, with_std=True)
    for method, other in (extra_soft or {}).items():
        for rec, res in zip(recs, _soft(frames, other), strict=True):
            rec |= _fields(method, res, with_std=True)
    return recs


def estimate_value(rec: dict[str, Any], method: str, q: str) -> float:
    """A method's value, reading a frame it did not measure (any status but ``ok``, e.g.
    ``no_contact`` or ``fit_failed``) as 0: a failed frame counts as a 100 % relative error."""
    if rec.get(f"{method}_status") != "ok":
        return 0.0
    v = float(rec[f"{method}_{q}"])
    return v if math.isfinite(v) else 0.0


def abs_error(rec: dict[str, Any], method: str, q: str) -> float:
    return abs(estimate_value(rec, method, q) - float(rec[f"true_{q}"]))


def rel_error_pct(rec: dict[str, Any], method: str, q: str) -> float:
    true = float(rec[f"true_{q}"])
    return 100.0 * abs_error(rec, method, q) / true if true > 0 else math.nan


def failed(rec: dict[str, Any], method: str) -> bool:
    return rec.get(f"{method}_status") != "ok"


def median(values: Iterable[float]) -> float:
    v = np.asarray([x for x in values if math.isfinite(x)], dtype=np.float64)
    return float(np.median(v)) if v.size else math.nan


def mean(values: Iterable[float]) -> float:
    v = np.asarray([x for x in values if math.isfinite(x)], dtype=np.float64)
    return float(np.mean(v)) if v.size else math.nan


# ----------------------------------------------------------------------------- files


def save_records(setup: Setup, name: str, recs: Sequence[dict[str, Any]]) -> Path:
    """Per-frame records as ``<cache>/<name>_frames.csv`` (union of keys, in first-seen order)."""
    keys: list[str] = []
    for r in recs:
        keys += [k for k in r if k not in keys]
    path = setup.cache_dir / f"{name}_frames.csv"
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=keys, lineterminator="\n")
        w.writeheader()
        for r in recs:
            w.writerow({k: _cell(r.get(k)) for k in keys})
    return path


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if not math.isfinite(v) else repr(round(v, 6))
    return str(v)


def load_records(path: Path) -> list[dict[str, Any]]:
    """Read a ``*_frames.csv``: numeric cells as floats (empty -> NaN), the rest as strings."""
    out = []
    with path.open(encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            rec: dict[str, Any] = {}
            for k, v in row.items():
                if k.endswith("_status") or k in ("name", "terrain", "factor", "run", "level"):
                    rec[k] = v
                elif v == "":
                    rec[k] = math.nan
                else:
                    try:
                        rec[k] = float(v)
                    except ValueError:
                        rec[k] = v
            out.append(rec)
    return out


def save_summary(setup: Setup, name: str, summary: dict[str, Any]) -> None:
    """Headline numbers for the results index (``<cache>/<name>_summary.json``)."""
    path = setup.cache_dir / f"{name}_summary.json"
    path.write_text(json.dumps(summary, indent=1, default=float) + "\n", encoding="utf-8")


def load_summary(cache_dir: Path, name: str) -> dict[str, Any] | None:
    path = cache_dir / f"{name}_summary.json"
    if not path.is_file():
        return None
    data: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    return data


def fmt(x: float | None, nd: int = 2) -> str:
    if x is None or not math.isfinite(x):
        return "—"
    return f"{x:.{nd}f}"


def md_table(headers: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def generated_line(setup: Setup, script: str, seconds: float, frames: int) -> str:
    flag = " --quick" if setup.quick else ""
    return (
        f"Generated by `python experiments/{script}{flag}` (seed {setup.seed}; {setup.width}x"
        f"{setup.height} px, rim radius {140 * setup.width / 640:.0f} px = 140 mm; {frames} "
        f"rendered frames; {seconds:.0f} s on {machine()})."
    )


def write_md(setup: Setup, name: str, text: str) -> Path:
    path = setup.out_dir / f"{name}.md"
    path.write_text(text.rstrip() + "\n", encoding="utf-8")
    return path


def figure(nrows: int = 1, ncols: int = 1, size: tuple[float, float] = (7.0, 4.5)) -> Any:
    """A matplotlib (figure, axes) pair on the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(nrows, ncols, figsize=size, squeeze=False)


def log_axis(ax: Any, which: str = "y") -> None:
    """A log axis labelled with plain numbers (0.1, 1, 10) instead of powers of ten."""
    from matplotlib.ticker import FuncFormatter

    axis = ax.yaxis if which == "y" else ax.xaxis
    (ax.set_yscale if which == "y" else ax.set_xscale)("log")
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    # Label the 2s and 5s between decades too, so a range narrower than a decade has labels.
    axis.set_minor_formatter(
        FuncFormatter(
            lambda v, _: (
                f"{v:g}" if v > 0 and round(v / 10 ** math.floor(math.log10(v))) in (2, 5) else ""
            )
        )
    )


def save_figure(setup: Setup, fig: Any, name: str) -> Path:
    import matplotlib.pyplot as plt

    path = setup.out_dir / f"{name}.png"
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def timed(fn: Callable[[Setup], dict[str, Any]], setup: Setup, name: str) -> dict[str, Any]:
    """Run one experiment, log its wall time, store its summary (with ``seconds``)."""
    t0 = time.perf_counter()
    log(f"{name}: start ({setup.mode})")
    summary = fn(setup)
    summary["seconds"] = time.perf_counter() - t0
    summary["mode"] = setup.mode
    save_summary(setup, name, summary)
    log(f"{name}: done in {summary['seconds']:.0f} s")
    return summary


def parse_md_table(text: str, first_header: str) -> list[dict[str, str]]:
    """The rows of the first Markdown table whose first header cell is ``first_header``."""
    lines = [ln.strip() for ln in text.splitlines()]
    for i, ln in enumerate(lines):
        cells = [c.strip() for c in ln.strip("|").split("|")]
        if ln.startswith("|") and cells[0] == first_header:
            rows = []
            for body in lines[i + 2 :]:
                if not body.startswith("|"):
                    break
                vals = [c.strip() for c in body.strip("|").split("|")]
                rows.append(dict(zip(cells, vals, strict=False)))
            return rows
    return []


def number(cell: str) -> float:
    """The leading number of a table cell ('1.4x' -> 1.4, '-' -> NaN)."""
    import re

    m = re.match(r"\s*(-?[0-9]+(?:\.[0-9]+)?)", cell)
    return float(m.group(1)) if m else math.nan
