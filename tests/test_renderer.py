"""Renderers: the tiled torch rasterizer against an independent dense reference, SH, gsplat."""
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from trial_helpers import shared_path
from gs_regional.data.cameras import Camera
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.registry import find
from gs_regional.renderers import gsplat_rasterizer as gsplat_mod
from gs_regional.renderers.torch_rasterizer import TorchRasterizer
from gs_regional.utils.rotations import quat_to_rotmat
from gs_regional.utils.sh import SH_C0, eval_sh, num_sh_coeffs, rgb_to_sh, sh_to_color

PARAMS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # Small tensors: a second intra-op thread only adds synchronisation, which becomes very
    # slow when the (2-core) machine is busy with other processes.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# ---------------------------------------------------------------------------------------------
# Independent dense reference: every pixel against every Gaussian, one Gaussian at a time in
# depth order, exactly the per-pixel loop of gsplat's forward kernel.


def _skew(v):
    o = torch.zeros_like(v[:, 0])
    return torch.stack(
        [o, -v[:, 2], v[:, 1], v[:, 2], o, -v[:, 0], -v[:, 1], v[:, 0], o], dim=-1
    ).reshape(-1, 3, 3)


def reference_render(model, cam, background=None, override=None, near=0.01, block=1, with_weights=False):
    w2c = cam.world_to_camera.to(model.means)
    Rv, tv = w2c[:3, :3], w2c[:3, 3]
    with torch.no_grad():
        z_all = (model.means @ Rv.T + tv)[:, 2]
    keep = (z_all >= near).nonzero().squeeze(1)
    means = model.means[keep]
    p = (Rv @ means.T).T + tv
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    # Rotation by the vector form R = (w^2 - v.v) I + 2 v v^T + 2 w [v]x.
    q = F.normalize(model.quats[keep], dim=-1)
    w, v = q[:, 0], q[:, 1:]
    eye = torch.eye(3).expand(len(keep), 3, 3)
    Rq = (w * w - (v * v).sum(-1))[:, None, None] * eye + 2 * v[:, :, None] * v[:, None, :]
    Rq = Rq + 2 * w[:, None, None] * _skew(v)
    S = torch.diag_embed(torch.exp(model.log_scales[keep]))
    sigma3 = Rq @ S @ S @ Rq.transpose(1, 2)
    sigma_cam = Rv @ sigma3 @ Rv.T
    fx, fy, cx, cy, W, H = cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height
    limx = (-(cx / fx + 0.15 * W / fx), (W - cx) / fx + 0.15 * W / fx)
    limy = (-(cy / fy + 0.15 * H / fy), (H - cy) / fy + 0.15 * H / fy)
    xc = z * torch.clamp(x / z, *limx)
    yc = z * torch.clamp(y / z, *limy)
    zero = torch.zeros_like(z)
    J = torch.stack(
        [fx / z, zero, -fx * xc / z**2, zero, fy / z, -fy * yc / z**2], dim=-1
    ).reshape(-1, 2, 3)
    cov2d = J @ sigma_cam @ J.transpose(1, 2) + 0.3 * torch.eye(2)
    conic = torch.linalg.inv(cov2d)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)
    if means2d.requires_grad:
        means2d.retain_grad()
    opac = torch.sigmoid(model.opacity_logits[keep])
    if override is not None:
        colors = override[keep]
    else:
        centre = cam.center
        dirs = F.normalize(means - centre, dim=-1)
        colors = torch.clamp_min(eval_sh(model.sh_degree, model.sh[keep], dirs) + 0.5, 0.0)

    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    pc = torch.stack([xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5], dim=-1).float()
    P = pc.shape[0]
    T = torch.ones(P)
    done = torch.zeros(P, dtype=torch.bool)
    col = torch.zeros(P, colors.shape[1])
    dep = torch.zeros(P)
    acc = torch.zeros(P)
    weights = torch.zeros(P, model.means.shape[0]) if with_weights else None
    stops = 0
    # Gaussians in depth order, `block` at a time; block = 1 is literally gsplat's per-pixel loop,
    # larger blocks do the same with cumulative products inside the block.
    for ids in torch.split(torch.argsort(z.detach()), block):
        d = means2d[ids][None] - pc[:, None]  # (P, B, 2)
        c = conic[ids]
        sig = 0.5 * (c[:, 0, 0] * d[..., 0] ** 2 + c[:, 1, 1] * d[..., 1] ** 2)
        sig = sig + c[:, 0, 1] * d[..., 0] * d[..., 1]
        a = torch.clamp(opac[ids] * torch.exp(-sig), max=0.999)
        skip = (sig < 0) | (a < 1.0 / 255.0) | done[:, None]
        zero = torch.zeros_like(a)
        t_next = T[:, None] * torch.cumprod(1 - torch.where(skip, zero, a), dim=1)
        stop = ~skip & (t_next <= 1e-4)  # stop before this Gaussian, and skip all later ones
        stopped = torch.cumsum(stop.int(), dim=1) > 0
        stops += int(stop.any(1).sum())
        a_use = torch.where(~skip & ~stopped, a, zero)
        keep_t = torch.cumprod(1 - a_use, dim=1)
        t_before = T[:, None] * torch.cat([torch.ones(P, 1), keep_t[:, :-1]], dim=1)
        wt = a_use * t_before
        col = col + wt @ colors[ids]
        dep = dep + wt @ z[ids]
        acc = acc + wt.sum(1)
        if with_weights:
            weights[:, keep[ids]] = wt.detach()
        T = T * keep_t[:, -1]
        done = done | stopped.any(1)
    alpha = acc
    depth = torch.where(alpha > 0, dep / alpha.clamp_min(1e-10), torch.zeros_like(dep))
    if override is None:
        bg = torch.zeros(3) if background is None else background
        col = col + (1 - alpha)[:, None] * bg
    return {
        "rgb": col.reshape(H, W, -1),
        "depth": depth.reshape(H, W),
        "alpha": alpha.reshape(H, W),
        "one_minus_T": (1 - T).reshape(H, W),
        "weights": weights.reshape(H, W, -1) if with_weights else None,
        "means2d": means2d,
        "keep": keep,
        "stops": stops,
    }


# ---------------------------------------------------------------------------------------------
# Scenes


def _rotation(seed):
    g = torch.Generator().manual_seed(seed)
    return quat_to_rotmat(torch.randn(4, generator=g).double()).float()


def make_camera(seed=0):
    R = _rotation(seed)
    t = torch.tensor([0.3, -0.2, 0.5])
    w2c = torch.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, t
    # Non-square, fx != fy, off-centre principal point.
    return Camera(w2c, fx=46.0, fy=52.0, cx=22.5, cy=14.0, width=40, height=32)


def random_scene(cam, n=300, degree=3, seed=0):
    """Gaussians mostly in view, some behind the camera or partly / fully off screen."""
    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g)
    zc = 0.8 + 5.0 * u(n)
    xn = (u(n) - 0.5) * 2.4  # x/z, up to well beyond the image edges
    yn = (u(n) - 0.5) * 2.0
    pc = torch.stack([xn * zc, yn * zc, zc], dim=-1)
    pc[: n // 20, 2] = -1.0 - u(n // 20)  # behind the camera
    pc[n // 20 : n // 10, 2] = 0.005  # in front of the camera but closer than the near plane
    # An opaque cluster in the middle of the view so that early termination happens.
    m = n // 4
    pc[-m:] = torch.stack([(u(m) - 0.5) * 0.8, (u(m) - 0.5) * 0.6, 2.0 + u(m)], dim=-1)
    w2c = cam.world_to_camera
    R, t = w2c[:3, :3], w2c[:3, 3]
    model = GaussianModel(n=n, sh_degree=degree)
    model.means.data = (pc - t) @ R  # camera -> world
    model.quats.data = torch.randn(n, 4, generator=g)
    model.log_scales.data = torch.log(0.02 + 0.12 * u(n, 3))
    model.log_scales.data[:5] = math.log(0.6)  # a few large ones that cover many tiles
    logits = 3.0 * torch.randn(n, generator=g)
    logits[-m:] = 4.0 + 4.0 * u(m)  # opacity up to 0.9997 > 0.999: exercises the clamp
    model.opacity_logits.data = logits
    model.sh_dc.data = torch.randn(n, 3, generator=g) * 0.8
    k = num_sh_coeffs(degree)
    model.sh_rest.data = torch.randn(n, k - 1, 3, generator=g) * 0.3
    return model


def _grads(model):
    return {p: getattr(model, p).grad.clone() for p in PARAMS}


def _zero(model):
    for p in PARAMS:
        getattr(model, p).grad = None


def _loss(out, wr, wd, wa):
    return (out["rgb"] * wr).sum() + (out["depth"] * wd).sum() + (out["alpha"] * wa).sum()


# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "degree,seed,cfg",
    [
        (0, 1, {}),
        (3, 2, {}),
        # Small chunks: entries hidden behind opaque ones are dropped from the saved state.
        (3, 2, {"strip_width": 4, "chunk_size": 48}),
    ],
)
def test_matches_dense_reference_values_and_gradients(degree, seed, cfg):
    cam = make_camera(seed)
    model = random_scene(cam, n=300, degree=degree, seed=seed)
    bg = torch.tensor([0.2, 0.5, 0.9])
    g = torch.Generator().manual_seed(100 + seed)
    wr = torch.randn(32, 40, 3, generator=g)
    wa = torch.randn(32, 40, generator=g)

    ref = reference_render(model, cam, background=bg)
    assert ref["stops"] > 0, "scene must exercise early termination"
    # Depth gradients are only well conditioned where alpha is not tiny.
    wd = torch.randn(32, 40, generator=g) * (ref["alpha"].detach() > 0.05)
    _loss(ref, wr, wd, wa).backward()
    ref_grads = _grads(model)
    ref_m2d_grad = ref["means2d"].grad
    _zero(model)

    out = TorchRasterizer(cfg).render(model, cam, background=bg)
    assert out["rgb"].shape == (32, 40, 3)
    assert out["depth"].shape == (32, 40) and out["alpha"].shape == (32, 40)
    for key in ("rgb", "depth", "alpha"):
        diff = (out[key] - ref[key]).abs().max().item()
        assert diff < 1e-4, f"{key}: max abs diff {diff}"
    assert (out["alpha"] - ref["one_minus_T"]).abs().max() < 1e-4

    # Culling: behind the camera / before the near plane -> radius 0, not visible.
    assert not out["visible"][:30].any() and (out["radii"][:30] == 0).all()
    assert out["visible"].sum() > 100
    assert out["radii"].dtype == torch.int32 and out["radii"].shape == (300,)
    assert ((out["radii"] > 0) == out["visible"]).all()

    _loss(out, wr, wd, wa).backward()
    got = _grads(model)
    for p in PARAMS:
        if p == "sh_rest" and degree == 0:
            assert got[p].numel() == 0
            continue
        scale = ref_grads[p].abs().max().item()
        assert scale > 0, p
        torch.testing.assert_close(got[p], ref_grads[p], rtol=1e-3, atol=1e-5 * max(scale, 1.0), msg=p)

    # Screen-space means: part of the graph, gradient retained, equal to the reference's.
    m2d = out["means2d"]
    assert m2d.shape == (300, 2) and m2d.grad is not None
    assert (m2d.grad[~out["visible"]] == 0).all()
    keep = ref["keep"]
    assert not out["visible"][~torch.isin(torch.arange(300), keep)].any()
    full_ref = torch.zeros(300, 2)
    full_ref[keep] = ref_m2d_grad
    scale = full_ref.abs().max().item()
    torch.testing.assert_close(m2d.grad, full_ref, rtol=1e-3, atol=1e-5 * scale)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_render_nothing_is_differentiated_through_matches_the_reference(seed):
    """Renders under no_grad, or of a scene whose geometry needs no gradient (most of an edit's),
    take a shorter path (the culling projection's visible rows; no state kept for a backward
    pass): the same image as the dense reference and as the differentiable render."""
    cam = make_camera(seed)
    model = random_scene(cam, n=300, degree=3, seed=seed)
    bg = torch.tensor([0.2, 0.5, 0.9])
    ref = reference_render(model, cam, background=bg)
    slow = TorchRasterizer().render(model, cam, background=bg)
    with torch.no_grad():
        fast = TorchRasterizer().render(model, cam, background=bg)
    frozen = TorchRasterizer().render(model.requires_grad_(False), cam, background=bg)
    for out in (fast, frozen):
        assert out["rgb"].grad_fn is None
        assert torch.equal(out["radii"], slow["radii"]) and torch.equal(out["visible"], slow["visible"])
        for key in ("rgb", "depth", "alpha"):
            assert (out[key] - ref[key].detach()).abs().max() < 1e-4, key
            torch.testing.assert_close(out[key], slow[key].detach(), rtol=0, atol=1e-5, msg=key)


def test_override_color_gives_weights_and_lifting_gradient():
    cam = make_camera(3)
    model = random_scene(cam, n=200, degree=1, seed=3)
    ref = reference_render(model, cam, with_weights=True)
    weights = ref["weights"]  # (H, W, N)
    feat = torch.rand(200, 1, requires_grad=True)
    out = TorchRasterizer({"background": [1.0, 1.0, 1.0]}).render(model, cam, override_color=feat)
    assert out["rgb"].shape == (32, 40, 1)
    manual = (weights * feat.detach()[:, 0]).sum(-1)  # background is ignored for features
    assert (out["rgb"][..., 0] - manual).abs().max() < 1e-5
    # d/dfeature of sum M * render(feature) = sum_x w_i(x) M(x): the 2D -> 3D mask lifting.
    mask = (torch.rand(32, 40, generator=torch.Generator().manual_seed(0)) > 0.5).float()
    (out["rgb"][..., 0] * mask).sum().backward()
    expected = (weights * mask[..., None]).sum((0, 1))
    torch.testing.assert_close(feat.grad[:, 0], expected, rtol=1e-4, atol=1e-6)
    assert expected.max() > 1.0

    # Several channels at once.
    feats = torch.rand(200, 5)
    out5 = TorchRasterizer().render(model, cam, override_color=feats)
    assert out5["rgb"].shape == (32, 40, 5)
    manual5 = torch.einsum("hwn,nc->hwc", weights, feats)
    assert (out5["rgb"] - manual5).abs().max() < 1e-5
    with pytest.raises(ValueError, match="override_color must be"):
        TorchRasterizer().render(model, cam, override_color=torch.rand(199, 1))


@pytest.mark.parametrize("chunk_size", [1 << 20, 64])
def test_pixel_weights_are_the_compositing_weights(chunk_size):
    """Localization keeps each view's weights from one forward pass and reuses them: they must be
    the dense reference's w_i(x), `splat` must be exactly a render of the same features, and
    `gather` the lifting gradient that the generic (render + autograd) version computes."""
    from gs_regional.renderers.base import RenderedPixelWeights

    cam = make_camera(4)
    model = random_scene(cam, n=250, degree=0, seed=4)
    renderer = TorchRasterizer({"chunk_size": chunk_size})  # 64: many chunks and bands
    view = renderer.pixel_weights(model, cam)
    generic = RenderedPixelWeights(renderer, model, cam)
    weights = reference_render(model, cam, with_weights=True)["weights"]  # (H, W, N)
    feats = torch.rand(250, 3, generator=torch.Generator().manual_seed(1))
    # float32 sums in another order than the dense loop: values <= 1, so 1e-5 on any CPU
    assert (view.splat(feats) - torch.einsum("hwn,nc->hwc", weights, feats)).abs().max() < 1e-5
    # the same entries, products and index_add order as the forward pass: bit-identical
    assert torch.equal(view.splat(feats), generic.splat(feats))
    image = torch.rand(32, 40, generator=torch.Generator().manual_seed(2))
    expected = (weights * image[..., None]).sum((0, 1))
    # sums of up to ~1e3 weighted pixels, in float32, in different orders: relative 1e-4
    torch.testing.assert_close(view.gather(image), expected, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(view.gather(image), generic.gather(image), rtol=1e-4, atol=1e-5)
    assert view.gather(torch.stack([image, 1 - image], -1)).shape == (250, 2)
    assert expected.max() > 1.0 and int((expected == 0).sum()) > 10  # some are culled or hidden


def test_early_termination_and_alpha_clamp_by_hand():
    """Opaque Gaussians stacked on one pixel: gsplat stops before the one that takes T <= 1e-4."""
    cam = Camera(torch.eye(4), fx=20.0, fy=20.0, cx=8.0, cy=8.0, width=16, height=16)
    k = 6
    model = GaussianModel(n=k, sh_degree=0)
    zs = 1.0 + torch.arange(k, dtype=torch.float32)
    model.means.data = torch.stack([0.025 * zs, 0.025 * zs, zs], -1)  # on pixel (8, 8)'s centre
    model.log_scales.data = torch.full((k, 3), math.log(1e-4))  # only the 0.3 px low-pass left
    opac = torch.tensor([0.95, 0.95, 0.95, 0.95, 0.95, 0.95])
    model.opacity_logits.data = torch.logit(opac)
    feat = torch.tensor([[1.0], [2.0], [3.0], [1e4], [1e4], [1e4]])
    out = TorchRasterizer().render(model, cam, override_color=feat)
    # At the centre pixel sigma = 0: T = 1, .05, .0025, 1.25e-4, then 6.25e-6 <= 1e-4 -> stop.
    expected = 0.95 * (1.0 + 0.05 * 2.0 + 0.0025 * 3.0)
    assert abs(out["rgb"][8, 8, 0].item() - expected) < 1e-5
    assert abs(out["alpha"][8, 8].item() - (1 - 0.05**3)) < 1e-5
    assert abs(out["depth"][8, 8].item() - 0.95 * (1 + 0.05 * 2 + 0.0025 * 3) / (1 - 0.05**3)) < 1e-4
    # radius = ceil(3.33 sqrt(largest eigenvalue)); here the 2D covariance is ~0.3 I.
    assert out["radii"].tolist() == [2] * k
    model.log_scales.data[0] = math.log(0.05)  # 1 px at z = 1: eigenvalues 1.3 -> 3.33 * 1.14
    assert TorchRasterizer().render(model, cam)["radii"][0] == 4
    # Opacity above 0.999 is clamped to 0.999, and gets no opacity gradient there.
    model.opacity_logits.data = torch.full((k,), 9.0)  # sigmoid(9) = 0.99988
    feat1 = torch.ones(k, 1)
    out = TorchRasterizer().render(model, cam, override_color=feat1)
    assert abs(out["alpha"][8, 8].item() - 0.999) < 1e-6
    out["rgb"][8, 8, 0].backward()
    assert model.opacity_logits.grad[0] == 0


def test_tiles_and_chunks_do_not_change_the_result():
    cam = make_camera(4)
    model = random_scene(cam, n=300, degree=2, seed=4)
    results = []
    configs = (
        {},
        {"strip_width": 16},
        {"tile_size": 8, "strip_width": 2, "chunk_size": 300},
        {"tile_size": 5, "strip_width": 1, "chunk_size": 1},
    )
    for cfg in configs:
        _zero(model)
        out = TorchRasterizer(cfg).render(model, cam)
        (out["rgb"].sum() + out["alpha"].sum()).backward()
        results.append((out["rgb"].detach(), out["depth"].detach(), _grads(model)))
    for rgb, depth, grads in results[1:]:
        assert (rgb - results[0][0]).abs().max() < 1e-6
        assert (depth - results[0][1]).abs().max() < 1e-5
        for p in PARAMS:
            torch.testing.assert_close(grads[p], results[0][2][p], rtol=1e-4, atol=1e-5)


def test_empty_and_invisible_scenes():
    cam = make_camera(5)
    r = TorchRasterizer({"background": [0.1, 0.2, 0.3]})
    out = r.render(GaussianModel(n=0, sh_degree=0), cam)
    assert torch.allclose(out["rgb"], torch.tensor([0.1, 0.2, 0.3]).expand(32, 40, 3))
    assert (out["alpha"] == 0).all() and (out["depth"] == 0).all()
    model = random_scene(cam, n=20, degree=0, seed=5)
    with torch.no_grad():
        model.means.data = model.means.data - 100 * cam.world_to_camera[2, :3]  # all behind
    out = r.render(model, cam)
    assert not out["visible"].any() and (out["alpha"] == 0).all()
    out["rgb"].sum().backward()
    assert (model.means.grad == 0).all()


def test_registered_and_config_errors():
    assert find("torch-rasterizer") is TorchRasterizer
    from gs_regional.config import ConfigError

    with pytest.raises(ConfigError, match="tile_sise"):
        TorchRasterizer({"tile_sise": 8})
    with pytest.raises(ValueError, match="strip_width must divide"):
        TorchRasterizer({"tile_size": 16, "strip_width": 5})


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_matches_cpu():
    cam = make_camera(6)
    model = random_scene(cam, n=300, degree=3, seed=6)
    cpu = TorchRasterizer().render(model, cam)
    gpu = TorchRasterizer().render(model.cuda(), cam)
    for key in ("rgb", "depth", "alpha"):
        assert (gpu[key].cpu() - cpu[key]).abs().max() < 1e-4


# ---------------------------------------------------------------------------------------------
# Spherical harmonics


def _fibonacci_sphere(n):
    i = torch.arange(n, dtype=torch.float64) + 0.5
    phi = torch.arccos(1 - 2 * i / n)
    theta = math.pi * (1 + 5**0.5) * i
    return torch.stack(
        [torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi), torch.cos(phi)], -1
    )


def test_sh_basis_is_orthonormal_and_matches_known_values():
    dirs = _fibonacci_sphere(20000)
    basis = eval_sh(3, torch.eye(16, dtype=torch.float64)[None].expand(len(dirs), 16, 16), dirs)
    gram = basis.T @ basis * (4 * math.pi / len(dirs))
    assert (gram - torch.eye(16, dtype=torch.float64)).abs().max() < 1e-3
    # 3DGS sign conventions: Y_1 = -C1 y, Y_2 = C1 z, Y_3 = -C1 x.
    onehot = torch.eye(16)[None]
    d = torch.tensor([[0.0, 0.0, 1.0]])
    vals = eval_sh(3, onehot, d)[0]
    assert abs(vals[0] - SH_C0) < 1e-7 and abs(vals[2] - 0.4886025) < 1e-6
    assert abs(eval_sh(1, onehot, torch.tensor([[0.0, 1.0, 0.0]]))[0, 1] + 0.4886025) < 1e-6
    assert abs(eval_sh(1, onehot, torch.tensor([[1.0, 0.0, 0.0]]))[0, 3] + 0.4886025) < 1e-6
    # Colours: degree 0 ignores the direction; clamped at 0; rgb_to_sh inverts it.
    rgb = torch.rand(7, 3)
    coeffs = rgb_to_sh(rgb)[:, None, :]
    col = sh_to_color(0, coeffs, torch.randn(7, 3), torch.zeros(3))
    assert torch.allclose(col, rgb, atol=1e-6)
    assert (sh_to_color(0, -torch.ones(2, 1, 3) * 10, torch.randn(2, 3), torch.zeros(3)) == 0).all()
    with pytest.raises(ValueError, match="needs 16 coefficients"):
        eval_sh(3, torch.zeros(2, 9, 3), torch.zeros(2, 3))


# ---------------------------------------------------------------------------------------------
# Real data: gsplat's garden test asset


def test_garden_points_real_cameras_match_reference():
    path = shared_path("garden_points", "test_garden.npz")
    data = np.load(path)
    means = torch.from_numpy(data["means3d"]).float()
    colors = torch.from_numpy(data["colors"]).float() / 255.0
    viewmats = torch.from_numpy(data["viewmats"]).float()
    Ks = torch.from_numpy(data["Ks"]).float()
    width, height = int(data["width"]), int(data["height"])
    assert (width, height) == (648, 420)
    g = torch.Generator().manual_seed(0)
    sel = torch.randperm(len(means), generator=g)[:3000]
    n = len(sel)
    model = GaussianModel(n=n, sh_degree=0)
    model.means.data = means[sel]
    model.log_scales.data = torch.full((n, 3), math.log(0.015))
    model.opacity_logits.data = torch.full((n,), 2.0)
    model.sh_dc.data = rgb_to_sh(colors[sel])
    renderer = TorchRasterizer()
    for c in range(len(viewmats)):
        K = Ks[c]
        cam = Camera(viewmats[c], K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height).scaled(1 / 6)
        with torch.no_grad():
            out = renderer.render(model, cam)
            ref = reference_render(model, cam, block=128)
        assert out["alpha"].mean() > 0.2, "the real cameras should see the points"
        for key in ("rgb", "depth", "alpha"):
            diff = (out[key] - ref[key]).abs().max().item()
            assert diff < 1e-4, f"camera {c} {key}: max abs diff {diff}"


# ---------------------------------------------------------------------------------------------
# gsplat


def test_gsplat_unavailable_message(monkeypatch):
    if gsplat_mod.gsplat_available():
        pytest.skip("gsplat and CUDA are available here")
    with pytest.raises((ImportError, RuntimeError)) as e:
        find("gsplat-rasterizer")()
    msg = str(e.value)
    assert "pip install 'gs_regional[gsplat]'" in msg and "torch-rasterizer" in msg
    # gsplat importable but no GPU: a RuntimeError that says CUDA is missing.
    monkeypatch.setattr(gsplat_mod, "_gsplat", object())
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(RuntimeError, match="CUDA") as e:
        gsplat_mod.GsplatRasterizer()
    assert "pip install 'gs_regional[gsplat]'" in str(e.value)


def test_mirror_grad_exposes_per_camera_slice_gradient():
    p = torch.randn(5, 2, requires_grad=True)
    batched = (p * 3.0)[None]  # like gsplat's (C, N, 2) means2d
    view = gsplat_mod.mirror_grad(batched)
    assert view.shape == (5, 2)
    (batched * 2.0).sum().backward()
    torch.testing.assert_close(view.grad, torch.full((5, 2), 2.0))


def test_mirror_grad_lets_a_render_and_its_graph_go():
    """A render's graph must die with the render: if the hook held the view, the cycle through the
    autograd graph would keep every gsplat render's graph (and the parameters' gradient
    accumulators in it) alive. Found on an H200: a later change of the number of Gaussians then
    broke the next backward."""
    import gc
    import weakref

    p = torch.randn(5, 2, requires_grad=True)
    batched = (p * 3.0)[None]
    view = gsplat_mod.mirror_grad(batched)
    gone = weakref.ref(view)
    del view, batched
    gc.collect()
    assert gone() is None


@pytest.mark.skipif(
    not gsplat_mod.gsplat_available(), reason="gsplat-vs-torch agreement needs gsplat and a CUDA GPU"
)
def test_gsplat_agrees_with_torch_rasterizer():
    cam = make_camera(7)
    model = random_scene(cam, n=300, degree=3, seed=7).cuda()
    bg = torch.tensor([0.2, 0.5, 0.9], device="cuda")
    ours = TorchRasterizer().render(model, cam, background=bg)
    theirs = find("gsplat-rasterizer")().render(model, cam, background=bg)
    # gsplat uses fast-math exp on the GPU; a few 1e-5 of difference are expected.
    for key in ("rgb", "alpha"):
        assert (ours[key] - theirs[key]).abs().max() < 1e-3, key
    solid = ours["alpha"] > 0.5
    assert ((ours["depth"] - theirs["depth"]).abs()[solid] / ours["depth"][solid]).max() < 1e-3
    # gsplat's boxes are never larger than ours (and newer versions also cull by opacity).
    assert not (theirs["visible"] & ~ours["visible"]).any()
    feat = torch.rand(300, 1, device="cuda")
    a = TorchRasterizer().render(model, cam, override_color=feat)["rgb"]
    b = find("gsplat-rasterizer")().render(model, cam, override_color=feat)["rgb"]
    assert (a - b).abs().max() < 1e-3
    loss = ours["rgb"].sum()
    loss.backward()
    g_ours = model.means.grad.clone()
    model.means.grad = None
    theirs["rgb"].sum().backward()
    torch.testing.assert_close(model.means.grad, g_ours, rtol=1e-2, atol=1e-3 * g_ours.abs().max())
    m_ours, m_theirs = ours["means2d"].grad, theirs["means2d"].grad
    both = ours["visible"] & theirs["visible"]
    torch.testing.assert_close(m_theirs[both], m_ours[both], rtol=1e-2, atol=1e-3 * m_ours.abs().max())
