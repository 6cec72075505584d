"""Wheel below a boundary point counted inside the rim only (soft.below.wheel_below_in_disc).

A bare-metal wheel on grey sand: the default segmenter takes lit patches of the sand for the
wheel's face. Counted down the whole column, that "wheel" below the soil line made every point
of the line look like the top edge of a lightening hole, and the frame read as no contact.
Where the first count finds no boundary on a mask made from intensity, the recording runner
(soft.batch) measures the frame again, counting inside the rim.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import synth as S
from sinkjax.result import FEATURES_HUE_SAT, FEATURES_INTENSITY
from sinkjax.soft.adaptive import default_segmenter
from sinkjax.soft.batch import estimate_batch
from sinkjax.soft.below import wheel_below_in_disc
from sinkjax.soft.estimator import prepare
from sinkjax.soft.fit import build_evidence
from sinkjax.soft.outline import extract_outline
from sinkjax.soft.rim import RecordingRim
from sinkjax.soft.segmentation import smooth
from sinkjax.soft.segmenter import Segmenter
from sinkjax.soft.settings import SoftSettings
from sinkjax.status import Status

CX, CY, R = 160.0, 100.0, 100.0
SINKAGE_PX = 10.0
SETTINGS = SoftSettings()


@functools.cache
def _frame() -> tuple[np.ndarray, S.Truth]:
    scene = S.Scene(
        width=320,
        height=240,
        centre_x_px=CX,
        centre_y_px=CY,
        radius_px=R,
        n_lugs=0,
        hub_radius_px=14.0,
        soil_level_px=CY + R - SINKAGE_PX,
        pebbles=20,
        noise_std=2.0,
        blur_sigma_px=0.5,
    )
    return S.render(scene, seed=5)


@functools.cache
def _mask_with_soil_as_wheel() -> tuple[jnp.ndarray, jnp.ndarray]:
    """The frame's default mask, plus a band of soil taken for wheel just below the rim, under
    the whole chord (clear of the ring at 1.2 r that the checks read)."""
    image, _ = _frame()
    rig = S.rig_for(S.Scene(width=320, height=240, centre_x_px=CX, centre_y_px=CY, radius_px=R))
    img = jnp.asarray(image, jnp.float64) / 255.0
    rim = RecordingRim.fixed(CX, CY, R, 0.05)
    segment = default_segmenter(rig.segmentation).with_rim
    mask = np.array(jax.jit(lambda i: segment(i, rig.confidence_rect, rim.disc()))(img))
    u = np.arange(320) - CX
    mask[int(CY + R) + 3 : int(CY + R) + 11, np.abs(u) <= 45] = 1.0
    return img, jnp.asarray(mask)


def test_counted_inside_the_disc_is_a_column_sum() -> None:
    # Reference: for each outline point, the solid mask (as extract_outline counts it) summed
    # row by row in NumPy from 3 px below the point to the disc's lowest row in its column.
    _, mask = _mask_with_soil_as_wheel()
    outline = jax.jit(lambda m: extract_outline(m, SETTINGS))(mask)
    got = wheel_below_in_disc(outline, mask, *(jnp.asarray(v) for v in (CX, CY, R)))
    solid = 1.0 / (1.0 + np.exp(-(np.asarray(smooth(mask)) - 0.5) / 0.1))
    valid = np.flatnonzero(np.asarray(outline.valid))
    assert valid.size > 100
    for i in valid:
        col = int(np.clip(np.round(float(outline.x_px[i])), 0, 319))
        row = int(np.clip(np.round(float(outline.y_px[i])), 0, 239))
        bottom = int(np.floor(CY + np.sqrt(max(R**2 - (col - CX) ** 2, 0.0))))
        ref = solid[row + 3 : bottom + 1, col].sum()
        assert float(got.wheel_below_px[i]) == pytest.approx(ref, abs=1e-6)
    # The band below the rim is counted down the whole column, not inside the disc.
    x, y = np.asarray(outline.x_px)[valid], np.asarray(outline.y_px)[valid]
    on_line = valid[(np.abs(y - (CY + R - SINKAGE_PX)) < 1.5) & (np.abs(x - CX) < 40.0)]
    assert on_line.size > 20
    assert np.all(np.asarray(outline.wheel_below_px)[on_line] > 5.0)
    assert np.all(np.asarray(got.wheel_below_px)[on_line] < 0.5)


@pytest.mark.heavy
def test_soil_taken_for_wheel_below_the_rim_keeps_the_contact() -> None:
    # The frame's own rim (no recording rim): the recording rim's mask repairs (soft.shadow_cut
    # cuts a mask that spills below the rim) would remove the band before the outline is read.
    img, mask = _mask_with_soil_as_wheel()
    _, truth = _frame()

    # Counted down the whole column, the soil line has no weight left: no contact.
    @jax.jit
    def line_weight(i: jnp.ndarray, m: jnp.ndarray) -> jnp.ndarray:
        prep = prepare(i, m)
        c = prep.choice
        return jnp.sum(build_evidence(prep.outline, c.circle, 1.0, SETTINGS, c.prior_weight).w_line)

    assert float(line_weight(img, mask)) < float(SETTINGS.min_boundary_points)
    # Through the recording runner, each frame with its own rim. A mask made from intensity (a
    # wheel without colour): counted again inside the rim, the soil line is found.
    grey = _row(FEATURES_INTENSITY)
    assert grey.status == Status.OK, grey.message
    assert grey.sinkage_mm == pytest.approx(truth.sinkage_px, abs=0.3)
    # A hue mask keeps the first count (soft.below.recounted says why).
    assert _row(FEATURES_HUE_SAT).sinkage_mm == 0.0


@pytest.mark.heavy
def test_a_padded_batch_is_recounted_alike(monkeypatch: pytest.MonkeyPatch) -> None:
    # An accelerator's path (soft.batch: padded batches, vmapped): the same row as frame by
    # frame, for the frame recounted and the padding's copies of it.
    monkeypatch.setattr("sinkjax.soft.batch._use_vmap", lambda: True)
    _, truth = _frame()
    rows = [_row(FEATURES_INTENSITY, n=2, pad_to=3), _row(FEATURES_HUE_SAT, n=1, pad_to=3)]
    assert [r.status for r in rows[0]] == [Status.OK, Status.OK]
    for r in rows[0]:
        assert r.sinkage_mm == pytest.approx(truth.sinkage_px, abs=0.3)
    assert rows[1][0].sinkage_mm == 0.0


def _row(features: int, n: int = 1, pad_to: int | None = None) -> Any:
    """The runner's row(s) for the frame segmented by the banded mask with ``features``
    (wheel_radius_mm = r, so millimetres are pixels); one row if ``n`` is 1."""
    img, mask = _mask_with_soil_as_wheel()
    scene = S.Scene(width=320, height=240, centre_x_px=CX, centre_y_px=CY, radius_px=R)
    rig = dataclasses.replace(S.rig_for(scene), wheel_radius_mm=R)
    frame = np.asarray(np.round(np.asarray(img) * 255.0), np.uint8)
    fixed = _FixedMask(mask, jnp.asarray(features, jnp.int32))
    names = [str(i) for i in range(n)]
    rows = estimate_batch([frame] * n, rig, names, rim="frame", segmenter=fixed, pad_to=pad_to)
    return rows[0] if n == 1 and pad_to is None else rows


class _FixedMask(Segmenter):
    """The same mask for every image, and a given features code."""

    mask: jnp.ndarray
    code: jnp.ndarray

    def __call__(self, image: jnp.ndarray, rect: object) -> jnp.ndarray:
        return self.mask.astype(image.dtype)

    def features(self, image: jnp.ndarray, rect: object) -> jnp.ndarray:
        return self.code
