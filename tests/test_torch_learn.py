"""The torch path of learned segmenters (sinkjax.torch.learn): gradients of the frame-label loss
through the DLPack bridge against finite differences, and a few training steps lower the loss."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("kornia")

from sinkjax import learn as L  # noqa: E402
from sinkjax.torch import measure_torch  # noqa: E402
from sinkjax.torch.learn import (  # noqa: E402
    TorchColourSegmenter,
    imitate_torch,
    label_loss,
    train_torch,
)


@functools.cache
def data() -> tuple:
    rec = L.synthetic_recording(3, seed=11, preset="full", width=240, height=180)
    images = torch.from_numpy(rec.frames.images).permute(0, 3, 1, 2).double() / 255.0
    masks = torch.from_numpy(rec.masks).double()[:, None]
    targets = torch.from_numpy(rec.frames.targets)
    return rec.rig, images, masks, targets


@pytest.fixture
def started(computed_once) -> TorchColourSegmenter:
    """A fresh copy of the model that imitated the exact masks (400 steps, about a minute):
    imitated once per session, by whichever worker needs it first."""
    rig, images, masks, _ = data()

    def imitate(path: Path) -> None:
        torch.manual_seed(0)
        seg = TorchColourSegmenter(rig.confidence_rect).double()
        assert imitate_torch(seg, images, masks, steps=400) < 0.1
        torch.save(seg.state_dict(), path)

    seg = TorchColourSegmenter(rig.confidence_rect).double()
    seg.load_state_dict(torch.load(computed_once("torch_learn_started.pt", imitate)))
    return seg


def _loss(seg: TorchColourSegmenter) -> torch.Tensor:
    rig, images, _, targets = data()
    est = measure_torch(images, seg(images), travel=rig.travel, wheel_radius_mm=rig.wheel_radius_mm)
    assert bool((est.status == 0).all())  # every frame measures
    return label_loss(est.values, est.status, targets)


@pytest.mark.heavy
@pytest.mark.slow
def test_torch_frame_loss_gradient_matches_finite_differences(
    started: TorchColourSegmenter,
) -> None:
    seg = started
    seg.zero_grad()
    loss = _loss(seg)
    loss.backward()
    params = list(seg.parameters())
    grads = [p.grad.detach().clone() for p in params]
    gen = torch.Generator().manual_seed(1)
    eps = 1e-5
    # The differences are taken with autograd on, as the gradient was: the bridge then runs the
    # forward it has compiled already (with no_grad it would compile its plain forward too,
    # about a minute of this test on two busy cores); the numbers are the same.
    for _ in range(3):
        d = [torch.randn(p.shape, generator=gen, dtype=p.dtype) for p in params]
        ad = sum(float((g * v).sum()) for g, v in zip(grads, d, strict=True))
        with torch.no_grad():
            for p, v in zip(params, d, strict=True):
                p.add_(eps * v)
        plus = float(_loss(seg).detach())
        with torch.no_grad():
            for p, v in zip(params, d, strict=True):
                p.sub_(2 * eps * v)
        minus = float(_loss(seg).detach())
        with torch.no_grad():
            for p, v in zip(params, d, strict=True):
                p.add_(eps * v)
        fd = (plus - minus) / (2 * eps)
        # 1 %, not the JAX path's 0.5 %: kornia's HSV takes max/min over the channels, which
        # has kinks at the many tied channels of 8-bit pixels; central differences straddle
        # them (measured: 0.6-0.8 % for eps 1e-5 and 1e-6 alike).
        np.testing.assert_allclose(ad, fd, rtol=1e-2, atol=1e-6 * abs(fd) + 1e-8)


@pytest.mark.heavy
@pytest.mark.slow
def test_torch_training_lowers_the_loss(started: TorchColourSegmenter) -> None:
    rig, images, _, targets = data()
    seg = started
    import copy

    grown = copy.deepcopy(seg)
    with torch.no_grad():
        # The mask grows into the soil (loss about 14). A shrunk one no longer makes a bad start:
        # its soil line measures (bias - 0.5: loss 0.77), since the rim edge's dips inside the
        # rim are no longer taken for soil (soft.fit.boundary_side).
        grown.head.bias += 2.5
    losses = train_torch(
        grown,
        images,
        targets,
        travel=rig.travel,
        wheel_radius_mm=rig.wheel_radius_mm,
        steps=8,
        lr=3e-3,
    )
    assert min(losses[1:]) < 0.7 * losses[0]
