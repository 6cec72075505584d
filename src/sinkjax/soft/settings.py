"""The soft estimator's tuning settings: edge detection, grouping bands, priors, acceptance.

One :class:`SoftSettings` holds every choice of the soft method that a user or a calibration
may want to change, with the values the method was developed with as defaults. It is threaded
explicitly through the stages (outline -> rim -> evidence -> residuals -> status), so that two
settings can be compared in one process and ``jax.grad`` reaches the continuous ones.

Continuous values are scalar array leaves: passing a new value to a jitted function does not
recompile it, and gradients flow to them wherever the method is smooth in them (the edge weight's
level and softness, the colour mix of the edge profile, the fit's priors; the band edges and
thresholds are comparisons, whose gradient is zero). The stages convert each leaf to the dtype
of the computation (:meth:`SoftSettings.astype`), so a float64 setting never promotes a float32
computation and the defaults give the same numbers as Python constants did. Sizes that shape
arrays (the edge profile's sampling, the Hough bin) are static fields: changing one recompiles.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def _scalar(default: float) -> Any:
    """A dataclass field for a scalar array leaf (what the annotation of the field says)."""
    return eqx.field(converter=jnp.asarray, default=default)


class SoftSettings(eqx.Module):
    """Tuning settings of the soft estimator (pixels of the image, mask units in [0, 1]).

    Outline (``sinkjax.soft.outline``):

    - ``edge_level``: mask-gradient magnitude (mask units per px) at which an edge point gets
      half weight; ``edge_softness`` the width of that sigmoid ramp, same units.
    - ``chroma_weight``: weight of the two chroma axes against luma in the edge profile that
      places each point to sub-pixel precision (video and JPEG smear chroma).
    - ``refine_half_width_px``, ``refine_step_px`` (static): the profile's half length along
      the normal and its sampling step; ``refine_passes`` (static): how many times the profile
      is taken, each centred where the last put the edge, where the mask's edge was more than a
      third of the half length off (3 by default; 1 is the former single profile, see
      ``soft.outline.refine_outline``).

    Rim (``sinkjax.soft.hough``):

    - ``centre_bin_px`` (static): side of a Hough centre bin; candidate radii are as far apart.

    Grouping of outline points (``sinkjax.soft.fit``):

    - ``rim_band_in_px``, ``rim_band_out_px``: the band around the start circle, inside and
      outside it, whose points are rim evidence; points further inside may be boundary.
    - ``end_clearance_px``: distance inside the rim that the boundary points holding the ends'
      tangents must keep: where the soil edge and the rim edge meet neither is clean, and
      smoothing rounds that corner over a few pixels, which would bend the tangents upward.
      Kept small: where the surface meets the rim at a shallow angle, every pixel of clearance
      drops several pixels of surface next to the end (the ends' robust loss, not the
      clearance, keeps stray edges near the corner out).
    - ``wheel_below_scale_px``: soft scale of the wheel allowed below a boundary point in its
      column. Small: the top edge of a lightening hole near the soil has only a few pixels of
      wheel between the hole and the soil.
    - ``end_window_fraction``, ``end_window_min_px``, ``end_window_max_px``: the longest length
      of boundary used for each end's curve, a fraction of the rim radius clipped to [min, max]
      px; the shortest window tried is ``end_window_min_px`` (``end_window_z`` below). The end
      curve bends (``sinkjax.soft.model``), so the window may be long enough to average noise
      without tilting the tangent at the rim.
    - ``end_taper``: how much the window's points are down-weighted with their distance from the
      end (``sinkjax.soft.ends.end_kernel``: 0 uniform, 1 a biweight kernel). A rut's or a pile's
      edge inside the window is not a bend the curve can follow; tapered, the points nearest the
      rim decide the tangent (``experiments/end_tangents.py``: on the paper rig's bulldozed
      frames the exit angle's median error 0.83 -> 0.53 deg with the smaller clearance).
    - ``end_window_z``: the window's length is chosen per end and frame
      (``sinkjax.soft.ends.chosen_window``): the longest of a ladder of windows, from
      ``end_window_min_px`` to the length above, whose rim crossing agrees with every shorter
      one's within this many standard errors each. ``inf`` keeps the longest window always.

    Model and priors (``sinkjax.soft.model``):

    - ``rim_loss_scale_px``: scale of the redescending (Welsch) loss on the rim residuals.
    - ``end_loss_scale_px``: the same for the ends' residuals: a lug's or a hole's edge a few
      pixels off the surface, next to the end, loses its pull.
    - ``end_angle_prior_points``: pull of each end line's angle towards the equivalent line's,
      with the weight of this many boundary points at ``end_lever_px`` (px) from the end:
      nothing when the end window is well populated, but a short window (shallow sinkage) no
      longer swings the end around. Weak (a tenth of a point): the surface's tangent where it
      meets the rim differs from the equivalent line's direction by many degrees on a bump or
      a rut, and a strong pull would bias it by as much.
    - ``end_offset_prior_points``: likewise each end line's offset, in boundary points (default
      a twentieth): an end with no points of its own (the boundary never gets clear of the rim:
      very shallow contact) becomes the equivalent line, not a line held by nothing whose rim
      intersection has unbounded variance. It is measured as the end line's distance from
      the point where the equivalent line meets the rim on that side.
    - ``end_bend_prior_points``: pull of each end curve's bend (curvature, 1/px) towards a
      straight line, with the weight of this many boundary points at ``end_lever_px`` from the
      end: a short or noisy window is not read as a strongly curved surface.
    - ``prior_weight``: pull of every parameter towards the starting point (per px^2 or rad^2).
      Tiny: it keeps the normal equations regular when a group has no points (no contact: no
      boundary, so no line) without moving well-determined parameters.

    Acceptance (``sinkjax.soft.estimator``):

    - ``min_rim_support``: fraction of the rim's circumference that must show edge evidence,
      else the frame is ``no_wheel``.
    - ``min_boundary_points``: boundary weight (points) needed to count as contact.
    - ``contact_window_px``: half-width (px along the ground) of the window over which the lower
      edge's offset inside the rim is averaged to tell a shallow soil edge from rim noise.
    - ``contact_z``: how many sigmas of that average (the frame's own edge noise and the
      recording rim's sigma) the edge must lie inside the rim to be soil: one-sided 99.9 %.
    """

    edge_level: Float[Array, ""] = _scalar(0.08)
    edge_softness: Float[Array, ""] = _scalar(0.02)
    chroma_weight: Float[Array, ""] = _scalar(0.25)
    rim_band_in_px: Float[Array, ""] = _scalar(1.5)
    rim_band_out_px: Float[Array, ""] = _scalar(4.0)
    end_clearance_px: Float[Array, ""] = _scalar(0.5)
    wheel_below_scale_px: Float[Array, ""] = _scalar(0.75)
    end_window_fraction: Float[Array, ""] = _scalar(0.2)
    end_window_min_px: Float[Array, ""] = _scalar(8.0)
    end_window_max_px: Float[Array, ""] = _scalar(40.0)
    end_taper: Float[Array, ""] = _scalar(1.0)
    end_window_z: Float[Array, ""] = _scalar(2.0)
    rim_loss_scale_px: Float[Array, ""] = _scalar(1.0)
    end_loss_scale_px: Float[Array, ""] = _scalar(1.0)
    end_angle_prior_points: Float[Array, ""] = _scalar(0.1)
    end_lever_px: Float[Array, ""] = _scalar(10.0)
    end_offset_prior_points: Float[Array, ""] = _scalar(0.05)
    end_bend_prior_points: Float[Array, ""] = _scalar(2.0)
    prior_weight: Float[Array, ""] = _scalar(1e-4)
    min_rim_support: Float[Array, ""] = _scalar(0.2)
    min_boundary_points: Float[Array, ""] = _scalar(4.0)
    contact_window_px: Float[Array, ""] = _scalar(5.0)
    contact_z: Float[Array, ""] = _scalar(3.09)
    refine_half_width_px: float = eqx.field(static=True, default=3.0)
    refine_step_px: float = eqx.field(static=True, default=0.5)
    refine_passes: int = eqx.field(static=True, default=3)
    centre_bin_px: int = eqx.field(static=True, default=4)

    def __check_init__(self) -> None:
        if self.refine_step_px <= 0 or self.refine_half_width_px < self.refine_step_px:
            raise ValueError(
                "SoftSettings needs 0 < refine_step_px <= refine_half_width_px, got "
                f"{self.refine_step_px} and {self.refine_half_width_px}"
            )
        if not isinstance(self.refine_passes, int) or self.refine_passes < 0:
            raise ValueError(
                f"SoftSettings.refine_passes must be an int >= 0, got {self.refine_passes!r}"
            )
        if not isinstance(self.centre_bin_px, int) or self.centre_bin_px < 1:
            raise ValueError(
                f"SoftSettings.centre_bin_px must be a positive int, got {self.centre_bin_px!r}"
            )

    def astype(self, dtype: jnp.dtype) -> SoftSettings:
        """The same settings with every continuous leaf an array of ``dtype``."""
        return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), self)
