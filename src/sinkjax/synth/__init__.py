"""Synthetic side-view wheel-in-soil frames with EXACT ground truth (docs/conventions.md §1).

A :class:`Scene` holds every parameter of one frame (``scene``); :func:`true_geometry` computes the
paper's quantities from the true surface and rim circle (``truth``); :func:`coverage` gives each
layer's area fraction per pixel (``layers``) and :func:`render` draws the frame (``raster``);
:func:`random_scene` and :func:`recording_scenes` sample camera set-ups and terrains
(``presets``); :func:`write_recording` writes frames, ``rig.toml`` and ``truth.csv``
(``recording``).
"""

from .layers import coverage as coverage
from .presets import (
    PRESETS as PRESETS,
    TERRAINS as TERRAINS,
    random_scene as random_scene,
    recording_scenes as recording_scenes,
)
from .raster import render as render
from .recording import (
    TRUTH_COLUMNS as TRUTH_COLUMNS,
    rig_for as rig_for,
    write_recording as write_recording,
)
from .scene import Scene as Scene, mirrored as mirrored, surface_y_px as surface_y_px
from .truth import (
    Truth as Truth,
    boundary_points as boundary_points,
    n_rim_crossings as n_rim_crossings,
    true_geometry as true_geometry,
)
