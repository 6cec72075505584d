"""Labelled frames for training: recordings (each with its own rig) -> batches of arrays.

``sinkjax train`` reads one LABELS.csv per recording (docs/conventions.md §3) with the rig beside
it, as ``sinkjax calibrate`` does. Training compiles once per image size, whatever the rigs: the
frames of one size are stacked into a :class:`FrameBatch` whose rig numbers (rectangle, travel,
radius, rim search range, thresholds) are per-frame arrays, traced like
:class:`sinkjax.soft.estimator.RigArrays`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt8

from ..calibration.labels import LabelError, LabelledFrames, read_labels
from ..geometry import travel_sign
from ..rig import Rig, SegmentationParams, load_rig, rim_hint_range_px, srgb_flag
from ..soft.hough import radius_range_px


@dataclasses.dataclass(frozen=True)
class LabelledRecording:
    """One recording's labelled frames and its rig; ``masks`` (N, H, W) in [0, 1] where exact
    wheel masks are known (synthetic frames), else None; ``name`` for reports."""

    frames: LabelledFrames
    rig: Rig
    name: str
    masks: Float[np.ndarray, "N H W"] | None = None

    def subset(self, index: Sequence[int] | np.ndarray) -> LabelledRecording:
        """The frames at ``index`` (and their masks)."""
        idx = np.asarray(index, dtype=np.int64)
        f = self.frames
        frames = LabelledFrames(f.images[idx], f.targets[idx], tuple(f.names[i] for i in idx))
        masks = None if self.masks is None else self.masks[idx]
        return LabelledRecording(frames, self.rig, self.name, masks)

    def __len__(self) -> int:
        return len(self.frames.names)


def load_labelled(
    paths: Sequence[str | Path], rig_path: str | Path | None = None
) -> list[LabelledRecording]:
    """Read LABELS.csv files, each with the ``rig.toml`` beside it (else ``rig_path``).

    Raises :class:`~sinkjax.calibration.LabelError` (a ``RigError``) naming the file for a
    missing rig or a bad labels file, before any other work.
    """
    out = []
    for path in paths:
        p = Path(path)
        rig_file = p.parent / "rig.toml"
        if not rig_file.is_file():
            if rig_path is None:
                raise LabelError(
                    f"{p}: no rig.toml beside it; put the recording's rig there or pass --rig"
                )
            rig_file = Path(rig_path)
        rig = load_rig(rig_file)
        out.append(LabelledRecording(read_labels(p, rig), rig, str(p)))
    return out


def split(
    recordings: Sequence[LabelledRecording], held_out_fraction: float, seed: int = 0
) -> tuple[list[LabelledRecording], list[LabelledRecording]]:
    """(training, held-out) frames: ``held_out_fraction`` of each recording's frames (at least
    one where a recording has 3 or more, none where fewer), drawn with ``seed``."""
    rng = np.random.default_rng(seed)
    train, held = [], []
    for rec in recordings:
        n = len(rec)
        k = 0 if n < 3 or held_out_fraction <= 0 else max(1, round(held_out_fraction * n))
        order = rng.permutation(n)
        held_idx, train_idx = np.sort(order[:k]), np.sort(order[k:])
        train.append(rec.subset(train_idx))
        if k:
            held.append(rec.subset(held_idx))
    return train, held


class FrameBatch(eqx.Module):
    """Frames of one image size with their rigs' numbers, one row per frame."""

    images_u8: UInt8[Array, "N H W 3"]
    targets: Float[Array, "N 3"]  # (sinkage_mm, theta1_deg, theta2_deg), NaN = not labelled
    rect_px: Int[Array, "N 4"]
    travel_sign: Float[Array, " N"]
    wheel_radius_mm: Float[Array, " N"]
    rim_range_px: Float[Array, "N 2"]  # the rim radii searched, the rig's hint or the default
    srgb: Float[Array, " N"]  # 1.0 where the rig's encoding is "srgb", else 0.0
    seg: SegmentationParams  # each leaf (N,): the rig's thresholds (imitation targets)
    masks: Float[Array, "N H W"]  # exact wheel masks where known, else 0
    has_mask: Bool[Array, " N"]

    def __len__(self) -> int:
        return int(self.images_u8.shape[0])

    def take(self, index: Int[Array, " n"] | np.ndarray) -> FrameBatch:
        """The rows at ``index``."""
        return jax.tree_util.tree_map(lambda x: x[index], self)


def frame_batches(recordings: Sequence[LabelledRecording]) -> list[FrameBatch]:
    """One :class:`FrameBatch` per image size over all ``recordings`` (in first-seen order)."""
    groups: dict[tuple[int, int], list[tuple[LabelledRecording, int]]] = {}
    for rec in recordings:
        for i in range(len(rec)):
            groups.setdefault(rec.frames.images.shape[1:3], []).append((rec, i))
    dtype = jax.dtypes.canonicalize_dtype(jnp.float64)
    batches = []
    for (height, width), rows in groups.items():
        recs = [r for r, _ in rows]
        default_range = radius_range_px(height, width)
        ranges = [rim_hint_range_px(r.rig) or default_range for r in recs]
        masks = [np.zeros((height, width)) if r.masks is None else r.masks[i] for r, i in rows]
        segs = [r.rig.segmentation for r in recs]
        batches.append(
            FrameBatch(
                images_u8=jnp.asarray(np.stack([r.frames.images[i] for r, i in rows])),
                targets=jnp.asarray(np.stack([r.frames.targets[i] for r, i in rows]), dtype),
                rect_px=jnp.asarray([r.rig.confidence_rect for r in recs], jnp.int32),
                travel_sign=jnp.asarray([travel_sign(r.rig.travel) for r in recs], dtype),
                wheel_radius_mm=jnp.asarray([r.rig.wheel_radius_mm for r in recs], dtype),
                rim_range_px=jnp.asarray(ranges, dtype),
                srgb=jnp.asarray([srgb_flag(r.rig.encoding) for r in recs], dtype),
                seg=jax.tree_util.tree_map(lambda *v: jnp.asarray(np.stack(v), dtype), *segs),
                masks=jnp.asarray(np.stack(masks), dtype),
                has_mask=jnp.asarray([r.masks is not None for r in recs]),
            )
        )
    return batches


def synthetic_recording(
    n_frames: int,
    *,
    seed: int,
    preset: str = "full",
    width: int = 640,
    height: int = 480,
    travel: str = "right",
) -> LabelledRecording:
    """A rendered recording (:mod:`sinkjax.synth`, one camera set-up) labelled with its exact
    truth, exact wheel masks included: for experiments and tests."""
    from ..synth import recording_scenes, render, rig_for
    from ..synth.layers import WHEEL_LAYERS, coverage
    from ..synth.recording import frame_seed

    rng = np.random.default_rng(seed)
    scenes = recording_scenes(
        rng, n_frames, preset=preset, width=width, height=height, travel=travel
    )
    images, targets, masks = [], [], []
    for i, scene in enumerate(scenes):
        image, truth = render(scene, frame_seed(seed, i))
        images.append(image)
        targets.append([truth.sinkage_mm, truth.theta1_deg, truth.theta2_deg])
        masks.append(coverage(scene)[..., list(WHEEL_LAYERS)].sum(-1))
    names = tuple(f"{preset}-{seed}/frame_{i:04d}" for i in range(n_frames))
    frames = LabelledFrames(np.stack(images), np.asarray(targets, np.float64), names)
    return LabelledRecording(frames, rig_for(scenes[0]), f"{preset}-{seed}", np.stack(masks))
