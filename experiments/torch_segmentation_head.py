"""A learned torch segmentation head trained from sinkage/angle labels only, through the bridge.

Question: under hard lighting (presets "shading", "dust", "cast"), can a small conv net that
corrects the HSI mask, trained end-to-end through :mod:`sinkjax.torch`'s JAX bridge from
nothing but (z0, theta1, theta2) labels, beat the default HSI thresholds, and the thresholds
calibrated on the same labels (:func:`sinkjax.calibrate`)?

Set-up (seeded): one synthetic camera set-up (rig) per preset and per recording, each with
``train`` labelled frames and ``test`` held-out frames of the same rig (different terrain, sinkage,
wheel phase, noise). The head sees RGB plus HSI features relative to the rig's confidence
rectangle (hue offset from H_w, S/S_w, I/I_w) and the default HSI soft mask, and outputs a
correction to the HSI mask's logit (last layer zero-initialised, so training starts exactly at the
default thresholds' mask). Loss: pseudo-Huber of the errors in mm and degrees over the labelled
contact frames the estimator measures (status ok); gradients reach the head only through the JAX
fit (implicit differentiation) via ``measure_torch``. One head is shared by all rigs.

    .venv/bin/python experiments/torch_segmentation_head.py [--quick] [--out FILE.md]

Writes experiments/results/torch_head.md (a table per method and preset).
"""

from __future__ import annotations

import argparse
import copy
import math
import pathlib
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

import sinkjax.torch as st
from sinkjax import Rig, SegmentationParams
from sinkjax.synth import recording_scenes, render, rig_for

PRESETS = ("shading", "dust", "cast")
SEED = 20250611
# Weight of the mean squared logit correction, and how often the whole training set is scored.
L2_CORRECTION = 1.0
CHECK_EVERY = 10
DEFAULT_OUT = pathlib.Path(__file__).parent / "results" / "torch_head.md"


@dataclass
class Config:
    width: int
    height: int
    rigs_per_preset: int
    train: int
    test: int
    steps: int
    batch: int
    lr: float
    calibration_steps: int


FULL = Config(240, 180, 1, 10, 10, 60, 6, 5e-4, 30)
QUICK = Config(160, 120, 1, 5, 5, 10, 5, 3e-4, 8)


@dataclass
class Recording:
    preset: str
    rig: Rig
    images: torch.Tensor  # (N, 3, H, W) float32 in [0, 1]
    targets: np.ndarray  # (N, 3) mm, deg, deg
    contact: np.ndarray  # (N,) bool
    is_train: np.ndarray  # (N,) bool


def make_data(cfg: Config, seed: int) -> list[Recording]:
    recs = []
    for p_i, preset in enumerate(PRESETS):
        for r_i in range(cfg.rigs_per_preset):
            rng = np.random.default_rng([seed, p_i, r_i])
            n = cfg.train + cfg.test
            scenes = recording_scenes(rng, n, preset=preset, width=cfg.width, height=cfg.height)
            imgs, tg, contact = [], [], []
            for i, s in enumerate(scenes):
                im, t = render(s, int(rng.integers(2**31)) + i)
                imgs.append(im)
                tg.append((t.sinkage_mm, t.theta1_deg, t.theta2_deg))
                contact.append(t.contact)
            x = torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).float() / 255.0
            # Terrain kinds cycle with the frame index, so alternate train/test to give both sets
            # every kind.
            is_train = np.zeros(n, bool)
            is_train[np.arange(0, 2 * cfg.train, 2)[: cfg.train]] = True
            recs.append(
                Recording(
                    preset,
                    rig_for(scenes[0]),
                    x.contiguous(),
                    np.array(tg),
                    np.array(contact),
                    is_train,
                )
            )
    return recs


# ----------------------------------------------------------------------------- the head


def hsi_features(images: torch.Tensor, rect: tuple[int, int, int, int]) -> torch.Tensor:
    """(B, 3, H, W) -> (B, 6, H, W): RGB, hue offset from H_w / 180, S / S_w, I / I_w."""
    hsi = st.rgb_to_hsi(images)
    x, y, w, h = rect
    win = hsi[:, :, y : y + h, x : x + w]
    rad = torch.deg2rad(win[:, 0])
    h_w = torch.rad2deg(torch.atan2(torch.sin(rad).mean((-2, -1)), torch.cos(rad).mean((-2, -1))))
    dh = torch.remainder(hsi[:, 0] - h_w[:, None, None] + 180.0, 360.0) - 180.0
    s_rel = hsi[:, 1] / win[:, 1].mean((-2, -1)).clamp_min(1e-3)[:, None, None]
    i_rel = hsi[:, 2] / win[:, 2].mean((-2, -1)).clamp_min(1e-3)[:, None, None]
    return torch.cat([images, (dh / 180.0)[:, None], s_rel[:, None], i_rel[:, None]], 1)


class MaskHead(nn.Module):
    """HSI soft mask with a learned logit correction from local colour context."""

    last_correction: torch.Tensor

    def __init__(self, width: int = 16) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(7, width, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=2, dilation=2),
            nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=4, dilation=4),
            nn.ReLU(),
            nn.Conv2d(width, 1, 3, padding=1),
        )
        last = self.net[-1]
        assert isinstance(last, nn.Conv2d)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)  # type: ignore[arg-type]

    def forward(self, images: torch.Tensor, rect: tuple[int, int, int, int]) -> torch.Tensor:
        base = st.soft_hsi_mask(images, SegmentationParams(), rect).clamp(1e-4, 1 - 1e-4)
        base_logit = torch.log(base) - torch.log1p(-base)
        feats = torch.cat([hsi_features(images, rect), base], 1)
        self.last_correction = self.net(feats)
        return torch.sigmoid(base_logit + self.last_correction)


# ----------------------------------------------------------------------------- evaluation


def pseudo_huber(x: torch.Tensor) -> torch.Tensor:
    return torch.sqrt(1.0 + x * x) - 1.0


def run_bridge(
    rec: Recording, idx: np.ndarray, masks: torch.Tensor, batch: int
) -> tuple[np.ndarray, np.ndarray]:
    """Values (n, 6) and status (n,) for frames ``idx`` with the given masks, fixed batch size."""
    vals, stats = [], []
    for s in range(0, len(idx), batch):
        j = idx[s : s + batch]
        pad = np.concatenate([j, np.full(batch - len(j), j[0])])  # one compiled shape
        with torch.no_grad():
            est = st.measure_torch(
                rec.images[pad],
                masks[s : s + batch][_pad_index(len(j), batch)],
                travel=rec.rig.travel,
                wheel_radius_mm=rec.rig.wheel_radius_mm,
            )
        vals.append(torch.stack(est[:6], -1)[: len(j)].numpy())
        stats.append(est.status[: len(j)].numpy())
    return np.concatenate(vals), np.concatenate(stats)


def _pad_index(n: int, batch: int) -> torch.Tensor:
    return torch.tensor(list(range(n)) + [0] * (batch - n))


@dataclass
class Score:
    method: str
    preset: str
    abs_err: np.ndarray  # (n, 3) over contact frames; not-ok frames count as measuring 0
    n_ok: int
    n: int


def score(
    method: str,
    preset: str,
    values: np.ndarray,
    status: np.ndarray,
    rec: Recording,
    idx: np.ndarray,
) -> Score:
    contact = rec.contact[idx]
    v = np.where((status == 0)[:, None] & np.isfinite(values[:, :3]), values[:, :3], 0.0)
    err = np.abs(v - rec.targets[idx])[contact]
    return Score(method, preset, err, int(np.sum((status == 0) & contact)), int(contact.sum()))


def hsi_masks(rec: Recording, idx: np.ndarray, seg: SegmentationParams) -> torch.Tensor:
    return st.soft_hsi_mask(rec.images[idx], seg, rec.rig.confidence_rect)


def head_masks(head: MaskHead, rec: Recording, idx: np.ndarray) -> torch.Tensor:
    with torch.no_grad():
        return head(rec.images[idx], rec.rig.confidence_rect)


# ----------------------------------------------------------------------------- training


def frame_losses(values: torch.Tensor, status: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-frame pseudo-Huber of the errors (units 1 mm, 1 deg); not ok counts as measuring 0."""
    ok = (status == 0)[:, None] & torch.isfinite(values[:, :3])
    used = torch.where(ok, values[:, :3], torch.zeros_like(values[:, :3]))
    return pseudo_huber(used - target).sum(-1)


def train_loss(head: MaskHead, recs: list[Recording], batch: int) -> float:
    """Mean frame loss over every labelled contact training frame (the checkpoint criterion)."""
    total, n = 0.0, 0
    for rec in recs:
        tr = np.flatnonzero(rec.is_train & rec.contact)
        v, s = run_bridge(rec, tr, head_masks(head, rec, tr), batch)
        t = torch.from_numpy(rec.targets[tr]).float()
        total += float(frame_losses(torch.from_numpy(v).float(), torch.from_numpy(s), t).sum())
        n += len(tr)
    return total / max(n, 1)


def train_head(
    recs: list[Recording], cfg: Config, seed: int, log, augment: bool = False
) -> tuple[MaskHead, list[float], list[tuple[int, float]]]:
    """Adam on random batches of labelled frames; returns the head with the best train loss.

    A batch's loss only has gradient through frames the estimator measures, so a step that
    breaks frames is not pulled back by the loss: the logit correction is kept small by an L2
    penalty, and, as calibration does, the head kept is the best one seen on the whole training
    set (checked every ``CHECK_EVERY`` steps).
    """
    torch.manual_seed(seed)
    # Photometric only: the sinkage and angle labels stay valid under it.
    aug = st.lighting_augmentation(p=0.5) if augment else None
    head = MaskHead()
    opt = torch.optim.Adam(head.parameters(), lr=cfg.lr)
    pool = [
        (r, i) for r, rec in enumerate(recs) for i in np.flatnonzero(rec.is_train) if rec.contact[i]
    ]
    rng = np.random.default_rng(seed)
    losses: list[float] = []
    checks = [(0, train_loss(head, recs, cfg.batch))]
    best = (checks[0][1], copy.deepcopy(head.state_dict()))
    log(f"  train loss at start {checks[0][1]:.3f}")
    for step in range(1, cfg.steps + 1):
        pick = rng.choice(len(pool), size=cfg.batch, replace=len(pool) < cfg.batch)
        # The head takes each frame's own rig (confidence rectangle).
        imgs, masks, tg, rigs = [], [], [], []
        penalty = torch.zeros(())
        for k in pick:
            r, i = pool[k]
            rec = recs[r]
            x = rec.images[i : i + 1]
            if aug is not None:
                x = aug(x)
            m = head(x, rec.rig.confidence_rect)
            penalty = penalty + head.last_correction.square().mean()
            imgs.append(x)
            masks.append(m)
            tg.append(rec.targets[i])
            rigs.append(rec.rig)
        # All rigs share travel and radius (recording_scenes: travel right, R = 140 mm).
        est = st.measure_torch(
            torch.cat(imgs),
            torch.cat(masks),
            travel=rigs[0].travel,
            wheel_radius_mm=rigs[0].wheel_radius_mm,
        )
        target = torch.tensor(np.array(tg), dtype=torch.float32)
        fl = frame_losses(est.values, est.status, target)
        loss = fl.mean() + L2_CORRECTION * penalty / cfg.batch
        opt.zero_grad()
        loss.backward()
        finite = all(torch.isfinite(p.grad).all() for p in head.parameters() if p.grad is not None)
        if finite:
            opt.step()
        losses.append(float(fl.mean().detach()))
        n_ok = int((est.status == 0).sum())
        if step % CHECK_EVERY == 0 or step == cfg.steps:
            tl = train_loss(head, recs, cfg.batch)
            checks.append((step, tl))
            if tl < best[0]:
                best = (tl, copy.deepcopy(head.state_dict()))
            log(
                f"  step {step:3d} batch loss {losses[-1]:.3f} ok {n_ok}/{cfg.batch}; "
                f"train loss {tl:.3f}" + ("" if finite else " (non-finite grad, step skipped)")
            )
    head.load_state_dict(best[1])
    return head, losses, checks


def calibrated_seg(rec: Recording, cfg: Config) -> SegmentationParams | None:
    """Thresholds calibrated on the rig's training frames, if sinkjax.calibrate exists."""
    try:
        from sinkjax.calibration import LabelledFrames, calibrate
    except ImportError:
        return None
    tr = np.flatnonzero(rec.is_train)
    u8 = (rec.images[tr].permute(0, 2, 3, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
    frames = LabelledFrames(
        images=u8,
        targets=rec.targets[tr].astype(np.float64),
        names=tuple(f"f{i}" for i in tr),
    )
    return calibrate(frames, rec.rig, steps=cfg.calibration_steps).rig.segmentation


# ----------------------------------------------------------------------------- report


def table(scores: list[Score]) -> list[str]:
    lines = [
        "| method | preset | median abs z0 err (mm) | p90 abs z0 err (mm) "
        "| median abs θ1 err (deg) | median abs θ2 err (deg) | ok / contact frames |",
        "|---|---|---|---|---|---|---|",
    ]
    methods = list(dict.fromkeys(s.method for s in scores))
    for m in methods:
        ss = [s for s in scores if s.method == m]
        for preset in [*PRESETS, "all"]:
            sel = ss if preset == "all" else [s for s in ss if s.preset == preset]
            if not sel:
                continue
            e = np.concatenate([s.abs_err for s in sel])
            n_ok, n = sum(s.n_ok for s in sel), sum(s.n for s in sel)
            med = np.median(e, 0) if len(e) else np.full(3, math.nan)
            p90 = np.percentile(e[:, 0], 90) if len(e) else math.nan
            name = f"**{preset}**" if preset == "all" else preset
            lines.append(
                f"| {m} | {name} | {med[0]:.2f} | {p90:.2f} | {med[1]:.2f} | {med[2]:.2f} "
                f"| {n_ok} / {n} |"
            )
    return lines


def verdict(scores: list[Score]) -> list[str]:
    """Which method has the lowest median |z0 error| and median mean |angle error|, overall."""
    rows = []
    for m in dict.fromkeys(s.method for s in scores):
        e = np.concatenate([s.abs_err for s in scores if s.method == m])
        rows.append((m, float(np.median(e[:, 0])), float(np.median(e[:, 1:].mean(1)))))
    best_z = min(rows, key=lambda r: r[1])
    best_a = min(rows, key=lambda r: r[2])
    return [
        f"Lowest median |z0 error| over all test frames: {best_z[0]} ({best_z[1]:.2f} mm); "
        f"lowest median of the mean |θ1|, |θ2| error: {best_a[0]} ({best_a[2]:.2f} deg).",
        "",
        "Per method (median |z0 error| mm, median mean-angle error deg): "
        + "; ".join(f"{m}: {z:.2f}, {a:.2f}" for m, z, a in rows)
        + ".",
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small images, few steps (smoke run)")
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--out", type=pathlib.Path, default=None)
    ap.add_argument(
        "--augment", action="store_true", help="train the head on kornia lighting augmentations"
    )
    args = ap.parse_args(argv)
    cfg = QUICK if args.quick else FULL
    out = args.out or (DEFAULT_OUT.with_name("torch_head_quick.md") if args.quick else DEFAULT_OUT)
    torch.set_num_threads(2)
    t0 = time.perf_counter()
    c0 = time.process_time()
    log = lambda msg: print(f"[{time.perf_counter() - t0:6.0f} s] {msg}", flush=True)

    recs = make_data(cfg, args.seed)
    log(f"rendered {sum(len(r.targets) for r in recs)} frames of {cfg.width}x{cfg.height}")

    scores: list[Score] = []
    calibrated = {}
    for k, rec in enumerate(recs):
        test = np.flatnonzero(~rec.is_train)
        v, s = run_bridge(rec, test, hsi_masks(rec, test, rec.rig.segmentation), cfg.batch)
        scores.append(score("HSI, default thresholds", rec.preset, v, s, rec, test))
        seg = calibrated_seg(rec, cfg)
        if seg is not None:
            calibrated[k] = seg
            v, s = run_bridge(rec, test, hsi_masks(rec, test, seg), cfg.batch)
            scores.append(score("HSI, calibrated on the train labels", rec.preset, v, s, rec, test))
        log(f"baselines done for rig {k} ({rec.preset})")

    t_train = time.perf_counter()
    head, _losses, checks = train_head(recs, cfg, args.seed, log, augment=args.augment)
    t_train = time.perf_counter() - t_train
    for rec in recs:
        test = np.flatnonzero(~rec.is_train)
        v, s = run_bridge(rec, test, head_masks(head, rec, test), cfg.batch)
        scores.append(score("torch head (HSI + learned correction)", rec.preset, v, s, rec, test))
    total = time.perf_counter() - t0
    cpu = time.process_time() - c0
    log("done")

    lines = [
        "# Torch segmentation head trained through the JAX bridge",
        "",
        f"`experiments/torch_segmentation_head.py{' --quick' if args.quick else ''}` "
        f"(seed {args.seed}); {total / 60:.1f} min wall, {cpu / 60:.1f} min CPU (2 threads) "
        f"(head training {t_train / 60:.1f} min, {cfg.steps} Adam steps of {cfg.batch} frames"
        f"{', kornia lighting augmentation' if args.augment else ''}).",
        "",
        f"Frames {cfg.width}x{cfg.height}; presets {', '.join(PRESETS)}; "
        f"{cfg.rigs_per_preset} rig(s) per preset, {cfg.train} labelled training frames and "
        f"{cfg.test} held-out test frames per rig (same rig, different terrain/sinkage/phase). "
        "Errors are over the test frames with contact; a frame the estimator does not measure "
        "(status other than ok) counts as measuring zeros, as in calibration.",
        "",
        *table(scores),
        "",
        *verdict(scores),
        "",
        "Loss: pseudo-Huber of the errors in units of 1 mm / 1 deg per frame, summed over "
        "(z0, θ1, θ2); a frame not measured counts as measuring zeros. Head training: "
        f"Adam (lr {cfg.lr:g}) on random batches, L2 {L2_CORRECTION:g} on the logit correction; "
        "the head kept is the one with the lowest loss on the whole training set, checked every "
        f"{CHECK_EVERY} steps (calibration likewise keeps its best step).",
        "",
        "Whole-training-set loss of the head at the checks (step: loss): "
        + ", ".join(f"{s_}: {l_:.2f}" for s_, l_ in checks)
        + ".",
        "",
    ]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    print("\n".join(lines))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
