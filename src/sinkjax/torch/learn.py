"""Learned segmenters in torch: a kornia-based ``nn.Module`` trained through the JAX fit.

The torch counterpart of :mod:`sinkjax.learn` for researchers who live in torch: the same idea
(colour relative to the confidence rectangle, a tiny network, the loss on the fitted z0, theta1,
theta2 against frame labels) with the fit reached through the DLPack bridge
(:func:`sinkjax.torch.measure_torch`, whose backward is JAX's implicit-differentiated VJP).

Example:
    >>> seg = TorchColourSegmenter(rect=(300, 120, 40, 30))  # doctest: +SKIP
    >>> imitate_torch(seg, images, masks)                      # doctest: +SKIP
    >>> losses = train_torch(seg, images, targets, wheel_radius_mm=140.0)  # doctest: +SKIP
"""

from __future__ import annotations

import kornia
import torch
from torch import Tensor, nn

from ..learn.train import MAX_HALVINGS, MAX_RISE
from ..status import Status
from .bridge import measure_torch
from .segmentation import _check_images, _valid_rect

__all__ = ["TorchColourSegmenter", "imitate_torch", "label_loss", "train_torch"]

SPREAD_FLOOR = 0.01  # as sinkjax.learn.features: a flat patch must not blow the inputs up
Z_LIMIT = 6.0
N_FEATURES = 7


def rect_normalised(images: Tensor, rect: tuple[int, int, int, int]) -> Tensor:
    """(B, 3, H, W) RGB in [0, 1] -> (B, 14, H, W): R, G, B, V, S, S cos H, S sin H (kornia's
    HSV) as squashed z-scores and plain differences from their means over the rectangle."""
    hsv = kornia.color.rgb_to_hsv(images)
    h, s, v = hsv[:, 0:1], hsv[:, 1:2], hsv[:, 2:3]
    f = torch.cat([images, v, s, s * torch.cos(h), s * torch.sin(h)], dim=1)
    x, y, w, hh = rect
    patch = f[:, :, y : y + hh, x : x + w]
    mean = patch.mean(dim=(2, 3), keepdim=True)
    spread = torch.sqrt(patch.var(dim=(2, 3), unbiased=False, keepdim=True) + SPREAD_FLOOR**2)
    d = f - mean
    return torch.cat([Z_LIMIT * torch.tanh(d / spread / Z_LIMIT), d], dim=1)


class TorchColourSegmenter(nn.Module):
    """Per-pixel MLP (1x1 convolutions) plus one depthwise 3x3 refinement, on
    :func:`rect_normalised` inputs: ``(B, 3, H, W)`` -> soft wheel mask ``(B, 1, H, W)``."""

    def __init__(self, rect: tuple[int, int, int, int], hidden: int = 16) -> None:
        super().__init__()
        self.rect = tuple(int(v) for v in rect)
        self.pixel = nn.Sequential(
            nn.Conv2d(2 * N_FEATURES, hidden, 1), nn.ReLU(), nn.Conv2d(hidden, hidden, 1)
        )
        self.context = nn.Conv2d(hidden, hidden, 3, padding=1, groups=hidden)
        self.head = nn.Conv2d(hidden, 1, 1)

    def forward(self, images: Tensor) -> Tensor:
        _check_images(images)
        rect = _valid_rect(self.rect, images.shape[-2], images.shape[-1])
        x = torch.relu(self.pixel(rect_normalised(images, rect)))
        x = x + torch.relu(self.context(x))
        return torch.sigmoid(self.head(x))


def imitate_torch(
    segmenter: nn.Module, images: Tensor, masks: Tensor, *, steps: int = 150, lr: float = 1e-2
) -> float:
    """A sensible start: fit the module's masks to ``masks`` (B, 1, H, W) by pixel
    cross-entropy (Adam). Returns the last cross-entropy."""
    opt = torch.optim.Adam(segmenter.parameters(), lr=lr)
    value = torch.tensor(float("nan"))
    for _ in range(steps):
        opt.zero_grad()
        pred = segmenter(images).clamp(1e-6, 1 - 1e-6)
        value = nn.functional.binary_cross_entropy(pred, masks)
        value.backward()
        opt.step()
    return float(value.detach())


def label_loss(values: Tensor, status: Tensor, targets: Tensor) -> Tensor:
    """Mean pseudo-Huber (1 mm, 1 degree) error of (B, 3) estimates against (B, 3) labels over
    the labelled (finite) cells; a frame that is not ``ok`` counts as measuring zeros, as in
    :func:`sinkjax.calibration.frame_loss` (its error then has no gradient)."""
    ok = (status == Status.OK.code)[:, None] & torch.isfinite(values)
    used = torch.where(ok, values, torch.zeros_like(values))
    measured = torch.isfinite(targets)
    err = used - torch.where(measured, targets, torch.zeros_like(targets))
    huber = torch.sqrt(1.0 + err * err) - 1.0
    cells = measured.sum().clamp(min=1)
    return torch.where(measured, huber, torch.zeros_like(huber)).sum() / cells


def train_torch(
    segmenter: nn.Module,
    images: Tensor,
    targets: Tensor,
    *,
    travel: str = "right",
    wheel_radius_mm: float = 1.0,
    steps: int = 20,
    lr: float = 1e-3,
) -> list[float]:
    """Adam on :func:`label_loss` of the JAX fit of ``segmenter(images)``; returns the loss
    before each step. ``images`` (B, 3, H, W) of one rig; ``targets`` (B, 3) (z0 mm, theta1,
    theta2 deg; NaN = not labelled).

    As :func:`sinkjax.learn.train`: a step that raises the loss by more than ``MAX_RISE`` is
    halved, up to ``MAX_HALVINGS`` times, else not taken. The loss is piecewise smooth: a frame
    whose fit stops passing the plausibility checks jumps from its error to that of measuring
    zeros, and a fixed-size Adam step can cross such an edge."""
    opt = torch.optim.Adam(segmenter.parameters(), lr=lr)
    params = [p for p in segmenter.parameters() if p.requires_grad]

    def loss_now() -> Tensor:
        est = measure_torch(
            images, segmenter(images), travel=travel, wheel_radius_mm=wheel_radius_mm
        )
        return label_loss(est.values, est.status, targets)

    losses = []
    loss = loss_now()
    for _ in range(steps):
        opt.zero_grad()
        loss.backward()
        before = [p.detach().clone() for p in params]
        opt.step()
        step = [p.detach() - b for p, b in zip(params, before, strict=True)]
        # The step's check is the next step's loss, graph and all: one fit per step (and one
        # compiled forward: under no_grad the bridge would compile its plain forward as well).
        for halvings in range(MAX_HALVINGS + 2):
            factor = 0.5**halvings if halvings <= MAX_HALVINGS else 0.0
            with torch.no_grad():
                for p, b, d in zip(params, before, step, strict=True):
                    p.copy_(b + factor * d)
            after = loss_now()
            if factor == 0.0 or float(after.detach()) <= float(loss.detach()) * (1.0 + MAX_RISE):
                break
        losses.append(float(loss.detach()))
        loss = after
    return losses
