"""Calibration: tune the segmentation thresholds to a few hand-labelled frames by gradient.

``labels`` reads and checks LABELS.csv -> ``loss`` is the robust error of the soft estimator on
those frames, differentiable in the thresholds (``compiled``: compiled once per image size) ->
``optimise`` scores a coarse grid and runs Adam from its best points (back-off, early stop),
``rescore`` measures the candidates with their own rims and polishes the best (a compass
search), and ``optimise`` reports the calibrated rig; ``checks`` says whether it converged, which
frames disagree and the leave-one-out error; ``augment`` relights frames so the thresholds
survive a moving lamp; ``cli`` is ``sinkjax calibrate``.
The public names are re-exported here, flat.
"""

from .augment import (
    DEFAULT_CONFIG as DEFAULT_CONFIG,
    AugmentConfig as AugmentConfig,
    augment as augment,
)
from .checks import (
    CalibrationResult as CalibrationResult,
    Checks as Checks,
    Errors as Errors,
    run_checks as run_checks,
)
from .compiled import loss_and_grad as loss_and_grad, loss_value as loss_value
from .labels import (
    LABEL_COLUMNS as LABEL_COLUMNS,
    QUANTITIES as QUANTITIES,
    LabelError as LabelError,
    LabelledFrames as LabelledFrames,
    read_labels as read_labels,
)
from .loss import (
    RAW_NAMES as RAW_NAMES,
    FrameLoss as FrameLoss,
    LossAndGrad as LossAndGrad,
    boundary_contrast as boundary_contrast,
    frame_loss as frame_loss,
    from_raw as from_raw,
    labelled_soil_side as labelled_soil_side,
    mask_frame_loss as mask_frame_loss,
    pseudo_huber as pseudo_huber,
    to_raw as to_raw,
)
from .optimise import (
    BACKTRACK as BACKTRACK,
    GRID as GRID,
    calibrate as calibrate,
)
