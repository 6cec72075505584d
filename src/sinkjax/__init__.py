"""sinkjax: wheel sinkage z0 and entry/exit angles from images, with honest uncertainty.

The pipeline, one private module per stage (the paper's "Processes of Sinkage Detection"):
``_colour`` (RGB -> HSI) -> ``_segmentation`` (soft H/S masks) -> ``_outline`` (sub-pixel wheel
outline) -> ``_hough`` (rim circle start) -> ``_model`` (circle + equivalent line + ends) ->
``_fit`` (one optimistix solve) -> ``_uncertainty`` (delta method) -> ``_calibration``
(gradient tuning of the thresholds); ``_geometry`` holds Eqs. 1-3, ``_classic`` the paper's
OpenCV pipeline, ``_synth`` the renderer with exact truth, and ``_io``/``_pipeline``/``_cli``
the command line. The optional ``sinkjax.torch`` holds the PyTorch/kornia side.
"""

from .app.inputs import read_image as read_image
from .app.overlay import draw_overlay as draw_overlay
from .app.pipeline import (
    estimate_paths as estimate_paths,
    estimate_stream as estimate_stream,
    estimate_to_csv as estimate_to_csv,
)
from .app.plots import plot_accuracy as plot_accuracy, plot_series as plot_series
from .app.results import (
    COLUMNS as COLUMNS,
    FrameResult as FrameResult,
    Overlay as Overlay,
    ResultsWriter as ResultsWriter,
)
from .app.smoothing import smooth_csv as smooth_csv
from .calibration.calibrate import (
    LabelError as LabelError,
    calibrate as calibrate,
    read_labels as read_labels,
)
from .classic.estimator import estimate_classic as estimate_classic, rgb_to_hsi_np as rgb_to_hsi_np
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
from .rig import (
    Rig as Rig,
    RigError as RigError,
    SegmentationParams as SegmentationParams,
    load_rig as load_rig,
    rig_to_toml as rig_to_toml,
    save_rig as save_rig,
)
from .soft.colour import circular_mean_deg as circular_mean_deg, rgb_to_hsi as rgb_to_hsi
from .soft.estimator import (
    SoftEstimate as SoftEstimate,
    estimate_batch as estimate_batch,
    measure as measure,
    measure_from_mask as measure_from_mask,
)
from .soft.segmentation import (
    confidence_means as confidence_means,
    soft_mask as soft_mask,
    wheel_mask as wheel_mask,
)
from .soft.settings import SoftSettings as SoftSettings
from .soft.uncertainty import UncertaintyModel as UncertaintyModel
from .status import Status as Status
from .synth.render import (
    Scene as Scene,
    Truth as Truth,
    random_scene as random_scene,
    recording_scenes as recording_scenes,
    render as render,
    rig_for as rig_for,
    write_recording as write_recording,
)

__version__ = "0.1.0"
