"""PyTorch and kornia front end: the soft HSI segmentation in torch, and a gradient bridge to JAX.

Optional: needs the ``torch`` extra (``pip install 'sinkjax[torch]'``). Images are kornia's
``(B, 3, H, W)`` RGB in [0, 1]; masks are ``(B, 1, H, W)`` in [0, 1] (1 = wheel).

- :func:`rgb_to_hsi`, :func:`soft_hsi_mask` / :class:`SoftHSISegmenter`, :func:`smooth_mask`,
  :func:`soft_open`: the paper's HSI segmentation, equal to :mod:`sinkjax.soft.segmentation` to
  float64 round-off, differentiable with respect to the image and the six thresholds.
- :func:`measure_torch` / :class:`SinkageFromMask` / :class:`SinkageFromImage`: z0, theta1,
  theta2 and their one-sigma from the JAX estimator, as torch tensors whose backward is JAX's VJP
  (through the implicit-differentiated fit). Tensors cross by DLPack.
- :func:`lighting_augmentation`: kornia photometric augmentations for robustness studies.
- :class:`TorchColourSegmenter`, :func:`train_torch`: a learned segmenter trained from frame
  labels through the bridge (the torch counterpart of :mod:`sinkjax.learn`).
"""

from __future__ import annotations

try:
    import kornia  # noqa: F401
    import torch  # noqa: F401
except ImportError as e:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        "sinkjax.torch needs PyTorch and kornia; install them with: pip install 'sinkjax[torch]'"
    ) from e

from ..rig import SEG_FIELDS as SEG_FIELDS
from ..status import Status as Status
from .augment import lighting_augmentation as lighting_augmentation
from .bridge import (
    MeasureFromMask as MeasureFromMask,
    SinkageFromImage as SinkageFromImage,
    SinkageFromMask as SinkageFromMask,
    TorchEstimate as TorchEstimate,
    measure_torch as measure_torch,
)
from .learn import (
    TorchColourSegmenter as TorchColourSegmenter,
    imitate_torch as imitate_torch,
    label_loss as label_loss,
    train_torch as train_torch,
)
from .segmentation import (
    RgbToHsi as RgbToHsi,
    SoftHSISegmenter as SoftHSISegmenter,
    rgb_to_hsi as rgb_to_hsi,
    smooth_mask as smooth_mask,
    soft_hsi_mask as soft_hsi_mask,
    soft_open as soft_open,
)

__all__ = [
    "MeasureFromMask",
    "RgbToHsi",
    "SinkageFromImage",
    "SinkageFromMask",
    "SoftHSISegmenter",
    "Status",
    "TorchColourSegmenter",
    "TorchEstimate",
    "imitate_torch",
    "label_loss",
    "lighting_augmentation",
    "measure_torch",
    "rgb_to_hsi",
    "smooth_mask",
    "soft_hsi_mask",
    "soft_open",
    "train_torch",
]
