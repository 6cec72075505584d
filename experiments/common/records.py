"""Per-frame records: render frames, measure them with both methods, save and load them as CSV,
and their errors by the ONE rule of :mod:`sinkjax.metrics`.

A record is a flat dict per frame: ``name``, the frame's tags, ``true_{sinkage,theta1,theta2}``
(mm, deg) and per method ``{method}_status``, ``{method}_{q}`` (NaN when not measured) and, for
soft methods, ``{method}_{q}_std``. The reports are made from the saved CSV
(``<cache>/<name>_frames.csv``), never from another report.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

import sinkjax as sj
from sinkjax import metrics as sm, synth as S

from .runs import Setup, load_run, save_run

QUANTITIES = ("sinkage", "theta1", "theta2")


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


def _soft(frames: Sequence[Frame], rig: sj.Rig) -> list[sj.FrameResult]:
    rows: list[Any] = []
    recording = sj.SoftRecording()  # the frames are one recording: one rim
    for i in range(0, len(frames), SOFT_BATCH):
        chunk = frames[i : i + SOFT_BATCH]
        rows += recording([f.image for f in chunk], rig, [f.name for f in chunk], pad_to=SOFT_BATCH)
    return rows


def _classic(frames: Sequence[Frame], rig: sj.Rig) -> list[sj.FrameResult]:
    return [sj.estimate_classic(f.image, rig, f.name) for f in frames]


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
    rig: sj.Rig,
    *,
    classic: bool = True,
    soft: bool = True,
    extra_soft: dict[str, sj.Rig] | None = None,
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


# ----------------------------------------------------------------------------- errors


def truth(recs: Sequence[dict[str, Any]], q: str) -> np.ndarray:
    """The true ``q`` (mm or deg) of each record."""
    return np.asarray([float(r[f"true_{q}"]) for r in recs], dtype=np.float64)


def statuses(recs: Sequence[dict[str, Any]], method: str) -> list[str]:
    """``method``'s status per record (a method that did not run: failed)."""
    return [str(r.get(f"{method}_status", "")) for r in recs]


def estimates(recs: Sequence[dict[str, Any]], method: str, q: str) -> list[float]:
    return [float(r.get(f"{method}_{q}", math.nan)) for r in recs]


def values(recs: Sequence[dict[str, Any]], method: str, q: str) -> np.ndarray:
    """``method``'s measurement of ``q`` per record as :mod:`sinkjax.metrics` reads it
    (``no_contact`` 0, failed NaN)."""
    return sm.measured_values(estimates(recs, method, q), statuses(recs, method))


def signed_errors(recs: Sequence[dict[str, Any]], method: str, q: str) -> np.ndarray:
    return sm.signed_error(truth(recs, q), estimates(recs, method, q), statuses(recs, method))


def abs_errors(recs: Sequence[dict[str, Any]], method: str, q: str) -> np.ndarray:
    return sm.abs_error(truth(recs, q), estimates(recs, method, q), statuses(recs, method))


def rel_errors_pct(recs: Sequence[dict[str, Any]], method: str, q: str) -> np.ndarray:
    """The paper's REDS / REEA / REDA per record (%; NaN for failed frames and truth 0)."""
    return sm.relative_error_pct(truth(recs, q), estimates(recs, method, q), statuses(recs, method))


def n_failed(recs: Sequence[dict[str, Any]], method: str) -> int:
    return int(sm.failed(statuses(recs, method)).sum())


def n_no_contact(recs: Sequence[dict[str, Any]], method: str) -> int:
    return sum(s == sj.Status.NO_CONTACT for s in statuses(recs, method))


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


def save(setup: Setup, name: str, recs: Sequence[dict[str, Any]], info: dict[str, Any]) -> None:
    """A run's records (``<name>_frames.csv``) and what else its report needs (``info``: time,
    frames rendered, ...; ``<name>_run.json``) in the cache folder."""
    save_records(setup, name, recs)
    save_run(setup, name, info)


def load(setup: Setup, name: str) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The records and run info that :func:`save` wrote, for the report."""
    return load_records(setup.cache_dir / f"{name}_frames.csv"), load_run(setup, name)
