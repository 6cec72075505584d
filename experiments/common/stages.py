"""The soft method stage by stage: each stage compiled alone and timed on its real inputs.

Used by ``campaign.py`` (one 640x480 frame on the CPU) and ``gpu_profile.py`` (a batch of
frames under ``jax.vmap`` on a GPU). Each stage gets the previous stage's output, so the times
are those of the values the estimator really sees.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np


def stage_times(image_u8: np.ndarray, rig: Any, repeats: int, batch: int | None = None) -> list:
    """Median ms of each stage: one frame jitted (``batch`` None), or the frame repeated
    ``batch`` times and each stage ``jit(vmap(...))`` (ms per batch). Rows ``{stage, ms}``;
    the rows named "segmenter part: ..." are inside the "default segmenter" row."""
    import jax
    import jax.numpy as jnp

    from sinkjax.soft.adaptive import default_segmenter
    from sinkjax.soft.colour import rgb_to_hsi
    from sinkjax.soft.fit import build_evidence, fit, rim_and_boundary_capacity
    from sinkjax.soft.hough import hough_rim
    from sinkjax.soft.outline import extract_outline, refine_outline
    from sinkjax.soft.segmentation import confidence_means, reference_mask, soft_mask
    from sinkjax.soft.settings import SoftSettings
    from sinkjax.soft.uncertainty import covariance, measurement_std

    h, w = image_u8.shape[:2]
    s = SoftSettings()
    dtype = jax.dtypes.canonicalize_dtype(jnp.float64)
    image = jnp.asarray(image_u8, dtype) / 255.0
    if batch is not None:
        image = jnp.broadcast_to(image, (batch, *image.shape)) + 0.0  # a real array, not a view
    rect = jnp.asarray(rig.confidence_rect, jnp.int32)
    seg = rig.segmentation
    sign = jnp.asarray(1.0 if rig.travel == "right" else -1.0, dtype)
    radius = jnp.asarray(rig.wheel_radius_mm, dtype)
    segmenter = default_segmenter(seg)

    def mask_of(hh, ss, r):
        h_w, s_w = confidence_means(hh, ss, r)
        return soft_mask(hh, ss, h_w, s_w, seg)

    def fit_of(outline, circle):
        # As the estimator calls it: the solve on the weighted points alone.
        ev = build_evidence(outline, circle, sign, s)
        return fit(ev, capacity=rim_and_boundary_capacity(h, w))

    def cov_of(outline, circle, p):
        ev = build_evidence(outline, circle, sign, s)
        return measurement_std(p, covariance(p, ev), radius)

    def compiled(fn: Callable, in_axes: tuple) -> Callable:
        # in_axes: 0 for a per-frame value, None for one shared by the batch (the rectangle).
        return jax.jit(fn if batch is None else jax.vmap(fn, in_axes=in_axes))

    v: dict[str, Any] = {}
    stages: dict[str, tuple[Callable, Callable[[], tuple]]] = {
        "segmenter part: HSI": (compiled(rgb_to_hsi, (0,)), lambda: (image,)),
        "segmenter part: H/S band (confidence means + soft mask)": (
            compiled(mask_of, (0, 0, None)),
            lambda: (v["hh"], v["ss"], rect),
        ),
        "segmenter part: soil/background veto (reference colours, nearest-mean)": (
            compiled(lambda im, r: reference_mask(im, r, seg.veto_fraction), (0, None)),
            lambda: (image, rect),
        ),
        "segmenter part: colour switch (the wheel's mean chroma)": (
            compiled(lambda im, r: segmenter.coloured(im, r), (0, None)),
            lambda: (image, rect),
        ),
        "default segmenter, all of the above in one call": (
            compiled(lambda im, r: segmenter(im, r), (0, None)),
            lambda: (image, rect),
        ),
        "outline (extract + refine)": (
            compiled(lambda im, m: refine_outline(im, extract_outline(m, s), s), (0, 0)),
            lambda: (image, v["mask"]),
        ),
        "Hough start circle": (
            compiled(lambda o: hough_rim(o, h, w, s), (0,)),
            lambda: (v["outline"],),
        ),
        "evidence + Levenberg-Marquardt fit": (
            compiled(fit_of, (0, 0)),
            lambda: (v["outline"], v["circle"]),
        ),
        "covariance + delta method": (
            compiled(cov_of, (0, 0, 0)),
            lambda: (v["outline"], v["circle"], v["params"]),
        ),
    }
    keep = {
        "segmenter part: HSI": lambda r: v.update(hh=r[0], ss=r[1]),
        "default segmenter, all of the above in one call": lambda r: v.update(mask=r),
        "outline (extract + refine)": lambda r: v.update(outline=r),
        "Hough start circle": lambda r: v.update(circle=r),
        "evidence + Levenberg-Marquardt fit": lambda r: v.update(params=r.params),
    }
    rows = []
    for name, (fn, args) in stages.items():
        result = jax.block_until_ready(fn(*args()))
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(*args()))
            times.append(1000 * (time.perf_counter() - t0))
        rows.append({"stage": name, "ms": round(statistics.median(times), 3)})
        if name in keep:
            keep[name](result)
    return rows
