"""sinkjax.torch: HSI segmentation parity with JAX, the DLPack/VJP bridge, kornia augmentations."""

from __future__ import annotations

import colorsys
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("kornia")

import sinkjax.torch as st  # noqa: E402
from sinkjax import SegmentationParams  # noqa: E402
from sinkjax.rig import rect_problem  # noqa: E402
from sinkjax.soft.colour import rgb_to_hsi as jax_rgb_to_hsi  # noqa: E402
from sinkjax.soft.estimator import measure_from_mask as jax_measure_from_mask  # noqa: E402
from sinkjax.soft.segmentation import paper_mask, smooth, soft_open, wheel_mask  # noqa: E402
from sinkjax.synth import recording_scenes, render, rig_for  # noqa: E402
from sinkjax.torch.bridge import _to_jax, _to_torch  # noqa: E402
from sinkjax.torch.jax_bridge import (  # noqa: E402
    estimate_values,
    measure_from_mask,
)

SIZE = 96


@pytest.fixture(scope="module")
def frames() -> tuple[np.ndarray, object]:
    """Two rendered 96x96 frames of one rig (float64 RGB (2, H, W, 3) in [0, 1]) and the rig."""
    scenes = recording_scenes(np.random.default_rng(3), 2, preset="full", width=SIZE, height=SIZE)
    imgs = np.stack([render(s, i)[0] for i, s in enumerate(scenes)]).astype(np.float64) / 255.0
    return imgs, rig_for(scenes[0])


def _chw(imgs: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(imgs).permute(0, 3, 1, 2).contiguous()


def _odd_params() -> SegmentationParams:
    return SegmentationParams(
        p_d_hue=0.93,
        p_a_hue=1.12,
        p_d_sat=0.4,
        p_a_sat=1.6,
        temperature_hue_deg=3.0,
        temperature_sat=0.05,
    )


def test_import_without_the_extra_names_it() -> None:
    code = (
        "import sys; sys.modules['kornia'] = None\n"
        "try:\n    import sinkjax.torch\nexcept ImportError as e:\n    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "pip install 'sinkjax[torch]'" in out.stdout


# ----------------------------------------------------------------------------- colour


def test_rgb_to_hsi_matches_jax_and_colorsys() -> None:
    rgb = np.random.default_rng(0).uniform(size=(2, 7, 5, 3))
    rgb[0, 0, 0] = 0.4  # grey
    rgb[0, 0, 1] = 0.0  # black
    hsi = st.rgb_to_hsi(torch.from_numpy(rgb).permute(0, 3, 1, 2)).permute(0, 2, 3, 1).numpy()
    ref = np.stack(jax_rgb_to_hsi(jnp.asarray(rgb)), -1)
    np.testing.assert_allclose(hsi, ref, rtol=0, atol=1e-10)
    # Independent reference: the HSI hue of a colour is its HSV hue to within the HSI/HSV
    # difference, which is exact at the six primaries and secondaries.
    for r, g, b in [(1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 1, 1), (0, 0, 1), (1, 0, 1)]:
        t = torch.tensor([[[[r]], [[g]], [[b]]]], dtype=torch.float64)
        assert float(st.rgb_to_hsi(t)[0, 0]) == pytest.approx(
            360.0 * colorsys.rgb_to_hsv(r, g, b)[0], abs=1e-9
        )


def test_rgb_to_hsi_gradients_finite_at_grey_and_black() -> None:
    x = torch.tensor([0.3, 0.3, 0.3, 0.0, 0.0, 0.0], dtype=torch.float64).reshape(2, 3, 1, 1)
    x.requires_grad_(True)
    st.rgb_to_hsi(x).sum().backward()
    assert torch.isfinite(x.grad).all()


def test_rgb_to_hsi_shapes_and_errors() -> None:
    assert st.RgbToHsi()(torch.rand(4, 3, 2, 5)).shape == (4, 3, 2, 5)
    assert st.rgb_to_hsi(torch.rand(3, 6, 6)).shape == (3, 6, 6)
    with pytest.raises(ValueError, match=r"\(\*, 3, H, W\). Got \(1, 4, 5, 5\)"):
        st.rgb_to_hsi(torch.rand(1, 4, 5, 5))
    with pytest.raises(TypeError):
        st.rgb_to_hsi(np.zeros((3, 4, 4)))  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- segmentation


@pytest.mark.parametrize("params", [SegmentationParams(), _odd_params()])
def test_soft_hsi_mask_matches_jax(frames, params) -> None:
    imgs, rig = frames
    got = st.soft_hsi_mask(_chw(imgs), params, rig.confidence_rect)
    assert got.shape == (2, 1, SIZE, SIZE) and got.dtype == torch.float64
    ref = np.stack([paper_mask(jnp.asarray(im), params, rig.confidence_rect) for im in imgs])
    assert np.abs(got[:, 0].numpy() - ref).max() <= 1e-5
    # Both sides are float64: the agreement is round-off, far inside the 1e-5 acceptance.
    assert np.abs(got[:, 0].numpy() - ref).max() <= 1e-9


def test_segmenter_module_parameters_and_gradients(frames) -> None:
    imgs, rig = frames
    seg = st.SoftHSISegmenter(rig.confidence_rect, _odd_params(), dtype=torch.float64)
    assert {n for n, _ in seg.named_parameters()} == set(st.SEG_FIELDS)
    assert seg.to_segmentation_params().as_dict() == pytest.approx(_odd_params().as_dict())
    x = _chw(imgs).requires_grad_(True)
    mask = seg(x)
    ref = st.soft_hsi_mask(x, _odd_params(), rig.confidence_rect)
    torch.testing.assert_close(mask, ref, rtol=0, atol=1e-12)
    mask.mean().backward()
    assert all(torch.isfinite(p.grad) and p.grad != 0 for p in seg.parameters())
    assert torch.isfinite(x.grad).all()

    # Threshold gradients against JAX's on the same mask statistic.
    def jax_stat(v):
        p = SegmentationParams(**{n: v[i] for i, n in enumerate(st.SEG_FIELDS)})
        return jnp.mean(
            jnp.stack([paper_mask(jnp.asarray(im), p, rig.confidence_rect) for im in imgs])
        )

    v0 = jnp.asarray([_odd_params().as_dict()[n] for n in st.SEG_FIELDS])
    g_jax = np.asarray(jax.grad(jax_stat)(v0))
    g_torch = np.array([float(getattr(seg, n).grad) for n in st.SEG_FIELDS])
    np.testing.assert_allclose(g_torch, g_jax, rtol=1e-8, atol=1e-12)


def test_segmenter_gradcheck_small() -> None:
    x = torch.rand(1, 3, 6, 7, dtype=torch.float64) * 0.5 + torch.tensor(
        [0.4, 0.25, 0.05], dtype=torch.float64
    ).view(1, 3, 1, 1)
    values = _odd_params().as_dict()
    params = {
        n: torch.tensor(values[n], dtype=torch.float64, requires_grad=True) for n in st.SEG_FIELDS
    }
    fn = lambda img, *ps: st.soft_hsi_mask(
        img, dict(zip(st.SEG_FIELDS, ps, strict=True)), (1, 1, 3, 3)
    )
    assert torch.autograd.gradcheck(fn, (x.requires_grad_(True), *params.values()))


def test_soft_hsi_mask_errors() -> None:
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\). Got \(3, 8, 8\)"):
        st.soft_hsi_mask(torch.rand(3, 8, 8), SegmentationParams(), (0, 0, 2, 2))
    with pytest.raises(ValueError, match="extends beyond the 8x8 image"):
        st.soft_hsi_mask(torch.rand(1, 3, 8, 8), SegmentationParams(), (6, 0, 4, 2))
    with pytest.raises(ValueError, match="lacks"):
        st.soft_hsi_mask(torch.rand(1, 3, 8, 8), {"p_d_hue": 0.9}, (0, 0, 2, 2))


def test_smooth_and_open_match_jax(frames) -> None:
    imgs, rig = frames
    m = st.soft_hsi_mask(_chw(imgs), SegmentationParams(), rig.confidence_rect)
    mj = [jnp.asarray(a) for a in m[:, 0].numpy()]
    np.testing.assert_allclose(
        st.smooth_mask(m)[:, 0].numpy(), np.stack([smooth(a) for a in mj]), rtol=0, atol=1e-12
    )
    for r in (1, 2):
        np.testing.assert_allclose(
            st.soft_open(m, r)[:, 0].numpy(),
            np.stack([soft_open(a, r) for a in mj]),
            rtol=0,
            atol=1e-12,
        )
    with pytest.raises(ValueError, match="radius_px"):
        st.soft_open(m, 0)
    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        st.smooth_mask(m[0])


# ----------------------------------------------------------------------------- augmentation


def test_lighting_augmentation() -> None:
    torch.manual_seed(0)
    aug = st.lighting_augmentation(p=1.0)
    x = torch.rand(2, 3, 32, 40)
    y = aug(x)
    assert y.shape == x.shape and float(y.min()) >= 0.0 and float(y.max()) <= 1.0
    assert not torch.allclose(x, y)
    with pytest.raises(ValueError, match="p must be"):
        st.lighting_augmentation(p=2.0)


@pytest.mark.parametrize(
    "rect",
    [
        (0, 0, 7, 5),
        (6, 4, 1, 1),
        (-1, 0, 2, 2),
        (0, -1, 2, 2),
        (0, 0, 0, 2),
        (0, 0, 2, 0),
        (6, 0, 2, 2),
        (0, 4, 2, 2),
        (0, 0, 7, 6),
        (0, 0, 2),
        (0, 0, 2.0, 2),
        (0, 0, True, 2),
    ],
)
def test_rect_rule_is_the_rigs(rect) -> None:
    """Torch accepts exactly the rectangles that cover a non-empty slice of a 7x5 image in full,
    and rejects the others with :func:`sinkjax.rig.rect_problem`'s message."""
    ints = len(rect) == 4 and all(type(v) is int for v in rect)
    pixels = np.zeros((5, 7))
    inside = (
        ints
        and min(rect[:2]) >= 0
        and min(rect[2:]) >= 1
        and pixels[rect[1] : rect[1] + rect[3], rect[0] : rect[0] + rect[2]].shape == rect[:1:-1]
    )
    images = torch.rand(1, 3, 5, 7, dtype=torch.float64)
    problem = rect_problem(rect, 5, 7)
    assert (problem is None) == inside
    if inside:
        assert st.soft_hsi_mask(images, SegmentationParams(), rect).shape == (1, 1, 5, 7)
        return
    for call in (
        lambda: st.soft_hsi_mask(images, SegmentationParams(), rect),
        lambda: st.measure_torch(images, seg=SegmentationParams(), rect=rect),
    ):
        with pytest.raises(ValueError) as info:
            call()
        assert str(info.value) == problem


# ----------------------------------------------------------------------------- bridge


def test_measure_torch_errors(frames) -> None:
    imgs, _ = frames
    x = _chw(imgs)
    with pytest.raises(ValueError, match=r"masks must have a shape of \(B, 1, H, W\)"):
        st.measure_torch(x, torch.zeros(2, SIZE, SIZE, dtype=torch.float64))
    with pytest.raises(ValueError, match="needs seg= and rect="):
        st.measure_torch(x)
    with pytest.raises(ValueError, match="travel"):
        st.measure_torch(x, torch.zeros(2, 1, SIZE, SIZE), travel="up")


def test_dlpack_shares_memory_when_it_can() -> None:
    x = torch.rand(2, 3, 4, 5, dtype=torch.float64)
    a = _to_jax(x, torch.float64)
    assert a.unsafe_buffer_pointer() == x.data_ptr()  # zero-copy
    b = _to_jax(x.float(), torch.float64)  # dtype mismatch: cast in torch, a copy
    np.testing.assert_allclose(np.asarray(b), x.float().double().numpy())
    back = _to_torch(a, x)
    assert back.data_ptr() == x.data_ptr() and torch.equal(back, x)


def test_measure_from_mask_shape_errors() -> None:
    # The estimator's own check says ValueError; under the test suite's runtime shape checks
    # jaxtyping catches the mismatched "H W" first and names the mask parameter.
    with pytest.raises((ValueError, TypeError), match=r"mask"):
        measure_from_mask(jnp.zeros((8, 8, 3)), jnp.zeros((8, 9)))


@pytest.fixture(scope="module")
def reference(frames) -> np.ndarray:
    """JAX's own soft estimate of both frames from the paper's band (the torch segmenter's
    mask), (2, 6): z0 mm, angles deg, and their sigmas."""
    imgs, rig = frames
    kw = dict(travel=rig.travel, wheel_radius_mm=rig.wheel_radius_mm)

    def one(im):
        mask = paper_mask(im, rig.segmentation, rig.confidence_rect)
        return estimate_values(jax_measure_from_mask(im, mask, **kw))

    fn = jax.jit(jax.vmap(one))
    return np.asarray(fn(jnp.asarray(imgs)))


@pytest.mark.heavy
@pytest.mark.slow
def test_bridge_from_mask(frames, reference) -> None:
    """One compiled bridge (images and masks, batch 2), several checks; compiling dominates.

    - torch segmenter + bridge give JAX's numbers on the paper's band (``measure_from_mask`` of
      ``paper_mask``: the torch masks are JAX's);
    - gradients are finite and reach the image and the six thresholds;
    - ``torch.autograd.gradcheck`` of (image, mask) -> (z0, theta1, theta2, sigmas), float64,
      along a random direction (fast mode: the full Jacobian would take 2 x 73728 solves);
    - full ``gradcheck`` of the six thresholds -> the six outputs, through torch and JAX.
    """
    imgs, rig = frames
    kw = dict(travel=rig.travel, wheel_radius_mm=rig.wheel_radius_mm)
    segmenter = st.SoftHSISegmenter(rig.confidence_rect, rig.segmentation, dtype=torch.float64)
    x = _chw(imgs).requires_grad_(True)
    masks = segmenter(x)
    est = st.MeasureFromMask(**kw)(x, masks)
    assert est.status.tolist() == [0, 0]
    got = torch.stack(est[:6], -1).detach().numpy()
    np.testing.assert_allclose(got, reference, rtol=1e-9, atol=1e-9)

    loss = (est.sinkage_mm + est.theta1_deg + est.theta2_deg + est.sinkage_std_mm).sum()
    loss.backward()
    assert torch.isfinite(x.grad).all() and float(x.grad.abs().sum()) > 0
    for p in segmenter.parameters():
        assert torch.isfinite(p.grad) and p.grad != 0, p

    # A frame with an empty mask: whatever it reports, the batch's backward must not raise, and
    # the other frame's gradient must be what it is alone.
    dead_masks = masks.detach().clone()
    dead_masks[1] = 0.0
    image2 = x.detach().clone().requires_grad_(True)
    est2 = st.measure_torch(image2, dead_masks, **kw)
    torch.nan_to_num(torch.stack(est2[:6], -1)).sum().backward()
    assert torch.isfinite(image2.grad).all()

    # Tolerances, measured (96x96, float64): central differences of the forward pass are stable
    # to 3 digits for eps from 1e-3 to 1e-8 (the map is smooth there), but the implicit-function
    # gradient is exact only at an exact optimum and the fit stops at rtol = atol = 1e-5: it
    # differs from the differences by 1e-5 to 8e-3 relative (0.2 % typical). Hence rtol 1e-2.
    image = x.detach().clone().requires_grad_(True)
    mask = masks.detach().clone().requires_grad_(True)

    def from_mask(im: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        return st.SinkageFromMask.apply(im, m, rig.travel, rig.wheel_radius_mm)[0]

    assert torch.autograd.gradcheck(
        from_mask, (image, mask), eps=1e-6, atol=1e-3, rtol=1e-2, fast_mode=True
    )

    params = [p.detach().clone().requires_grad_(True) for p in segmenter.parameters()]

    def from_params(*ps: torch.Tensor) -> torch.Tensor:
        m = st.soft_hsi_mask(
            image.detach(), dict(zip(st.SEG_FIELDS, ps, strict=True)), rig.confidence_rect
        )
        return st.SinkageFromMask.apply(image.detach(), m, rig.travel, rig.wheel_radius_mm)[0]

    # atol: that ~1e-3 relative error is relative to the Jacobian's scale (entries up to ~7 deg
    # per unit of temperature_sat), so near-zero entries miss by ~1.3e-3 absolute (measured).
    assert torch.autograd.gradcheck(from_params, params, eps=1e-6, atol=1e-2, rtol=1e-2)


@pytest.mark.heavy
@pytest.mark.slow
def test_bridge_from_image(frames) -> None:
    """measure_torch without masks: JAX segments (``wheel_mask``: the paper's band and the
    reference veto), so the reference is JAX's own estimate from that mask; gradients reach the
    thresholds."""
    imgs, rig = frames
    kw = dict(travel=rig.travel, wheel_radius_mm=rig.wheel_radius_mm)

    def one(im):
        mask = wheel_mask(im, rig.segmentation, rig.confidence_rect)
        return estimate_values(jax_measure_from_mask(im, mask, **kw))

    reference = np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(imgs)))
    # The band's thresholds (SEG_FIELDS); the soil/background veto keeps the rig's default.
    values = rig.segmentation.as_dict()
    seg = {
        n: torch.tensor(values[n], dtype=torch.float64, requires_grad=True) for n in st.SEG_FIELDS
    }
    est = st.measure_torch(
        _chw(imgs),
        seg=seg,
        rect=rig.confidence_rect,
        travel=rig.travel,
        wheel_radius_mm=rig.wheel_radius_mm,
    )
    np.testing.assert_allclose(
        torch.stack(est[:6], -1).detach().numpy(), reference, rtol=1e-9, atol=1e-9
    )
    est.sinkage_mm.sum().backward()
    assert all(torch.isfinite(v.grad) for v in seg.values())


def test_bridge_compiles_once_for_every_rig_of_an_image_size(frames) -> None:
    """The rig's numbers are traced arguments: two more rigs of the same image size (other
    rectangle, travel, radius) compile nothing, and the sinkage and its sigma scale with the
    wheel's radius (z0 = z0_px R / r) while the angles stay."""
    import sinkjax.torch.jax_bridge as bridge

    imgs, rig = frames
    images = _chw(imgs)
    values = rig.segmentation.as_dict()
    seg = {n: float(values[n]) for n in st.SEG_FIELDS}  # no gradient: the forward function

    def run(rect, travel, radius):
        return st.measure_torch(images, seg=seg, rect=rect, travel=travel, wheel_radius_mm=radius)

    a = run(rig.confidence_rect, rig.travel, rig.wheel_radius_mm)
    forward = bridge.from_image_batch(None, 0).forward  # the one SinkageFromImage runs
    compiled = forward._cache_size()
    b = run(rig.confidence_rect, rig.travel, 2.0 * rig.wheel_radius_mm)
    x, y, w, h = rig.confidence_rect
    other = "left" if rig.travel == "right" else "right"
    c = run((x + 1, y + 1, w - 2, h - 2), other, 0.5 * rig.wheel_radius_mm)
    assert compiled >= 1 and forward._cache_size() == compiled
    ok = (a.status == 0).numpy()
    assert ok.sum() >= 2 and np.array_equal(b.status.numpy(), a.status.numpy())
    for field in ("sinkage_mm", "sinkage_std_mm"):
        np.testing.assert_allclose(
            getattr(b, field).numpy()[ok], 2.0 * getattr(a, field).numpy()[ok], rtol=1e-9
        )
    for field in ("theta1_deg", "theta2_deg", "theta1_std_deg", "theta2_std_deg"):
        np.testing.assert_allclose(getattr(b, field).numpy(), getattr(a, field).numpy(), rtol=1e-9)
    assert c.status.shape == a.status.shape
