"""The bottom-floor helpers every layer shares: rotations, SH colour conversion, image checks."""
import math

import numpy as np
import pytest
import torch

from gs_regional.utils.image import check_cameras, check_images, dilate, gaussian_blur, resize, to_nchw
from gs_regional.utils.rotations import quat_to_rotmat, rotmat_to_quat
from gs_regional.utils.sh import SH_C0, rgb_to_sh, sh_to_rgb


def test_quat_to_rotmat_is_a_rotation():
    r = quat_to_rotmat(torch.randn(5, 4))
    torch.testing.assert_close(r @ r.transpose(1, 2), torch.eye(3).expand(5, 3, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.det(r), torch.ones(5))
    assert torch.equal(quat_to_rotmat(torch.tensor([2.0, 0, 0, 0])), torch.eye(3))
    np.testing.assert_allclose(quat_to_rotmat(torch.tensor([math.cos(0.5), 0, 0, math.sin(0.5)]))[:2, :2].numpy(),
                               [[math.cos(1), -math.sin(1)], [math.sin(1), math.cos(1)]], atol=1e-6)


def test_rotmat_to_quat_inverts_quat_to_rotmat_including_half_turns():
    q = torch.nn.functional.normalize(torch.randn(64, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64), dim=-1)
    # Half turns (w = 0) about an axis and about a diagonal: the trace formula alone breaks down there.
    q = torch.cat([q, torch.tensor([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], [0.0, 0.6, 0.8, 0.0]], dtype=torch.float64)])
    back = rotmat_to_quat(quat_to_rotmat(q))
    assert (back[:, 0] >= 0).all()
    # q and -q are the same rotation; the result picks w >= 0. float64 round trip: 1e-12 is ample.
    same = torch.minimum((back - q).abs().amax(-1), (back + q).abs().amax(-1))
    assert same.max() < 1e-12
    # Leading batch dimensions are kept: (2, 3, 3, 3) -> (2, 3, 4).
    R = quat_to_rotmat(q[:6]).reshape(2, 3, 3, 3)
    assert rotmat_to_quat(R).shape == (2, 3, 4)
    assert rotmat_to_quat(torch.eye(3, dtype=torch.float64)).tolist() == [1.0, 0.0, 0.0, 0.0]


def test_rgb_sh_round_trip():
    rgb = torch.rand(10, 3)
    torch.testing.assert_close(sh_to_rgb(rgb_to_sh(rgb)), rgb)
    assert rgb_to_sh(torch.tensor(0.5)) == 0 and sh_to_rgb(torch.tensor(1.0)) == pytest.approx(0.5 + SH_C0)


def test_check_images_batches_and_rejects_with_the_argument_name():
    x = torch.rand(8, 8, 3)
    assert check_images(x).shape == (1, 8, 8, 3)
    with pytest.raises(ValueError, match=r"cond_images must have shape \(B, H, W, 3\), got \(1, 8, 8, 4\)"):
        check_images(torch.rand(1, 8, 8, 4), "cond_images")
    with pytest.raises(TypeError, match="images must be a torch.Tensor"):
        check_images(x.numpy())
    with pytest.raises(TypeError, match="float"):
        check_images((x * 255).to(torch.uint8))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        check_images(x + 2)


def test_check_cameras():
    assert check_cameras(None, 3, "f") is None
    assert check_cameras(("a", "b"), 2, "f") == ["a", "b"]
    with pytest.raises(ValueError, match="f: 2 images but 1 cameras"):
        check_cameras(["a"], 2, "f")
    with pytest.raises(ValueError, match=r"f needs cameras=\[one Camera per image\]"):
        check_cameras(None, 2, "f", required=True)


def test_blur_dilate_resize():
    flat = torch.full((2, 9, 7), 0.25)
    torch.testing.assert_close(gaussian_blur(flat, 1.5), flat)  # a normalised kernel keeps constants
    dot = torch.zeros(1, 9, 9)
    dot[0, 4, 4] = 1
    blurred = gaussian_blur(dot, 1.0)
    assert blurred.sum() == pytest.approx(1.0, abs=1e-6) and blurred[0, 4, 4] == blurred.max()
    assert torch.equal(gaussian_blur(dot, 0.0), dot)
    grown = dilate(dot[0] > 0, 1)
    assert grown.dtype == torch.bool and grown.sum() == 9 and grown[3:6, 3:6].all()
    nchw = to_nchw(torch.rand(2, 5, 6, 3))
    assert nchw.shape == (2, 3, 5, 6) and resize(nchw, (5, 6)) is nchw
    assert resize(nchw, (10, 12)).shape == (2, 3, 10, 12)
