"""Depth Anything wrapper (tiny random-weight model, real loading path) and depth calibration."""
import numpy as np
import pytest
import torch

from tiny_models_fixture import one_thread, tiny_models  # noqa: F401

import gs_regional
from gs_regional.depth.calibration import calibrated_depth, robust_affine, transfer_depth
from gs_regional.depth.depth_anything import DepthAnything, dpt_resize_size
from gs_regional.utils.pretrained import PretrainedLoadError

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def depth(tiny_models):
    return DepthAnything({"pretrained": tiny_models["depth_anything"]})


def test_disparity_at_input_resolution(depth):
    assert gs_regional.find("depth-anything") is DepthAnything
    x = torch.rand(2, 36, 44, 3, generator=torch.Generator().manual_seed(0))  # not multiples of 14
    assert depth.input_size(36, 44) == (42, 56)
    d = depth.disparity(x)
    assert d.shape == (2, 36, 44) and d.dtype == torch.float32
    assert torch.isfinite(d).all() and float(d.min()) > 0
    assert not torch.allclose(d[0], d[1])  # depends on the image
    assert torch.allclose(depth.disparity(x[:1]), d[:1], atol=1e-5)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        depth.disparity(x * 3)


def test_resize_rule_matches_transformers():
    from transformers.models.dpt.image_processing_pil_dpt import get_resize_output_image_size

    for h, w, size in [(36, 44, 56), (512, 512, 518), (480, 640, 518), (1080, 1920, 518), (700, 300, 518)]:
        ref = get_resize_output_image_size(np.zeros((3, h, w)), (size, size), keep_aspect_ratio=True, multiple=14)
        assert dpt_resize_size(h, w, size, size, True, 14) == (ref.height, ref.width)


def test_preprocessing_matches_the_image_processor(depth, tiny_models):
    """Torch preprocessing follows the processor config: same size and, up to resampling
    differences, the same normalised values as transformers' own (PIL) processor."""
    from transformers import AutoImageProcessor

    proc = AutoImageProcessor.from_pretrained(tiny_models["depth_anything"])
    g = torch.Generator().manual_seed(1)
    smooth = torch.nn.functional.interpolate(torch.rand(1, 3, 6, 8, generator=g), size=(60, 80), mode="bilinear")
    pixels = (smooth[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    ref = torch.as_tensor(np.asarray(proc(images=pixels, return_tensors="np")["pixel_values"]))
    ours = depth.preprocess(torch.from_numpy(pixels).float()[None] / 255)
    assert ours.shape == ref.shape == (1, 3, 56, 70)  # "scale as little as possible": fit the height
    assert (ours - ref).abs().mean() < 0.02


def test_not_a_depth_model(tiny_models, tmp_path):
    with pytest.raises(PretrainedLoadError, match="not a depth-estimation model"):
        DepthAnything({"pretrained": tiny_models["clip"]})
    with pytest.raises(PretrainedLoadError, match="config.json"):
        DepthAnything({"pretrained": str(tmp_path)})


# ---------------------------------------------------------------------------------------- calibration


def synthetic_disparity(seed=0, n=64):
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, n), torch.linspace(0, 1, n), indexing="ij")
    mono = 0.2 + 0.5 * xx + 0.3 * torch.sin(3 * yy) + 0.05 * torch.rand(n, n, generator=g)
    return mono.double(), g


def test_robust_affine_recovers_scale_and_shift_exactly():
    mono, _ = synthetic_disparity()
    a, b = 2.7, 0.35
    ref = a * mono + b
    fit = robust_affine(mono, ref, torch.ones_like(mono, dtype=torch.bool))
    assert fit == pytest.approx((a, b), rel=1e-5)
    # Only the given pixels count: garbage elsewhere is ignored.
    pixels = torch.zeros_like(mono, dtype=torch.bool)
    pixels[:, :40] = True
    ref2 = torch.where(pixels, ref, torch.full_like(ref, 50.0))
    assert robust_affine(mono, ref2, pixels) == pytest.approx((a, b), rel=1e-5)
    # The paper's plain estimator (no re-estimation) is exact too on clean data.
    assert robust_affine(mono, ref, torch.ones_like(pixels), reject=0) == pytest.approx((a, b), rel=1e-5)


@pytest.mark.parametrize("corrupt", ["ref", "mono"])
def test_robust_affine_with_20_percent_outliers(corrupt):
    mono, g = synthetic_disparity(seed=2)
    a, b = 1.8, 0.4
    ref = a * mono + b + 0.002 * torch.randn(mono.shape, generator=g, dtype=torch.float64)  # mild noise
    outliers = torch.rand(mono.shape, generator=g) < 0.2
    large = 20 + 80 * torch.rand(mono.shape, generator=g, dtype=torch.float64)
    if corrupt == "ref":
        ref = torch.where(outliers, large, ref)
    else:
        mono = torch.where(outliers, large, mono)
    pixels = torch.ones_like(mono, dtype=torch.bool)
    fa, fb = robust_affine(mono, ref, pixels)
    assert fa == pytest.approx(a, rel=0.02) and fb == pytest.approx(b, rel=0.02)
    # The plain mean-absolute-deviation estimator is far off here: the re-estimation is what helps.
    pa, _ = robust_affine(mono, ref, pixels, reject=0)
    assert abs(pa / a - 1) > 0.2


def test_robust_affine_errors():
    x = torch.rand(8, 8)
    with pytest.raises(ValueError, match="same shape"):
        robust_affine(x, x[:4], torch.ones(8, 8, dtype=torch.bool))
    with pytest.raises(ValueError, match="at least 2"):
        robust_affine(x, x, torch.zeros(8, 8, dtype=torch.bool))
    with pytest.raises(ValueError, match="constant"):
        robust_affine(torch.ones(8, 8), x, torch.ones(8, 8, dtype=torch.bool))


def test_calibrated_and_transferred_depth():
    mono = torch.tensor([0.5, 1.0, 2.0, -10.0])
    d = calibrated_depth(mono, a=2.0, b=1.0)
    assert torch.allclose(d[:3], torch.tensor([0.5, 1 / 3, 0.2]))
    assert d[3] == pytest.approx(1e6)  # non-positive disparity: clamped, placed very far
    # The estimator sees the edited surface 20% nearer; the scene depth is scaled accordingly.
    d_3dgs = torch.tensor([[2.0, 4.0]])
    out = transfer_depth(torch.tensor([[0.8, 1.5]]), torch.tensor([[1.0, 1.5]]), d_3dgs)
    assert torch.allclose(out, torch.tensor([[1.6, 4.0]]))
