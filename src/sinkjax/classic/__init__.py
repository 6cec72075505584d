"""The paper's classic pipeline (float64 NumPy and OpenCV, no gradients), one module per step.

``segmentation`` (HSI, Eqs. 4-5, binary image, morphology) -> ``outline`` (wheel outline, 3-D
Hough rim, rim points) -> ``refine`` (the optional refinements beyond the paper) -> ``estimator``
(boundary, Eqs. 1-3, :func:`estimate_classic`). See docs/paper.md for the method.
"""

from .estimator import estimate_classic as estimate_classic
from .segmentation import (
    confidence_means_np as confidence_means_np,
    hard_mask as hard_mask,
    rgb_to_hsi_np as rgb_to_hsi_np,
)
