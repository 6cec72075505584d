"""Learned segmenters trained end to end through the differentiable fit from frame labels.

``segmenters`` turns colour into inputs relative to the confidence rectangle and holds
:class:`ColourMLP` and :class:`ConvSegmenter` -> ``data`` stacks labelled recordings (each
with its rig) into batches -> ``train`` imitates a starting mask, then trains on the frame-label
loss (:func:`sinkjax.calibration.mask_frame_loss`) with early stopping -> ``io`` saves and loads
them (JSON header + equinox leaves) -> ``cli`` is ``sinkjax train``. Public names are flat here.
"""

from .data import (
    FrameBatch as FrameBatch,
    LabelledRecording as LabelledRecording,
    frame_batches as frame_batches,
    load_labelled as load_labelled,
    split as split,
    synthetic_recording as synthetic_recording,
)
from .io import (
    SegmenterFileError as SegmenterFileError,
    load_segmenter as load_segmenter,
    save_segmenter as save_segmenter,
)
from .segmenters import (
    FEATURE_NAMES as FEATURE_NAMES,
    KINDS as KINDS,
    ColourMLP as ColourMLP,
    ConvSegmenter as ConvSegmenter,
    LearnedSegmenter as LearnedSegmenter,
    build as build,
    colour_distance_mask as colour_distance_mask,
    normalised_inputs as normalised_inputs,
    pixel_features as pixel_features,
    rect_statistics as rect_statistics,
)
from .train import (
    FrameScores as FrameScores,
    TrainResult as TrainResult,
    evaluate as evaluate,
    imitate as imitate,
    loss_and_grad as loss_and_grad,
    score as score,
    train as train,
)
