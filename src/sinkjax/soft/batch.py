"""The soft method over the frames of a recording: compiled halves, the recording's rim, rows.

:class:`SoftRecording` is what the pipeline runs for one recording. The first batch of frames of
an image size is measured with each frame's own rim; their circles vote for the recording's rim
(``soft.rim.combine_rims``), and the same prepared frames are then finished again with that rim
held as a strong prior (segmented again first where the segmenter uses the rim:
``Segmenter.with_rim``), as is every later frame: a stream is read once, and the output depends
only on the frames, never on how a run was cut into tasks. A frame of a wheel without colour read
as no contact is measured again with the wheel below its outline counted inside the rim
(``soft.below``). ``estimate_batch`` is the same for a list of frames taken as one recording.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..result import FEATURES_INTENSITY, FrameResult, failed
from ..rig import Rig, rect_problem, rim_hint_range_px
from ..status import Status
from ..xla import frames_in_lockstep, jit, side_by_side
from .adaptive import default_segmenter
from .estimator import Prepared, RigArrays, SoftEstimate, finish, prepare, rechoose, rig_arrays
from .hough import radius_range_px
from .rim import RecordingRim, combine_rims
from .rows import frame_result as frame_result
from .segmenter import Segmenter
from .settings import SoftSettings
from .uncertainty import UncertaintyModel
from .warm import first_time, loading, placed_like, warm, warmed

log = logging.getLogger("sinkjax")


def _float(image_u8: Array) -> Array:
    # The default float: float32, or float64 when jax_enable_x64 is on (one dtype throughout,
    # which the solver requires).
    return image_u8.astype(jax.dtypes.canonicalize_dtype(jnp.float64)) / 255.0


def _prepare_u8(
    image_u8: Array, segmenter: Segmenter, rig: RigArrays, rim: RecordingRim
) -> Prepared:
    # The mask stage: the segmenter is an argument, its parameters traced like the rig's. Its
    # choice of features is computed here too (the run summary reports it; the default
    # segmenter's choice shares its colour statistics with the mask under jit).
    image = _float(image_u8)
    mask = segmenter.with_rim(image, rig.rect_px, rim.disc())
    features = segmenter.features(image, rig.rect_px)
    blur = segmenter.blur_px(image, rig.rect_px)  # widens the sigmas (soft.denoise)
    return prepare(image, mask, rim, None, rig.rim_range_px, features, rig.srgb, blur)


def _finish_u8(
    image_u8: Array, prepared: Prepared, rig: RigArrays, recount_in_disc: bool = False
) -> SoftEstimate:
    return finish(
        _float(image_u8),
        prepared,
        travel=rig.travel_sign,
        wheel_radius_mm=rig.wheel_radius_mm,
        uncertainty=rig.uncertainty,
        srgb=rig.srgb,
        recount_in_disc=recount_in_disc,
    )


def _recount_u8(image_u8: Array, prepared: Prepared, rig: RigArrays) -> SoftEstimate:
    # finish with the wheel below the outline counted inside the rim (soft.below), for the
    # frames of a wheel without colour where finish found no contact.
    return _finish_u8(image_u8, prepared, rig, recount_in_disc=True)


# No static arguments: these compile once per image size (and batch size) and segmenter
# structure, whatever the rig, the rim and the segmenter's parameter values.
_prepare_one = jit(_prepare_u8)
_rechoose_one = jit(rechoose)
_finish_one = jit(_finish_u8)
_prepare_batch = jit(jax.vmap(_prepare_u8, in_axes=(0, None, None, None)))
_rechoose_batch = jit(jax.vmap(rechoose, in_axes=(0, None)))
_finish_batch = jit(jax.vmap(_finish_u8, in_axes=(0, 0, None)))
_recount_one = jit(_recount_u8)
_recount_batch = jit(jax.vmap(_recount_u8, in_axes=(0, 0, None)))

# (name, jitted function, example arguments) -> the callable to run on arguments of that shape.
CompiledProvider = Callable[[str, Any, tuple[Any, ...]], Callable[..., Any]]
_provider: CompiledProvider | None = None


def set_compiled_provider(provider: CompiledProvider | None) -> None:
    """Let the application layer supply the compiled functions (e.g. exported functions loaded
    from disk, :mod:`sinkjax.app.executables`); None: the jitted functions themselves."""
    global _provider
    _provider = provider


def _compiled(name: str, fn: Any, args: tuple[Any, ...]) -> Callable[..., Any]:
    return fn if _provider is None else _provider(name, fn, args)


# Accelerator batches are padded to one of these sizes (then to multiples of the largest).
BATCH_SIZES = (1, 8, 32, 128)


def padded_size(n: int) -> int:
    """The batch size ``n`` frames are padded to: the first of :data:`BATCH_SIZES` that holds
    them, else a multiple of the largest."""
    for size in BATCH_SIZES:
        if n <= size:
            return size
    top = BATCH_SIZES[-1]
    return -(-n // top) * top


def _use_vmap() -> bool:
    # On a CPU, vmap runs the Levenberg-Marquardt loops of all frames in lockstep until the
    # slowest converges, and XLA optimises a looped body (lax.map) worse than a plain one:
    # frame by frame is fastest there. Accelerators want the whole batch.
    return frames_in_lockstep()


def _stack(items: list) -> object:
    # NumPy, not jnp.stack: eager JAX ops would each compile once per process.
    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *items)


# A recording's rim is found from its first this many readable frames of each image size.
RIM_FRAMES = 8

FirstFrames = Callable[[int, int], list[np.ndarray]]


class SoftRecording:
    """The soft method for one recording (frames from one fixed camera), batch by batch.

    Call it like :func:`estimate_batch`; it keeps the recording's rim per image size between
    calls. ``rim``: "recording" (default) finds the rim once per image size from the
    recording's first :data:`RIM_FRAMES` readable frames of that size; "frame" measures every
    frame with its own rim (a camera that moves relative to the wheel); a
    :class:`RecordingRim` is used as given. ``first_frames(height, width)`` returns those first
    frames (the pipeline reads them from the start of the recording, so a resumed run or a
    chunk of a long video finds the same rim as the whole run); None: the first batch of each
    size is taken to be them. ``rims`` holds the rim per image size (``use`` 0 where the first
    frames gave no consensus: frames of that size are measured with their own rims).
    ``segmenter`` makes the masks (a :class:`~sinkjax.soft.segmenter.Segmenter`, e.g. a learned
    one, :func:`sinkjax.learn.load_segmenter`); None: the default segmenter with each rig's
    thresholds (``rig.segmentation``).
    """

    def __init__(
        self,
        *,
        rim: str | RecordingRim = "recording",
        uncertainty: UncertaintyModel | None = None,
        first_frames: FirstFrames | None = None,
        segmenter: Segmenter | None = None,
    ) -> None:
        if not isinstance(rim, RecordingRim) and rim not in ("recording", "frame"):
            raise ValueError(f"rim must be 'recording', 'frame' or a RecordingRim, got {rim!r}")
        self.mode = rim
        self.uncertainty = uncertainty
        self.first_frames = first_frames
        self.segmenter = segmenter
        self.rims: dict[tuple[int, int], RecordingRim] = {}

    def rim_for(self, height: int, width: int) -> RecordingRim | None:
        """The rim frames of this size are measured with; None: not decided yet."""
        if isinstance(self.mode, RecordingRim):
            return self.mode
        if self.mode == "frame":
            return RecordingRim.per_frame()
        return self.rims.get((height, width))

    def find_rim(self, images: list[np.ndarray], rig: Rig) -> RecordingRim:
        """The rim the first :data:`RIM_FRAMES` of ``images`` (one size) vote for, as
        :meth:`__call__` finds it, without measuring the frames again with it (per-frame where
        they show no common circle or the rig's rectangle lies off them)."""
        height, width = images[0].shape[:2]
        if rect_problem(rig.confidence_rect, height, width) is not None:
            return RecordingRim.per_frame()
        run = _Run(rig, self.uncertainty, None, self.segmenter)
        first = images[:RIM_FRAMES]
        own = run.finish(first, run.prepare(first, RecordingRim.per_frame()))
        return _vote(own, len(first))

    def __call__(
        self,
        images: list[np.ndarray],
        rig: Rig,
        names: list[str],
        *,
        pad_to: int | None = None,
    ) -> list[FrameResult]:
        if len(images) != len(names):
            raise ValueError(f"got {len(images)} images but {len(names)} names")
        if not images:
            return []
        shape = images[0].shape
        if any(im.shape != shape for im in images):
            raise ValueError("estimate_batch needs frames of one size; the pipeline groups them")
        height, width = shape[:2]
        problem = rect_problem(rig.confidence_rect, height, width)
        if problem is not None:
            return [failed(n, Status.BAD_RECT, problem) for n in names]
        run = _Run(rig, self.uncertainty, pad_to, self.segmenter)
        decided = (height, width) in self.rims
        out = self._estimates(images, run)
        rim = self.rims.get((height, width))
        if not decided and rim is not None and float(rim.use) < 0.5:
            log.warning(
                "%s: the recording's first frames show no common rim circle (a camera not fixed "
                "to the wheel, or unrelated pictures): each frame of %dx%d is measured with its "
                "own rim",
                names[0],
                width,
                height,
            )
        elif not decided and rim is not None:
            log.info("%s: the recording's %s", names[0], rim.describe())
        hint = rim_hint_range_px(rig)
        lo, hi = hint or radius_range_px(height, width)
        searched = f"{lo:.0f}-{hi:.0f} px, " + (
            "from the rig's rim_radius_px"
            if hint
            else "fractions of the image size; set rim_radius_px in the rig if the rim's radius "
            "is outside"
        )
        rows = [frame_result(out, i, names[i], rig, searched) for i in range(len(images))]
        if self.segmenter is None:
            return rows
        seg = self.segmenter
        return [
            r
            if r.segmenter_features is None
            else dataclasses.replace(r, segmenter_features=seg.features_label(r.segmenter_features))
            for r in rows
        ]

    def _estimates(self, images: list[np.ndarray], run: _Run) -> SoftEstimate:
        height, width = images[0].shape[:2]
        rim = self.rim_for(height, width)
        if rim is not None:
            return run.finish(images, run.prepare(images, rim))
        if self.first_frames is None:
            first = images[:RIM_FRAMES]
        else:
            first = self.first_frames(height, width)[:RIM_FRAMES]
        k = len(first)
        same = [np.array_equal(a, b) for a, b in zip(first, images[:k], strict=False)]
        if not (0 < k <= len(images) and all(same)):
            # This batch does not start with the rim's frames (a resumed run, a chunk of a
            # video): measure those first, then this batch with their rim.
            if k:
                own = run.finish(first, run.prepare(first, RecordingRim.per_frame()))
                self.rims[(height, width)] = _vote(own, k)
            else:
                self.rims[(height, width)] = RecordingRim.per_frame()
            return self._estimates(images, run)
        prepared = run.prepare(images, RecordingRim.per_frame())
        out = run.finish(images, prepared)
        rim = self.rims[(height, width)] = _vote(out, k)
        if float(rim.use) < 0.5:
            return out
        return run.finish(images, run.with_rim(images, prepared, rim))


class _Run:
    """One call's compiled-function plumbing: frame by frame on a CPU, padded batches else."""

    def __init__(
        self,
        rig: Rig,
        uncertainty: UncertaintyModel | None,
        pad_to: int | None,
        segmenter: Segmenter | None = None,
    ):
        self.default = segmenter is None
        if segmenter is None:
            # Fixed dtypes (not weak ones) for the thresholds too: a rig loaded from a file and
            # one built in Python must hit the same compiled function.
            dtype = jax.dtypes.canonicalize_dtype(jnp.float64)
            segmenter = jax.tree_util.tree_map(
                lambda v: jnp.asarray(v, dtype), default_segmenter(rig.segmentation)
            )
        self.segmenter = segmenter
        self.arrays = rig_arrays(rig, uncertainty)
        self.vmap = _use_vmap()
        self.pad_to = pad_to

    def _frames(self, images: list[np.ndarray]) -> list[Array]:
        if self.vmap:
            n = len(images)
            size = max(self.pad_to or padded_size(n), n)
            return [jnp.asarray(np.stack(images + [images[0]] * (size - n)))]
        return [jnp.asarray(im) for im in images]

    def _fn(self, name: str, args: tuple[Any, ...]) -> Callable[..., Any]:
        fns = {
            "prepare": (_prepare_one, _prepare_batch),
            "rechoose": (_rechoose_one, _rechoose_batch),
            "finish": (_finish_one, _finish_batch),
            "recount": (_recount_one, _recount_batch),
        }
        fn = fns[name][int(self.vmap)]
        if not self.default:
            # Exported functions (set_compiled_provider) are made for the default segmenter
            # only; another segmenter (a learned one) runs through jit, which still compiles
            # once per image size and segmenter structure (its parameters are traced).
            return fn
        return _compiled(f"{name}_batch" if self.vmap else f"{name}_one", fn, args)

    def prepare(self, images: list[np.ndarray], rim: RecordingRim) -> list[Prepared]:
        frames = self._frames(images)
        args = (frames[0], self.segmenter, self.arrays, rim)
        fn = self._fn("prepare", args)
        if _provider is not None and self.default and first_time(fn):
            # The later halves load while this one runs (soft.warm): their shapes from the
            # exported prepare's outputs, with no tracing of the method.
            out = placed_like(jax.eval_shape(fn, *args), frames[0])
            for name, shapes in (
                ("finish", (frames[0], out, self.arrays)),
                ("rechoose", (out, rim)),
            ):
                warm(self._fn(name, shapes), shapes)
        # While a later half loads (it is what the next step waits for), frames one at a time.
        return side_by_side(
            lambda f: fn(f, self.segmenter, self.arrays, rim), frames, alone=loading()
        )

    def rechoose(self, prepared: list[Prepared], rim: RecordingRim) -> list[Prepared]:
        fn = warmed(self._fn("rechoose", (prepared[0], rim)))
        return side_by_side(lambda p: fn(p, rim), prepared)

    def with_rim(
        self, images: list[np.ndarray], prepared: list[Prepared], rim: RecordingRim
    ) -> list[Prepared]:
        """``prepared`` (made before ``rim`` was known) as :meth:`prepare` with ``rim`` makes
        them: frames whose mask the segmenter makes with the rim (``Segmenter.uses_rim``) are
        segmented again, the others keep their outline and only choose the rim."""
        codes = np.concatenate([np.ravel(np.asarray(p.features)) for p in prepared])
        again = [self.segmenter.uses_rim(int(c)) for c in codes[: len(images)]]
        if not any(again):
            return self.rechoose(prepared, rim)
        if self.vmap:  # one padded batch: segment it all again
            return self.prepare(images, rim)
        redo = iter(self.prepare([im for im, a in zip(images, again, strict=True) if a], rim))
        kept = [p for p, a in zip(prepared, again, strict=True) if not a]
        keep = iter(self.rechoose(kept, rim) if kept else [])
        return [next(redo) if a else next(keep) for a in again]

    def finish(self, images: list[np.ndarray], prepared: list[Prepared]) -> SoftEstimate:
        frames = self._frames(images)
        fn = warmed(self._fn("finish", (frames[0], prepared[0], self.arrays)))
        each = side_by_side(lambda f, p: fn(f, p, self.arrays), frames, prepared)
        out = jax.tree_util.tree_map(np.asarray, each[0]) if self.vmap else _stack(each)
        return self._recount(frames, prepared, out, len(images))  # type: ignore[arg-type]

    def _recount(
        self, frames: list[Array], prepared: list[Prepared], out: SoftEstimate, n: int
    ) -> SoftEstimate:
        """``out`` with the frames of a wheel without colour read as no contact measured again
        with the wheel below the outline counted inside the rim (:mod:`sinkjax.soft.below`),
        where that finds a contact: compiled only for a run with such frames."""
        grey = np.asarray(out.features)[:n] == FEATURES_INTENSITY
        again = np.flatnonzero(grey & (np.asarray(out.sinkage_mm)[:n] == 0.0))
        if again.size == 0:
            return out
        fn = self._fn("recount", (frames[0], prepared[0], self.arrays))
        if self.vmap:  # one padded batch: all of it again
            new = jax.tree_util.tree_map(np.asarray, fn(frames[0], prepared[0], self.arrays))
            rows = [jax.tree_util.tree_map(lambda a, i=i: a[i], new) for i in again]
        else:
            rows = side_by_side(lambda i: fn(frames[i], prepared[i], self.arrays), again.tolist())
        leaves, tree = jax.tree_util.tree_flatten(out)
        leaves = [np.array(a) for a in leaves]
        for i, row in zip(again, rows, strict=True):
            if float(row.sinkage_mm) != 0.0:
                for a, b in zip(leaves, jax.tree_util.tree_leaves(row), strict=True):
                    a[i] = np.asarray(b)
        return jax.tree_util.tree_unflatten(tree, leaves)  # type: ignore[no-any-return]


def _vote(out: SoftEstimate, n: int) -> RecordingRim:
    """The recording's rim from the first ``n`` frames' own fits (per-frame if no consensus)."""
    least = float(SoftSettings().min_rim_support)
    found = combine_rims(np.asarray(out.params[:n, :3]), _rim_evidence(out, n), min_support=least)
    return RecordingRim.per_frame() if found is None else found


def _rim_evidence(out: SoftEstimate, n: int) -> np.ndarray:
    """Each frame's rim support where its own fit converged on a rim it saw, else 0."""
    status = np.asarray(out.status[:n])
    usable = np.isin(
        status, [Status.OK.code, Status.NO_CONTACT.code, Status.IMPLAUSIBLE.code]
    ) & np.all(np.isfinite(np.asarray(out.params[:n, :3])), axis=1)
    return np.where(usable, np.asarray(out.rim_support[:n]), 0.0)


def estimate_batch(
    images: list[np.ndarray],
    rig: Rig,
    names: list[str],
    *,
    pad_to: int | None = None,
    uncertainty: UncertaintyModel | None = None,
    rim: str | RecordingRim = "recording",
    segmenter: Segmenter | None = None,
) -> list[FrameResult]:
    """Soft estimates for frames of one size (uint8 RGB (H, W, 3) each), one row per frame,
    taken as one recording (see :class:`SoftRecording` for ``rim`` and ``segmenter``).

    ``pad_to`` pads the batch (repeating a frame) on an accelerator so that every call has the
    same shape and the compiled functions are reused; by default to :func:`padded_size`. The
    rig's numbers are traced (:class:`RigArrays`): a new rig of a size already seen compiles
    nothing.
    """
    recording = SoftRecording(rim=rim, uncertainty=uncertainty, segmenter=segmenter)
    return recording(images, rig, names, pad_to=pad_to)
