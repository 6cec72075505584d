"""Training a segmenter end to end from frame labels, through the differentiable fit.

The loss of one frame is :func:`sinkjax.calibration.mask_frame_loss` of the segmenter's mask:
the robust error of the fitted z0, theta1, theta2 against the labels (gradients flow from the
optimistix fit to the mask by implicit differentiation, then to the parameters), with
calibration's surrogate terms for labelled frames that do not measure, plus optionally
``pixel_weight`` x the mask's binary cross-entropy against an exact mask where one is known.

:func:`imitate` gives a new model a sensible start (the rig's default mask, or the exact mask);
:func:`train` runs Adam (optax) on mini-batches, scores held-out labelled frames every few steps,
keeps the best model and stops early when they stop improving.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from ..calibration.compiled import solve_failures_as_nan
from ..calibration.loss import boundary_contrast, mask_frame_loss
from ..soft.adaptive import default_segmenter
from ..soft.checks import MAX_HALF_RING_DISAGREEMENT, ring_disagreement
from ..status import Status
from ..xla import filter_jit, map_frames
from .data import FrameBatch
from .segmenters import LearnedSegmenter

_EPS = 1e-6
# Weight of the labelled-soil-line term (per unit of boundary contrast, in [0, 2]) in training.
CONTRAST_WEIGHT = 2.0
# Backtracking (``train``): an update may raise its mini-batch's loss by this fraction at most
# (mini-batch noise aside, a step along the gradient lowers it), halved at most this many times.
MAX_RISE = 0.05
MAX_HALVINGS = 3
# Weight of the ring check's margin in training: a labelled contact frame's mask that disagrees
# with its fitted rim and line over more than half of what the check allows pays this much per
# check limit, so the gradient turns away before the frame reads ``implausible`` (a cliff in the
# loss that no gradient sees coming). Scoring never includes it.
RING_WEIGHT = 4.0


def _bce(mask: Float[Array, "H W"], target: Float[Array, "H W"]) -> Float[Array, ""]:
    m = jnp.clip(mask, _EPS, 1.0 - _EPS)
    return -jnp.mean(target * jnp.log(m) + (1.0 - target) * jnp.log(1.0 - m))


def _frame(
    seg: LearnedSegmenter,
    batch: FrameBatch,
    pixel_weight: Array,
    contrast_weight: Array,
    ring_weight: Array,
) -> tuple[Array, Array]:
    """Loss of ONE frame (``batch`` holds one row, unbatched) and its (values 3, status)."""
    image = batch.images_u8.astype(jax.dtypes.canonicalize_dtype(jnp.float64)) / 255.0
    mask = seg(image, batch.rect_px)
    loss, seen = mask_frame_loss(
        image,
        mask,
        batch.targets,
        travel=batch.travel_sign,
        wheel_radius_mm=batch.wheel_radius_mm,
        rim_range_px=(batch.rim_range_px[0], batch.rim_range_px[1]),
        srgb=batch.srgb,
    )
    pixel = jnp.where(batch.has_mask, pixel_weight * _bce(mask, batch.masks), 0.0)
    # The labels say where the soil line is inside the fitted rim: a dense signal on the mask
    # near that line for every labelled contact frame (calibration uses it only for frames
    # that do not measure).
    t = batch.targets
    usable = jnp.isfinite(t[0]) & (jnp.where(jnp.isfinite(t[0]), t[0], 0.0) > 0)
    usable = usable & jnp.all(jnp.isfinite(seen.circle)) & (seen.circle[2] > 1.0)
    circle = jnp.where(usable, seen.circle, jnp.asarray([0.0, 0.0, 2.0], seen.circle.dtype))
    contrast = boundary_contrast(
        mask, circle, t, sign=batch.travel_sign, wheel_radius_mm=batch.wheel_radius_mm
    )
    loss = loss + jnp.where(usable, contrast_weight * contrast, 0.0)
    ring = ring_disagreement(
        mask, jnp.concatenate([circle, seen.line]), batch.travel_sign, jnp.asarray(True)
    )
    margin = jax.nn.relu(ring / MAX_HALF_RING_DISAGREEMENT - 0.5)
    loss = loss + jnp.where(usable, ring_weight * margin, 0.0)
    return loss + pixel, jnp.concatenate([seen.values, seen.status[None].astype(loss.dtype)])


def _n_cells(batch: FrameBatch) -> Array:
    return jnp.maximum(jnp.sum(jnp.isfinite(batch.targets)), 1).astype(batch.targets.dtype)


@filter_jit
def loss_and_grad(
    seg: LearnedSegmenter,
    batch: FrameBatch,
    pixel_weight: float | Array = 0.0,
    contrast_weight: float | Array = 0.0,
    ring_weight: float | Array = 0.0,
) -> tuple[Array, LearnedSegmenter, Array]:
    """(mean loss per labelled cell, its gradient w.r.t. the parameters, per-frame (values 3,
    status) (N, 4)) over a batch, with the weights of :func:`train`'s optional terms.
    Gradients are taken frame by frame so that a frame whose fit
    produced non-finite values (a NaN implicit gradient) drops out; its penalty still counts."""
    params, static = eqx.partition(seg, eqx.is_array)
    pw = jnp.asarray(pixel_weight, batch.targets.dtype)
    cw = jnp.asarray(contrast_weight, batch.targets.dtype)
    rw = jnp.asarray(ring_weight, batch.targets.dtype)

    def one(p: LearnedSegmenter, row: FrameBatch) -> tuple[Array, Array]:
        return _frame(eqx.combine(p, static), row, pw, cw, rw)

    both = jax.value_and_grad(one, has_aux=True)
    (losses, seen), grads = map_frames(lambda row: both(params, row), batch)
    leaves = jax.tree_util.tree_leaves(grads)
    finite = jnp.all(
        jnp.stack([jnp.all(jnp.isfinite(g.reshape(g.shape[0], -1)), 1) for g in leaves]), 0
    )
    n = _n_cells(batch)
    # The gradient in the parameters' own dtype (float32 as stored, see segmenters).
    grad = jax.tree_util.tree_map(
        lambda g, p: (
            jnp.sum(jnp.where(finite.reshape(-1, *[1] * (g.ndim - 1)), g, 0.0), 0)
            / n.astype(g.dtype)
        ).astype(p.dtype),
        grads,
        params,
    )
    return jnp.sum(losses) / n, grad, seen


@filter_jit
def evaluate(seg: LearnedSegmenter, batch: FrameBatch) -> tuple[Array, Array]:
    """(mean loss per labelled cell, per-frame (values 3, status) (N, 4)) without gradients."""
    zero = jnp.zeros((), batch.targets.dtype)
    losses, seen = map_frames(lambda row: _frame(seg, row, zero, zero, zero), batch)
    return jnp.sum(losses) / _n_cells(batch), seen


def _batches_of(batches: Sequence[FrameBatch], size: int, rng: np.random.Generator) -> FrameBatch:
    """A random mini-batch of ``size`` frames (fewer if the group is smaller) from one size
    group, groups drawn in proportion to their frames: a fixed shape per group, one compile."""
    counts = np.asarray([len(b) for b in batches], dtype=np.float64)
    g = int(rng.choice(len(batches), p=counts / counts.sum()))
    n = len(batches[g])
    return batches[g].take(np.sort(rng.choice(n, size=min(size, n), replace=False)))


@filter_jit
def _imitation_step(
    seg: LearnedSegmenter,
    state: optax.OptState,
    batch: FrameBatch,
    optimiser: optax.GradientTransformation,
) -> tuple[LearnedSegmenter, optax.OptState, Array]:
    def loss(s: LearnedSegmenter) -> Array:
        def one(row: FrameBatch) -> Array:
            image = row.images_u8.astype(jax.dtypes.canonicalize_dtype(jnp.float64)) / 255.0
            start = default_segmenter(row.seg)(image, row.rect_px)
            target = jnp.where(row.has_mask, row.masks, start)
            return _bce(s(image, row.rect_px), target)

        return jnp.mean(jax.vmap(one)(batch))

    value, grad = eqx.filter_value_and_grad(loss)(seg)
    return (*_adam_step(optimiser, seg, grad, state), value)


def _adam_step(
    optimiser: optax.GradientTransformation,
    seg: LearnedSegmenter,
    grad: LearnedSegmenter,
    state: optax.OptState,
    scale: float = 1.0,
) -> tuple[LearnedSegmenter, optax.OptState]:
    """One optimiser update, its step multiplied by ``scale`` (a backtracking try)."""
    # optax mixes Python floats with int32 step counts: allow that promotion here even where
    # the user runs JAX with strict dtype promotion.
    with jax.numpy_dtype_promotion("standard"):
        updates, state = optimiser.update(grad, state, eqx.filter(seg, eqx.is_array))
        if scale != 1.0:
            updates = jax.tree_util.tree_map(lambda u: u * scale, updates)
    return eqx.apply_updates(seg, updates), state


@filter_jit
def _batch_loss(
    seg: LearnedSegmenter, batch: FrameBatch, weights: tuple[Array, Array, Array]
) -> Array:
    """The training objective of :func:`loss_and_grad` without its gradient."""
    losses, _ = map_frames(lambda row: _frame(seg, row, *weights), batch)
    return jnp.sum(losses) / _n_cells(batch)


def _backtracked_step(
    optimiser: optax.GradientTransformation,
    seg: LearnedSegmenter,
    grad: LearnedSegmenter,
    state: optax.OptState,
    mini: FrameBatch,
    loss: float,
    weights: tuple[Array, Array, Array],
) -> tuple[LearnedSegmenter, optax.OptState, int]:
    """Adam's update if it does not raise the mini-batch's loss by more than ``MAX_RISE``;
    else the same update halved, up to ``MAX_HALVINGS`` times; else no update (the moments
    still learn the gradient). Returns the model, the state and the halvings taken (-1: none
    accepted).

    The loss is piecewise smooth: a frame whose fit stops passing the plausibility checks
    jumps from its error to the penalty of a frame that does not measure, and a fixed-size
    Adam step can cross such an edge (the loss of a few frames tripled in one step)."""
    for halvings in range(MAX_HALVINGS + 1):
        moved, moved_state = _adam_step(optimiser, seg, grad, state, 0.5**halvings)
        if float(_batch_loss(moved, mini, weights)) <= loss * (1.0 + MAX_RISE):
            return moved, moved_state, halvings
    return seg, moved_state, -1


def imitate(
    seg: LearnedSegmenter,
    batches: Sequence[FrameBatch],
    *,
    steps: int = 150,
    learning_rate: float = 1e-2,
    batch_size: int = 8,
    seed: int = 0,
) -> tuple[LearnedSegmenter, float]:
    """A sensible start: fit ``seg``'s mask to the exact mask where known, else to the rig's
    default mask (:func:`sinkjax.soft.adaptive.default_segmenter` with the rig's thresholds),
    by pixel cross-entropy.
    Cheap (no fit involved). Returns the model and its last cross-entropy."""
    optimiser = optax.adam(learning_rate)
    state = optimiser.init(eqx.filter(seg, eqx.is_array))
    rng = np.random.default_rng(seed)
    value = jnp.asarray(np.nan)
    for _ in range(steps):
        seg, state, value = _imitation_step(
            seg, state, _batches_of(batches, batch_size, rng), optimiser
        )
    return seg, float(value)


@dataclasses.dataclass
class FrameScores:
    """How a model does on a set of labelled frames (sinkage where labelled > 0)."""

    loss: float
    median_rel_sinkage_pct: float
    median_abs_sinkage_mm: float
    failed: int
    n_frames: int

    def line(self) -> str:
        return (
            f"loss {self.loss:.4g}, median sinkage error {self.median_rel_sinkage_pct:.2f} % "
            f"({self.median_abs_sinkage_mm:.3g} mm), failed {self.failed}/{self.n_frames}"
        )


def score(seg: LearnedSegmenter, batches: Sequence[FrameBatch]) -> FrameScores:
    """:class:`FrameScores` of ``seg`` over every frame of ``batches`` (failed: any status but
    ok and no_contact, as :mod:`sinkjax.metrics` counts them)."""
    total, cells, rel, err, failed, n = 0.0, 0.0, [], [], 0, 0
    for b in batches:
        loss, seen_jax = evaluate(seg, b)
        seen, targets = np.asarray(seen_jax), np.asarray(b.targets)
        k = float(np.sum(np.isfinite(targets)))
        total, cells = total + float(loss) * k, cells + k
        for (z, _, _, code), t in zip(seen, targets, strict=True):
            n += 1
            status = Status.from_code(int(code))
            if status not in (Status.OK, Status.NO_CONTACT):
                failed += 1
            elif np.isfinite(t[0]) and t[0] > 0:
                z = z if status == Status.OK else 0.0
                err.append(abs(z - t[0]))
                rel.append(100.0 * abs(z - t[0]) / t[0])
    med = lambda v: float(np.median(v)) if v else float("nan")
    return FrameScores(total / max(cells, 1.0), med(rel), med(err), failed, n)


@dataclasses.dataclass
class TrainResult:
    """The trained (best) model and how training went: ``history`` rows are (step, training
    mini-batch loss, held-out loss or NaN); scores on the training and held-out frames before
    and after; ``best_step``; ``stopped_early``; wall-clock ``seconds``; ``skipped_steps``: updates
    that raised their mini-batch's loss even when halved three times, so were not taken."""

    segmenter: LearnedSegmenter
    history: list[tuple[int, float, float]]
    best_step: int
    stopped_early: bool
    seconds: float
    train_before: FrameScores
    train_after: FrameScores
    held_before: FrameScores | None
    held_after: FrameScores | None
    skipped_steps: int = 0

    def summary(self) -> str:
        """A few lines for the terminal."""
        lines = [
            f"trained {self.segmenter.kind} ({self.segmenter.n_parameters} parameters) for "
            f"{self.history[-1][0] if self.history else 0} steps in {self.seconds:.0f} s; "
            f"best at step {self.best_step}{' (stopped early)' if self.stopped_early else ''}"
            + (
                f"; {self.skipped_steps} updates not taken (each raised its mini-batch's loss)"
                if self.skipped_steps
                else ""
            ),
            f"  training frames, start: {self.train_before.line()}",
            f"  training frames, end:   {self.train_after.line()}",
        ]
        if self.held_before is not None and self.held_after is not None:
            lines += [
                f"  held-out frames, start: {self.held_before.line()}",
                f"  held-out frames, end:   {self.held_after.line()}",
            ]
        return "\n".join(lines)

    def report(self) -> dict[str, object]:
        """JSON-able record (kept in the saved file's header)."""
        out: dict[str, object] = {
            "steps": self.history[-1][0] if self.history else 0,
            "best_step": self.best_step,
            "skipped_steps": self.skipped_steps,
            "stopped_early": self.stopped_early,
            "seconds": round(self.seconds, 1),
        }
        for name in ("train_before", "train_after", "held_before", "held_after"):
            s = getattr(self, name)
            if s is not None:
                out[name] = dataclasses.asdict(s)
        return out


def train(
    seg: LearnedSegmenter,
    batches: Sequence[FrameBatch],
    held_out: Sequence[FrameBatch] = (),
    *,
    steps: int = 100,
    learning_rate: float = 1e-3,
    batch_size: int = 8,
    eval_every: int = 10,
    patience: int = 3,
    pixel_weight: float = 0.0,
    contrast_weight: float = CONTRAST_WEIGHT,
    ring_weight: float = RING_WEIGHT,
    seed: int = 0,
    progress: bool = False,
) -> TrainResult:
    """Adam on the frame-label loss (:func:`loss_and_grad`) over random mini-batches.

    Every ``eval_every`` steps the model is scored on ``held_out`` (or, without held-out frames,
    on all training frames); the best-scoring model is returned, and training stops after
    ``patience`` scorings without improvement. ``pixel_weight``: the exact-mask cross-entropy's
    weight (frames with masks only); ``contrast_weight``: the weight of the mask's contrast
    across the labelled soil line inside the fitted rim (a dense signal from the frame labels;
    scoring never includes it); ``ring_weight``: the weight of the ring check's margin (see
    ``RING_WEIGHT``; scoring never includes it). ``progress``: a tqdm bar on stderr.

    Each update is backtracked: one that raises its mini-batch's loss by more than 5 % is halved,
    up to three times, or else not taken (``TrainResult.skipped_steps``); the loss has cliffs
    where a frame stops passing the plausibility checks, and a fixed-size step can cross one.
    """
    from tqdm import tqdm

    if steps < 0 or batch_size < 1 or eval_every < 1 or patience < 1:
        raise ValueError("steps >= 0, batch_size, eval_every and patience >= 1 are required")
    if not batches:
        raise ValueError("no training frames")
    start = time.perf_counter()
    watch = list(held_out) or list(batches)
    optimiser = optax.adam(learning_rate)
    state = optimiser.init(eqx.filter(seg, eqx.is_array))
    rng = np.random.default_rng(seed)
    train_before = score(seg, batches)
    held_before = score(seg, held_out) if held_out else None
    best, best_loss, best_step = seg, (held_before or train_before).loss, 0
    history: list[tuple[int, float, float]] = []
    waited, stopped, skipped = 0, False, 0
    weights = (
        jnp.asarray(pixel_weight, batches[0].targets.dtype),
        jnp.asarray(contrast_weight, batches[0].targets.dtype),
        jnp.asarray(ring_weight, batches[0].targets.dtype),
    )
    bar = tqdm(range(1, steps + 1), desc="train", unit="step", disable=not progress, leave=False)
    for step in bar:
        mini = _batches_of(batches, batch_size, rng)
        with solve_failures_as_nan():  # a singular implicit solve: NaN, dropped; cacheable
            loss, grad, _ = loss_and_grad(seg, mini, *weights)
        seg, state, halvings = _backtracked_step(
            optimiser, seg, grad, state, mini, float(loss), weights
        )
        skipped += halvings < 0
        watched = float("nan")
        if step % eval_every == 0 or step == steps:
            watched = float(np.mean([float(evaluate(seg, b)[0]) for b in watch]))
            if watched < best_loss:
                best, best_loss, best_step, waited = seg, watched, step, 0
            else:
                waited += 1
        history.append((step, float(loss), watched))
        bar.set_postfix(loss=f"{float(loss):.3g}", held=f"{best_loss:.3g}")
        if waited >= patience:
            stopped = True
            break
    bar.close()
    return TrainResult(
        segmenter=best,
        history=history,
        best_step=best_step,
        stopped_early=stopped,
        seconds=time.perf_counter() - start,
        train_before=train_before,
        train_after=score(best, batches),
        held_before=held_before,
        held_after=score(best, held_out) if held_out else None,
        skipped_steps=skipped,
    )
