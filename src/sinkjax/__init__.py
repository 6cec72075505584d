"""sinkjax: wheel sinkage z0 and entry/exit angles from images, with honest uncertainty."""

from ._geometry import (
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
from ._results import (
    COLUMNS as COLUMNS,
    FrameResult as FrameResult,
    Overlay as Overlay,
    ResultsWriter as ResultsWriter,
)
from ._rig import (
    Rig as Rig,
    RigError as RigError,
    SegmentationParams as SegmentationParams,
    load_rig as load_rig,
    rig_to_toml as rig_to_toml,
    save_rig as save_rig,
)

__version__ = "0.1.0"
