"""Synthetic recordings with exact truth: scene, truth, raster, presets, recording writer."""

from .render import (
    PRESETS as PRESETS,
    Scene as Scene,
    Truth as Truth,
    random_scene as random_scene,
    recording_scenes as recording_scenes,
    render as render,
    rig_for as rig_for,
    true_geometry as true_geometry,
    write_recording as write_recording,
)
from .render import (  # noqa: E402  (temporary: the split moves these)
    _FACE as _FACE,
    _RIM as _RIM,
    TERRAINS as TERRAINS,
    TRUTH_COLUMNS as TRUTH_COLUMNS,
    _camera_setup as _camera_setup,
    _frame_seed as _frame_seed,
    _hole_centres as _hole_centres,
    _with_terrain as _with_terrain,
    boundary_points as boundary_points,
    colorsys as colorsys,
    coverage as coverage,
    mirrored as mirrored,
    n_rim_crossings as n_rim_crossings,
    surface_y_px as surface_y_px,
)
