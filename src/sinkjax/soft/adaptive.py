"""The default segmenter: hue and saturation for a coloured wheel, intensity, chroma and texture
for a black or bare-metal one, chosen per frame from the confidence rectangle.

The paper's H/S test needs a wheel with colour. A black (rubber, 3D-printed) or bare-aluminium
wheel has a saturation at the noise level (S_w ~ 0.04), so its H_w is noise and the H/S bands
select noise. The rectangle's mean chroma vector (saturation times the unit hue direction,
averaged: noise averages out, a real tint does not) says which case a frame is:

- at least ``min_wheel_chroma``: the paper's test, exactly
  :func:`~sinkjax.soft.segmentation.wheel_mask` (the same numbers as before), of the frame
  blurred first where sensor noise drowns a dim wheel's hue (:mod:`~sinkjax.soft.denoise`);
- below: a soft distance in a small feature space, each feature scaled by the rectangle's own
  statistics (the paper's P_a/P_d generalised).

  - Intensity: the wheel is the side of a threshold on which the rectangle's mean I_w lies:
    darker than the frame for a black wheel, brighter for a metal one. For a black wheel the
    threshold is the paper-style ``p_a_int * I_w + int_floor`` (its shaded side is darker
    still), or the valley of the frame's log-intensity histogram between I_w and that, where
    there is one: a cast shadow on the soil is darker than the lit soil but brighter than the
    wheel, a population of its own that a fixed fraction of I_w would cut through (taken only
    where the histogram rises again beyond the valley: a glow on the wheel's face is a falling
    tail, not a population). A metal wheel under one-sided light spans a factor of three in
    brightness, its shaded side near the background's, so no fixed fraction of I_w separates
    them; its threshold sits in the valley of the frame's log-intensity histogram between the
    wheel's population and the background's nearest below it, where the fewest pixels are
    (searched between ``0.1 I_w`` and ``p_d_int * I_w``).
  - Chroma: the opponent colour (R - (G + B)/2, sqrt(3)/2 (G - B)) stays within ``p_chroma``
    times a floor of the rectangle's spread of it (brown soil, however dark, has chroma; so has a
    black wheel's shadow on grey soil, lit by the tinted sky alone, where the wheel's own chroma
    is only its albedo's few percent of that tint). For a metal wheel, the chroma divided by the
    intensity (chromaticity; ``soft.grey_features``): the wheel's shadow on brown soil is nearly
    as grey as the wheel in chroma, not in chromaticity. A clipped pixel (a channel at the
    sensor's top) has lost its chroma and is not judged by it.
  - Texture: the local intensity spread after removing the window's own plane (shading is a
    gradient, not texture), the smallest of four one-sided windows (so that an edge does not
    count as texture on either side), stays under ``p_tex`` times the rectangle's (sand has
    grain, rubber and metal do not).

With the recording's rim known (:meth:`AdaptiveSegmenter.with_rim`, which the soft method uses once
a recording's rim is found), a metal wheel's intensity threshold inside the rim comes from the
inside's own histogram: only wheel and soil can be there, not the background, so the threshold goes
to the valley just under the wheel's population (its shaded side included, however dark): the
highest clear valley, with the face's whole population on its bright side, not a deeper one between
its holes and the soil in its shadow (:func:`~sinkjax.soft.histogram.deepest_valley` with ``reach``;
none: all of the inside passes the intensity test and chroma and texture alone part wheel from
soil). It is used only where that rule still calls the soil below the rim (the frame's bottom rows
under the circle) soil. Else, for a lit soil nearly as bright as the wheel's shaded side (grey
sand), the threshold goes to the valley between the soil below the rim and the wheel, in the
histogram of both (searched from the soil's median up to I_w, the face's whole population counted),
inside the rim and beyond it (no lower than the frame's own there), where that calls the soil below
soil; else the frame's own threshold stays. Beyond the rim below its centre, where only soil and
lugs can be, the texture limit is at most ``p_tex_rim`` times the face's own 95th percentile (the
upper half of the inside), on the texture averaged over 11 px windows (:func:`pooled_texture`): lit
grey sand as bright as the face, under the frame's texture limit, is still rougher than the face,
and averaged its few grains as smooth as the face no longer make patches of "wheel" (the narrow lugs
there, rough at both their edges, are lost too; they are not measured). A black wheel's threshold
below the rim's centre comes from its shading-corrected face (:mod:`~sinkjax.soft.dark_face`): the
wheel's cast shadow on the soil can be as dark as its lit side, but not as dark as the face just
above it where they meet.

The switch is a ``lax.cond`` on traced values: one compiled function serves every wheel. The
branch not taken gets no gradient; the thresholds and temperatures are array leaves.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..rig import CLIP_LEVEL, MIN_WHEEL_CHROMA, SegmentationParams
from .colour import rgb_to_hsi
from .dark_face import corrected_edge
from .denoise import RATIO_OFF, applied_blur_px, denoise, noise_ratio
from .grey_features import (
    chroma_distance,
    chromaticity_distance,
    face_texture as face_texture,
    pooled_texture as pooled_texture,
    safe_norm,
    texture as texture,
)
from .histogram import (
    deepest_valley,
    log_histogram,
    log_quantile,
    valley,
    valley_depth,
)
from .segmentation import HueSat, Rect, colour_box, colour_weight, smooth, wheel_mask
from .segmenter import FEATURES_HUE_SAT, FEATURES_INTENSITY, Disc, Segmenter, rect_weight

_SQRT3_2 = 0.8660254037844386
_POOL_PX = 11  # beyond the rim below its centre: texture averaged over windows this wide
_POOL_SHARPEN = 4.0


# A black wheel's threshold moves down to a valley of the histogram only where the population
# beyond it (up to this factor past the paper-style threshold) outnumbers the valley's bin by
# at least this much: a cast shadow on the soil, not the wheel's own glow.
_DARK_RISE = 2.0
_DARK_RISE_SPAN = 1.3
# The inside of a recording's rim sets its own threshold only with this many pixels in it (and
# as many in the soil below the rim to check it on).
_MIN_DISC_PX = 400.0
_SOIL_GAP_PX = 2.0  # the soil asked: below the rim, this far clear of it (its edge blur)
_MAX_SOIL_AS_WHEEL = 0.05  # the inside's rule is kept if it calls at most this share wheel


def wheel_chroma(
    image: Float[Array, "H W 3"], weight: Float[Array, "H W"], hs: HueSat | None = None
) -> Float[Array, ""]:
    """The length of the mean (S cos H, S sin H) over ``weight``: the wheel's colourfulness in
    saturation units, with the hue noise of a grey wheel averaged out. ``hs``: the image's hue
    (degrees) and saturation when the caller has them already."""
    h_deg, s = rgb_to_hsi(image)[:2] if hs is None else hs
    rad = jnp.radians(h_deg)
    total = jnp.maximum(jnp.sum(weight), 1.0)
    c = jnp.sum(weight * s * jnp.cos(rad)) / total
    d = jnp.sum(weight * s * jnp.sin(rad)) / total
    return safe_norm(c, d)


class AdaptiveSegmenter(Segmenter):
    """The default segmenter (module docstring): the paper's H/S mask for a coloured wheel, an
    intensity/chroma/texture mask for a black or metal one; no setting needed for either.

    ``seg``: the H/S test's parameters. The grey branch's leaves: ``p_a_int`` and ``int_floor``
    (a black wheel's intensity threshold ``p_a_int * I_w + int_floor`` where no valley is
    used), ``p_valley`` (a factor on a threshold found in the histogram's valley, a metal wheel's
    or a black one's; 1 by default), ``t_int`` (the intensity sigmoid's width, relative),
    ``p_chroma`` and ``chroma_floor`` (a black wheel's chroma radius is
    ``p_chroma * max(rectangle chroma spread, chroma_floor)``, RGB units), ``metal_chroma_floor``
    (a metal wheel's chromaticity radius is ``p_chroma * max(rectangle chromaticity spread,
    metal_chroma_floor / I_w)``), ``t_chroma`` (its sigmoid's width; a black wheel's:
    ``t_chroma_dark``),
    ``p_tex`` and ``tex_floor`` (texture limit ``p_tex * max(rectangle texture, tex_floor)``,
    intensity units), ``t_tex``, ``p_tex_rim`` (with the rim known, beyond it below its centre:
    at most ``p_tex_rim`` times the face's 95th percentile). Not differentiable:
    ``min_wheel_chroma`` (the switch) and ``p_d_int`` (the top of the valley's search: a metal
    wheel's threshold is at most ``p_d_int * I_w``).
    """

    seg: SegmentationParams = SegmentationParams()
    min_wheel_chroma: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=MIN_WHEEL_CHROMA)
    p_a_int: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=1.6)
    int_floor: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.03)
    p_d_int: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.6)
    p_valley: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=1.0)
    t_int: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.08)
    p_chroma: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=3.0)
    # A black wheel's chroma radius at least 3 x 0.008: the shadow it casts on the soil, lit by
    # the sky alone, is tinted by it (opponent chroma 0.02-0.05 where the wheel's own stays under
    # 0.01), and 3 x 0.012 let half of it pass as wheel; at 0.004 the wheel's own chroma (glows,
    # tinted shading, JPEG's 8 px chroma blocks) fails it (experiments/black_wheels.py).
    chroma_floor: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.008)
    metal_chroma_floor: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.012)
    t_chroma: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.008)
    # The black wheel's chroma sigmoid keeps its former width-to-radius ratio (0.008 to
    # 3 x 0.012): at 0.008 to 3 x 0.008, its product with the intensity sigmoid pulls the mask's
    # 0.5 level into the wheel at its edge against a tinted sky.
    t_chroma_dark: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.024 * 2 / 9)
    p_tex: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=3.0)
    tex_floor: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.006)
    t_tex: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.002)
    p_tex_rim: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=1.3)

    def coloured(
        self,
        image: Float[Array, "H W 3"],
        rect: Rect,
        hs: HueSat | None = None,
        box: Int[Array, " 4"] | None = None,
    ) -> Bool[Array, ""]:
        """True (as a 0-d bool array) when the wheel has enough colour for the H/S test.
        ``hs``: the image's hue and saturation, ``box`` its :func:`colour_box`, when the caller
        has them already."""
        # The rectangle's unclipped pixels: a glow's white has no chroma, the face around it has.
        weight = colour_weight(image, rect, box)
        return wheel_chroma(image, weight, hs) >= self.min_wheel_chroma

    def features(self, image: Float[Array, "H W 3"], rect: Rect) -> Int[Array, ""]:
        return jnp.where(self.coloured(image, rect), FEATURES_HUE_SAT, FEATURES_INTENSITY).astype(
            jnp.int32
        )

    def _edge(
        self,
        histogram: tuple[Array, Array],
        i_w: Float[Array, ""],
        dark: Bool[Array, ""],
    ) -> Float[Array, ""]:
        """The intensity threshold from a log-intensity ``histogram`` (bins, centres).

        Black: the paper-style threshold p_a_int * I_w + int_floor (its shaded side is darker
        still), or a valley below it. Metal: the histogram's valley below I_w (module
        docstring), at most p_d_int * I_w."""
        hist, centres = histogram
        ceiling = self.p_d_int * i_w
        found = valley(hist, centres, jnp.log(0.1 * i_w), jnp.log(ceiling), jnp.asarray(True))
        # A black wheel: the paper-style threshold, or lower where the histogram has a valley
        # between I_w and it (a cast shadow on the soil, darker than lit soil but brighter than
        # the wheel, is its own population: the threshold goes between it and the wheel).
        paper = self.p_a_int * i_w + self.int_floor
        found_dark = valley(hist, centres, jnp.log(i_w), jnp.log(paper), jnp.asarray(False))
        # Only a valley with a population beyond it (a shadow); on a wheel's own bright tail (a
        # lamp's glow on the face) the emptiest bin means nothing.
        deep = valley_depth(hist, centres, found_dark, _DARK_RISE_SPAN * paper) >= _DARK_RISE
        found = jnp.where(dark, found_dark, found)
        return jnp.where(dark & ~deep, paper, self.p_valley * jax.lax.stop_gradient(found))

    def grey_mask(
        self, image: Float[Array, "H W 3"], rect: Rect, disc: Disc | None = None
    ) -> Float[Array, "H W"]:
        """The intensity/chroma/texture mask alone (the branch for a wheel without colour);
        ``disc``: the inside of the recording's rim (:meth:`with_rim`), None: not known."""
        weight = rect_weight(rect, image.shape[0], image.shape[1], image.dtype)
        total = jnp.maximum(jnp.sum(weight), 1.0)

        def rect_mean(a: Array) -> Array:
            return jnp.sum(weight * a) / total

        r, g, b = image[..., 0], image[..., 1], image[..., 2]
        # Smoothed features (sigma ~ 1 px): sensor noise would otherwise salt a dark wheel's
        # chroma; the blur is symmetric, so edges stay where they are.
        intensity = smooth((r + g + b) / 3.0)
        q1 = smooth(r - 0.5 * (g + b))
        q2 = smooth(_SQRT3_2 * (g - b))
        tex = texture((r + g + b) / 3.0)

        i_w = rect_mean(intensity)
        # +1: the wheel is darker than the frame on average (black), -1: brighter (metal).
        dark = i_w <= jnp.mean(intensity)
        side = jnp.where(dark, 1.0, -1.0)
        still = jax.lax.stop_gradient(intensity)

        def by_intensity(edge: Array) -> Array:
            return jax.nn.sigmoid(side * (edge - intensity) / (self.t_int * edge))

        # A black wheel: chroma (a dark wheel's chromaticity is noise). A metal one:
        # chromaticity, which a shadow on brown soil keeps (grey_features).
        dist_q, spread_q = chroma_distance(q1, q2, weight)
        dist_r, spread_r = chromaticity_distance(q1, q2, intensity, weight)
        radius_q = self.p_chroma * jnp.maximum(spread_q, self.chroma_floor)
        lit = jnp.maximum(i_w, 1e-3)  # the face's intensity: chromaticity units to RGB units
        radius_r = self.p_chroma * jnp.maximum(spread_r, self.metal_chroma_floor / lit)
        m_chroma = jnp.where(
            dark,
            jax.nn.sigmoid((radius_q - dist_q) / self.t_chroma_dark),
            jax.nn.sigmoid((radius_r - dist_r) * lit / self.t_chroma),
        )
        # A clipped channel (a highlight, an over-exposed face) leaves no chroma to judge.
        clipped = jax.nn.sigmoid((smooth(jnp.max(image, axis=-1)) - CLIP_LEVEL) / 0.01)
        m_chroma = 1.0 - (1.0 - m_chroma) * (1.0 - clipped)

        limit_tex = self.p_tex * jnp.maximum(rect_mean(tex), self.tex_floor)
        # Only a bright wheel needs texture (grey sand can be as bright as shaded metal); on a
        # dark one it would only cut away the thin grousers.
        m_tex = jnp.where(dark, 1.0, jax.nn.sigmoid((limit_tex - tex) / self.t_tex))
        edge = self._edge(log_histogram(still), i_w, dark)
        mask = by_intensity(edge) * m_chroma * m_tex
        if disc is None:
            return mask
        # A metal wheel: inside the recording's rim only wheel and soil can be, so the
        # intensity threshold there comes from the histogram of the inside alone, at its
        # deepest valley (between the wheel and the soil or its shadow), not from the
        # background around the wheel (the wheel's shaded side can be as dark as a grey sky).
        # Used only where that rule still calls the soil below the rim soil (chroma or texture
        # part them). Else the valley between the soil below the rim and the wheel, in the
        # histogram of both: a lit soil nearly as bright as the wheel's shaded side (grey
        # sand) lies above the first search's top, and so does the valley that parts it from
        # the wheel; that threshold holds beyond the rim too (the same soil), where the frame's
        # own is not higher (a background brighter than the soil). Used where it calls the soil
        # below soil; else, or with no soil below the rim in the frame to ask, the frame's own
        # threshold stays. (A black wheel: dark_rule below.)
        cx, cy, rho = disc

        def inside_rule() -> Array:
            rows = jnp.arange(intensity.shape[0], dtype=intensity.dtype)[:, None]
            cols = jnp.arange(intensity.shape[1], dtype=intensity.dtype)[None, :]
            inside = (cols - cx) ** 2 + (rows - cy) ** 2 < rho * rho
            inside_px = inside.astype(intensity.dtype)
            below = jnp.broadcast_to(rows > cy + rho + _SOIL_GAP_PX, mask.shape)
            below_px = jnp.sum(below.astype(mask.dtype))
            enough = (jnp.sum(inside_px) >= _MIN_DISC_PX) & (below_px >= _MIN_DISC_PX)
            # Beyond the rim below its centre (where the soil is) only lugs are wheel: texture
            # no rougher than the face's own, averaged (its spread narrower: a sharper sigmoid).
            upper = (inside & (rows < cy) & (mask > 0.5)).astype(intensity.dtype)
            face_tex = face_texture(tex, upper)
            rough = pooled_texture(tex, _POOL_PX)
            tight = jax.nn.sigmoid(_POOL_SHARPEN * (self.p_tex_rim * face_tex - rough) / self.t_tex)
            m_tex_rim = jnp.where(inside | (rows < cy), m_tex, jnp.minimum(m_tex, tight))

            def with_edge(found: Array) -> tuple[Array, Array]:
                # The mask at this threshold, and whether it calls the soil below the rim soil.
                m = by_intensity(self.p_valley * jax.lax.stop_gradient(found)) * m_chroma
                m = m * m_tex_rim
                wheel_below = jnp.sum(jnp.where(below, m, 0.0)) / jnp.maximum(below_px, 1.0)
                return m, enough & (jax.lax.stop_gradient(wheel_below) <= _MAX_SOIL_AS_WHEEL)

            hist_in, centres = log_histogram(still, inside_px)
            lo, hi = jnp.log(0.1 * i_w), jnp.log(self.p_d_int * i_w)
            mask_in, use_in = with_edge(deepest_valley(hist_in, centres, lo, hi, jnp.log(i_w))[0])
            hist_below, _ = log_histogram(still, below.astype(intensity.dtype))
            soil = log_quantile(hist_below, centres, 0.5)
            zero = jnp.zeros((), intensity.dtype)  # log 1: the brightest the face can be
            found, parted = deepest_valley(hist_in + hist_below, centres, soil, jnp.log(i_w), zero)
            mask_soil, use_soil = with_edge(found)
            beyond = by_intensity(jnp.maximum(edge, self.p_valley * jax.lax.stop_gradient(found)))
            mask_soil = jnp.where(inside, mask_soil, beyond * m_chroma * m_tex_rim)
            base = by_intensity(edge) * m_chroma * m_tex_rim
            out = jnp.where(inside & use_in, mask_in, base)
            return jnp.where(~use_in & parted & use_soil, mask_soil, out)

        def dark_rule() -> Array:
            # A black wheel: its threshold from its shading-corrected face (soft.dark_face),
            # which parts it from a cast shadow the frame's threshold runs through.
            corr, face, apply = corrected_edge(intensity, mask, edge, disc)
            low = jnp.where(apply, jnp.minimum(edge, self.p_valley * corr), edge)
            gap = jnp.maximum(low - face, 1e-3)
            width = self.t_int * gap / jnp.maximum(self.p_a_int - 1.0, 0.05)
            lower = jax.nn.sigmoid((low - intensity) / width) * m_chroma * m_tex
            return jnp.where(apply, lower, mask)

        # Skipped (not computed) where no rim is known (radius 0).
        return jax.lax.cond(
            rho <= 0.0,
            lambda: mask,
            lambda: jax.lax.cond(dark, dark_rule, inside_rule),
        )

    def __call__(self, image: Float[Array, "H W 3"], rect: Rect) -> Float[Array, "H W"]:
        return self._mask(image, rect, None)

    def blur_px(self, image: Float[Array, "H W 3"], rect: Rect) -> Float[Array, ""]:
        # A dim coloured wheel's frame is blurred as its noise asks (soft.denoise).
        return jnp.where(self.coloured(image, rect), applied_blur_px(image, rect), 0.0)

    def uses_rim(self, features: int) -> bool:
        return features == FEATURES_INTENSITY  # the H/S mask does not use the rim

    def with_rim(self, image: Float[Array, "H W 3"], rect: Rect, disc: Disc) -> Float[Array, "H W"]:
        # A coloured wheel's H/S mask does not change; a grey one's intensity threshold inside
        # the rim comes from the inside alone, or a black one's from its face (grey_mask).
        return self._mask(image, rect, disc)

    def _mask(self, image: Float[Array, "H W 3"], rect: Rect, disc: Disc | None) -> Array:
        # lax.cond: per frame on a CPU only the branch taken runs (the grey features cost
        # about 40 % of a frame); under vmap it becomes a select of both, as jnp.where would.
        # One HSI conversion serves the switch and the H/S band.
        hs = rgb_to_hsi(image)[:2]
        box = colour_box(image, rect)
        return jax.lax.cond(
            self.coloured(image, rect, hs, box),
            lambda: self._hs_mask(image, rect, hs, box),
            lambda: self.grey_mask(image, rect, disc),
        )

    def _hs_mask(self, image: Array, rect: Rect, hs: HueSat, box: Array) -> Array:
        # The H/S mask, of the frame blurred as its noise asks where a dim wheel's hue is
        # drowned in it (soft.denoise); else of the frame itself, exactly.
        ratio = noise_ratio(image, rect)
        return jax.lax.cond(
            ratio > RATIO_OFF,
            lambda: wheel_mask(denoise(image, rect, ratio), self.seg, rect),
            lambda: wheel_mask(image, self.seg, rect, hs=hs, box=box),
        )


def default_segmenter(seg: SegmentationParams) -> Segmenter:
    """The soft method's segmenter when none is given, with a rig's H/S thresholds ``seg``:
    :class:`AdaptiveSegmenter`, which on a coloured wheel is the paper's H/S mask (the same
    estimates to float rounding) and also sees black wheels."""
    return AdaptiveSegmenter(seg)
