"""``sinkjax review``: a local web page to review a run frame by frame and label frames for
calibration by dragging the geometry (conventions §3).

``session`` (frames, rigs, results, label starts), ``suspicion`` (which frames first),
``labels`` (geometry -> z0, theta1, theta2 with :mod:`sinkjax.geometry`; LABELS.csv store) and
``jobs`` (measure, calibrate) need no server library; ``server`` (Starlette + uvicorn, the
``review`` extra) and ``static/`` (plain HTML/JS/SVG) make the page; ``command`` is the CLI.
"""

from .labels import (
    LabelGeometry as LabelGeometry,
    LabelStore as LabelStore,
    LabelValues as LabelValues,
    label_values as label_values,
)
from .session import ReviewSession as ReviewSession, rim_guess as rim_guess
from .suspicion import Suspicion as Suspicion, suspicion as suspicion
