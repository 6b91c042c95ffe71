"""The template-method interfaces: the base classes check the arguments once for every plugin, so
a plugin implements only `_edit` / `_relevance` / `_disparity` / `_render` and never sees bad input."""
import pytest
import torch

from gs_regional.data.cameras import Camera
from gs_regional.depth.base import DepthEstimator
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.guidance.base import Guidance
from gs_regional.renderers.base import Renderer


class InvertEditor(Guidance):
    """A plugin with only `_edit`, recording what reaches it."""

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where)
        self.calls = []

    def _edit(self, images, cond_images, prompt, t_start, seed, cameras):
        self.calls.append((images.shape, t_start, cameras))
        return 1 - images


class WrongShapeEditor(Guidance):
    def _edit(self, images, cond_images, prompt, t_start, seed, cameras):
        return images[..., :1]


def _cam(size=8):
    return Camera(torch.eye(4), fx=10.0, fy=10.0, cx=size / 2, cy=size / 2, width=size, height=size)


def test_guidance_checks_once_then_calls_the_plugin():
    ed = InvertEditor({"batch_size": 2})
    x = torch.rand(2, 8, 8, 3)
    out = ed.edit(x, x, "invert it", t_start=500, cameras=[_cam(), _cam()])
    torch.testing.assert_close(out, 1 - x)
    # A single (H, W, 3) image is batched; cameras arrive as a list, one per image.
    ed.edit(x[0], x[0], "invert it", cameras=(_cam(),))
    assert ed.calls[0][:2] == ((2, 8, 8, 3), 500)
    assert ed.calls[1][0] == (1, 8, 8, 3) and ed.calls[1][1] is None and isinstance(ed.calls[1][2], list)

    bad_calls = [
        (dict(images=torch.rand(2, 8, 8, 4)), ValueError, r"InvertEditor.edit: images must have shape \(B, H, W, 3\), got \(2, 8, 8, 4\)"),
        (dict(cond_images=torch.rand(2, 8, 8)), ValueError, r"InvertEditor.edit: cond_images must have shape \(B, H, W, 3\)"),
        (dict(cond_images=torch.rand(2, 6, 8, 3)), ValueError, "InvertEditor.edit: images .* must have the same shape"),
        (dict(images=x * 3), ValueError, r"images must be in \[0, 1\]"),
        (dict(images=(x * 255).byte()), TypeError, "float"),
        (dict(t_start=1000), ValueError, r"InvertEditor.edit: t_start must be an integer timestep in \[0, 999\], got 1000"),
        (dict(t_start=-1), ValueError, "t_start must be an integer timestep"),
        (dict(t_start=500.0), ValueError, "t_start must be an integer timestep"),
        (dict(prompt="  "), ValueError, "prompt must be a non-empty instruction string"),
        (dict(cameras=[_cam()]), ValueError, "InvertEditor.edit: 2 images but 1 cameras"),
    ]
    for change, error, message in bad_calls:
        args = dict(images=x, cond_images=x, prompt="invert it", t_start=None, cameras=None)
        args.update(change)
        with pytest.raises(error, match=message):
            ed.edit(args["images"], args["cond_images"], args["prompt"], t_start=args["t_start"], cameras=args["cameras"])
    assert len(ed.calls) == 2  # no bad call reached the plugin


def test_guidance_names_what_a_plugin_lacks_or_returns_wrong():
    x = torch.rand(1, 8, 8, 3)
    with pytest.raises(NotImplementedError, match="InvertEditor must implement _relevance"):
        InvertEditor().relevance(x, "p")
    with pytest.raises(NotImplementedError, match="InvertEditor must implement _relevance"):
        InvertEditor().mask(x, "p")
    assert InvertEditor().mask(x, "p", threshold=0).shape == (1, 8, 8)  # γ = 0: everything, no model
    with pytest.raises(ValueError, match=r"WrongShapeEditor.edit returned \(1, 8, 8, 1\); expected .*\(1, 8, 8, 3\)"):
        WrongShapeEditor().edit(x, x, "p")
    # relevance arguments are checked before the plugin runs.
    with pytest.raises(ValueError, match="timestep must be an integer timestep"):
        InvertEditor().relevance(x, "p", timestep=1000)
    with pytest.raises(ValueError, match="samples must be an integer >= 1"):
        InvertEditor().relevance(x, "p", samples=0)


class SeedEditor(Guidance):
    """Adds each view's seed (as a brightness) and records the batches it is called with."""

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where)
        self.batches = []

    def _relevance(self, images, prompt, timestep, samples, seeds, cameras):
        self.batches.append(list(seeds))
        return torch.tensor(seeds, dtype=torch.float32)[:, None, None].expand(images.shape[:3]) / 100

    def _edit(self, images, cond_images, prompt, t_start, seeds, cameras):
        self.batches.append((list(seeds), None if cameras is None else len(cameras)))
        return torch.tensor(seeds, dtype=torch.float32)[:, None, None, None].expand(images.shape) / 100


def test_guidance_batches_views_and_gives_each_its_seed():
    x = torch.rand(5, 8, 8, 3)
    ed = SeedEditor({"batch_size": 2})
    out = ed.edit(x, x, "p", seed=[10, 11, 12, 13, 14], cameras=[_cam()] * 5)
    assert ed.batches == [([10, 11], 2), ([12, 13], 2), ([14], 1)]  # at most batch_size views per call
    torch.testing.assert_close(out[:, 0, 0, 0], torch.tensor([0.10, 0.11, 0.12, 0.13, 0.14]))
    ed.batches.clear()
    assert ed.relevance(x, "p", seed=7).shape == (5, 8, 8)
    assert ed.batches == [[7, 7], [7, 7], [7]]  # an int seed is every view's seed
    with pytest.raises(ValueError, match="SeedEditor.edit: 5 images but 2 seeds"):
        ed.edit(x, x, "p", seed=[1, 2])
    with pytest.raises(TypeError, match="seed must be an int or a list of one int per image"):
        ed.edit(x, x, "p", seed=[1.5] * 5)
    with pytest.raises(TypeError, match="seed must be an int"):
        ed.relevance(x, "p", seed="0")
    with pytest.raises(ValueError, match="batch_size .* must be >= 1"):
        SeedEditor({"batch_size": 0})


def test_guidance_config_must_carry_batch_size():
    from dataclasses import dataclass

    class OwnConfigEditor(Guidance):
        @dataclass
        class Config:
            strength: float = 1.0

    with pytest.raises(TypeError, match=r"OwnConfigEditor.Config must derive from Guidance.Config"):
        OwnConfigEditor()


class CamerasOnlyDepth(DepthEstimator):
    requires_cameras = True

    def _disparity(self, images, cameras):
        return torch.ones(images.shape[:3])


def test_depth_estimator_checks_images_and_cameras():
    est = CamerasOnlyDepth()
    x = torch.rand(2, 8, 8, 3)
    assert est.disparity(x, cameras=[_cam(), _cam()]).shape == (2, 8, 8)
    with pytest.raises(ValueError, match=r"CamerasOnlyDepth.disparity needs cameras=\[one Camera per image\]"):
        est.disparity(x)
    with pytest.raises(ValueError, match="2 images but 3 cameras"):
        est.disparity(x, cameras=[_cam()] * 3)
    with pytest.raises(ValueError, match=r"\(B, H, W, 3\)"):
        est.disparity(torch.rand(2, 8, 8, 2), cameras=[_cam(), _cam()])


class EchoRenderer(Renderer):
    def _render(self, model, camera, background, override_color):
        return {"background": background, "override_color": override_color}


def test_renderer_checks_background_and_override_color():
    model = GaussianModel.from_tensors(
        means=torch.zeros(4, 3), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(4, 1), log_scales=torch.zeros(4, 3),
        opacity_logits=torch.zeros(4), sh_dc=torch.zeros(4, 3),
    )
    r = EchoRenderer({"background": [0.0, 0.5, 1.0]})
    assert r.render(model, _cam())["background"].tolist() == [0.0, 0.5, 1.0]  # the configured default
    assert r.render(model, _cam(), background=(1, 1, 1))["background"].dtype == torch.float32
    out = r.render(model, _cam(), background=(1, 1, 1), override_color=torch.ones(4, 2))
    assert out["background"] is None  # features are composited over zero
    with pytest.raises(ValueError, match="background must have 3 values, got 2"):
        r.render(model, _cam(), background=(1, 1))
    with pytest.raises(ValueError, match=r"override_color must be \(N, C\) with N = 4 Gaussians, got \(3, 2\)"):
        r.render(model, _cam(), override_color=torch.ones(3, 2))
    with pytest.raises(ValueError, match="renderer.tile_size must be >= 1"):
        EchoRenderer({"tile_size": 0})


class MapEditor(Guidance):
    """A plugin whose relevance is a fixed map (the same for every image)."""

    relevance_map = None

    def _relevance(self, images, prompt, timestep, samples, seeds, cameras):
        return self.relevance_map.expand(images.shape[0], -1, -1).clone()


def test_mask_removes_specks_but_keeps_a_small_part_that_is_the_strongest_response():
    """The speck filter (σ = 2 px) erases any blob under about 17 px; a part that small in a view
    must survive when it is where the editor responds most, while weaker specks still go."""
    rel = torch.zeros(32, 32)
    rel[5:8, 5:8] = 1.0  # the part: 3 x 3 px, the strongest response
    rel[20, 20] = 0.8  # a speck of noise above the threshold
    rel[14:30, 24:30] = 0.7  # a large blob (a related part), kept by the filter as before
    MapEditor.relevance_map = rel
    m = MapEditor().mask(torch.rand(2, 32, 32, 3), "paint a patch", threshold=0.6, blur_sigma=2.0)[0].bool()
    assert m[5:8, 5:8].all() and int(m[:10, :10].sum()) == 9  # the part, whole and no more
    assert not m[20, 20] and m[20:26, 25:29].all()
    rel[5:8, 5:8] = 0.65  # the part is no longer the strongest response: a speck like any other
    rel[16:30, 24:30] = 1.0
    m = MapEditor().mask(torch.rand(1, 32, 32, 3), "paint a patch", threshold=0.6, blur_sigma=2.0)[0].bool()
    assert not m[:10, :10].any()
