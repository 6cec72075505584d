"""sinkjax: wheel sinkage z0 and entry/exit angles from images, with honest uncertainty.

The public API is flat, here; the implementation is in sub-packages that follow the paper's
"Processes of Sinkage Detection": ``soft/`` (colour -> segmentation -> outline -> hough -> model
-> fit -> uncertainty, then ``estimator``), ``classic/`` (the paper's OpenCV pipeline:
segmentation -> outline -> refine -> estimator), ``calibration/`` (labels -> loss -> optimise),
``synth/`` (scene -> truth -> layers -> raster -> presets -> recording), and ``app/`` (PATHs ->
recordings -> frames -> results -> CSV, overlays, plots, the command line). ``geometry`` holds
Eqs. 1-3, ``rig`` the rig file, ``status`` and ``result`` what every estimator reports, and
``metrics`` the one definition of every error statistic. ``sinkjax.torch`` (PyTorch/kornia) and
``sinkjax.review`` (the web page) are optional extras. The contract is docs/conventions.md.
"""

# First: when this process is the `sinkjax estimate` command, its compiled functions start
# loading beside the imports below (sinkjax.app.early; nothing happens on a library import).
from .app.early import begin as _begin

_begin()

from . import metrics as metrics
from .app.frames import read_image as read_image
from .app.overlay import draw_overlay as draw_overlay
from .app.pipeline import estimate_paths as estimate_paths, estimate_stream as estimate_stream
from .app.plots import plot_accuracy as plot_accuracy, plot_series as plot_series
from .app.results import COLUMNS as COLUMNS, ResultsWriter as ResultsWriter, csv_row as csv_row
from .app.run import RunSummary as RunSummary, estimate_to_csv as estimate_to_csv
from .app.smoothing import smooth_csv as smooth_csv
from .app.sources import (
    Recording as Recording,
    RigOverrides as RigOverrides,
    open_recordings as open_recordings,
)
from .calibration import (
    LabelError as LabelError,
    calibrate as calibrate,
    read_labels as read_labels,
)
from .classic import estimate_classic as estimate_classic, rgb_to_hsi_np as rgb_to_hsi_np
from .geometry import (
    SinkageGeometry as SinkageGeometry,
    entry_angle_rad as entry_angle_rad,
    equivalent_line as equivalent_line,
    exit_angle_rad as exit_angle_rad,
    flat_ground_angle_rad as flat_ground_angle_rad,
    from_wheel_frame as from_wheel_frame,
    geometry_from_boundary as geometry_from_boundary,
    sinkage_px as sinkage_px,
    to_wheel_frame as to_wheel_frame,
)
from .result import FrameResult as FrameResult, Overlay as Overlay
from .rig import (
    Rig as Rig,
    RigError as RigError,
    SegmentationParams as SegmentationParams,
    load_rig as load_rig,
    rig_to_toml as rig_to_toml,
    save_rig as save_rig,
)
from .soft.adaptive import AdaptiveSegmenter as AdaptiveSegmenter
from .soft.batch import SoftRecording as SoftRecording, estimate_batch as estimate_batch
from .soft.colour import circular_mean_deg as circular_mean_deg, rgb_to_hsi as rgb_to_hsi
from .soft.estimator import (
    SoftEstimate as SoftEstimate,
    measure as measure,
    measure_from_mask as measure_from_mask,
)
from .soft.rim import RecordingRim as RecordingRim
from .soft.segmentation import (
    confidence_means as confidence_means,
    soft_mask as soft_mask,
    wheel_mask as wheel_mask,
)
from .soft.segmenter import (
    Segmenter as Segmenter,
    ThresholdSegmenter as ThresholdSegmenter,
)
from .soft.settings import SoftSettings as SoftSettings
from .soft.uncertainty import UncertaintyModel as UncertaintyModel
from .status import Status as Status
from .synth import (
    Scene as Scene,
    Truth as Truth,
    random_scene as random_scene,
    recording_scenes as recording_scenes,
    render as render,
    rig_for as rig_for,
    write_recording as write_recording,
)

__version__ = "0.1.0"
