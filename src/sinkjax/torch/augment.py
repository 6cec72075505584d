"""Photometric kornia augmentations for lighting-robustness studies (geometry untouched)."""

from __future__ import annotations

import kornia
from torch import Tensor, nn

__all__ = ["lighting_augmentation"]


def lighting_augmentation(
    *,
    p: float = 0.5,
    shadow: bool = True,
    colour_jitter: bool = True,
    planckian: bool = True,
    noise_std: float = 0.02,
) -> kornia.augmentation.AugmentationSequential:
    """Photometric kornia augmentations mimicking the lighting a rig sees (no geometry changes).

    Plasma-fractal shadows (:class:`~kornia.augmentation.RandomPlasmaShadow`), brightness /
    contrast / saturation / small hue jitter (``ColorJitter``), black-body illuminant changes
    (``RandomPlanckianJitter``) and sensor noise (``RandomGaussianNoise``), each applied with
    probability ``p``. Geometry is untouched, so sinkage and angle labels stay valid.

    Shape: :math:`(B, 3, H, W)` in [0, 1] -> same (clipped to [0, 1]).

    Example:
        >>> import torch
        >>> aug = lighting_augmentation()
        >>> aug(torch.rand(2, 3, 32, 32)).shape
        torch.Size([2, 3, 32, 32])
    """
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"p must be in [0, 1]. Got {p}")
    aug = kornia.augmentation
    ops: list[nn.Module] = []
    if shadow:
        ops.append(aug.RandomPlasmaShadow(roughness=(0.1, 0.7), shade_intensity=(-0.5, 0.0), p=p))
    if colour_jitter:
        ops.append(aug.ColorJitter(brightness=0.2, contrast=0.2, saturation=0.2, hue=0.02, p=p))
    if planckian:
        ops.append(aug.RandomPlanckianJitter(mode="blackbody", p=p))
    if noise_std > 0:
        ops.append(aug.RandomGaussianNoise(mean=0.0, std=noise_std, p=p))
    ops.append(_Clip())
    # AugmentationSequential runs plain nn.Modules too (the final clip); its annotation is narrower.
    return aug.AugmentationSequential(*ops)  # type: ignore[arg-type]


class _Clip(nn.Module):
    def forward(self, x: Tensor) -> Tensor:
        return x.clamp(0.0, 1.0)
