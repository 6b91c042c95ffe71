"""The procedural scene, its cameras, its ground-truth edits and the `synthetic-scene` data module."""
import pytest
import torch

from gs_regional import find
from gs_regional.config import ConfigError
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.utils.sh import sh_to_rgb
from gs_regional.sim.scene import (
    CAMERA_AZIMUTH_SPAN,
    CAMERA_RADIUS,
    EDIT_NAMES,
    OBJECT_PARTS,
    SyntheticDataModule,
    _cached_source_images,
    make_cameras,
    make_edit,
    make_scene,
)
from gs_regional.sim.truth import GroundTruth

PARAMS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc")


def _renderer():
    return find("torch-rasterizer")()


def _subset(model: GaussianModel, keep: torch.Tensor) -> GaussianModel:
    out = GaussianModel(n=int(keep.sum()), sh_degree=0)
    for name in PARAMS:
        getattr(out, name).data = getattr(model, name).data[keep].clone()
    return out


def _colours(model):
    return sh_to_rgb(model.sh_dc.data)


@pytest.fixture(scope="module")
def scene():
    return make_scene(0)


@pytest.fixture(scope="module")
def cams():
    return make_cameras(40, 96, 96, seed=0)


@pytest.fixture(scope="module")
def front_index(cams):
    cameras, front = cams
    dirs = torch.stack([c.center / c.center.norm() for c in cameras])
    return int((dirs @ front).argmax())


def test_scene_is_deterministic_and_seeded():
    a, la, na = make_scene(0)
    b, lb, _ = make_scene(0)
    c, _, _ = make_scene(1)
    for name in PARAMS:
        assert torch.equal(getattr(a, name).data, getattr(b, name).data), name
    assert torch.equal(la, lb)
    assert not torch.allclose(a.means.data[: len(c)], c.means.data[: len(a)])
    # a fresh model every call: editing one must not leak into the next
    a.sh_dc.data += 1
    assert torch.equal(make_scene(0)[0].sh_dc.data, b.sh_dc.data)


def test_scene_contents(scene):
    model, labels, names = scene
    assert 3000 <= len(model) <= 20000
    assert model.sh_degree == 0 and len(labels) == len(model)
    counts = torch.bincount(labels, minlength=len(names))
    assert (counts > 0).all(), dict(zip(names, counts.tolist()))
    assert set(OBJECT_PARTS) <= set(names)
    obj = torch.isin(labels, torch.tensor([names.index(p) for p in OBJECT_PARTS]))
    # the figure sits at the origin and is about 1 unit tall
    lo, hi = model.means.data[obj].min(0).values, model.means.data[obj].max(0).values
    assert (hi - lo)[1].item() == pytest.approx(1.2, abs=0.25)
    assert hi.abs().max() < 0.8 and lo.abs().max() < 0.8
    # colours are valid, parts are coloured differently, splats are opaque, flat and small
    rgb = _colours(model)
    assert rgb.min() >= 0 and rgb.max() <= 1
    means = {p: rgb[labels == names.index(p)].mean(0) for p in OBJECT_PARTS}
    for i, p in enumerate(OBJECT_PARTS):
        for q in OBJECT_PARTS[i + 1 :]:
            assert (means[p] - means[q]).abs().max() > 0.1, (p, q)
    assert model.opacities[obj].min() > 0.9
    s = model.scales.data
    assert (s.min(1).values < 0.3 * s.max(1).values).float().mean() > 0.95
    assert s[obj].max() < 0.05
    assert torch.allclose(model.quats.data.norm(dim=-1), torch.ones(len(model)), atol=1e-5)
    assert (model.generation == 0).all() and not model.mask.any()


def test_cameras_ring_and_convention(cams):
    cameras, front = cams
    assert len(cameras) == 40 and torch.allclose(front, torch.tensor([0.0, 0.0, 1.0]))
    centres = torch.stack([c.center for c in cameras])
    az = torch.rad2deg(torch.atan2(centres[:, 0], centres[:, 2]))
    assert az.min() < -CAMERA_AZIMUTH_SPAN + 5 and az.max() > CAMERA_AZIMUTH_SPAN - 5
    elev = torch.rad2deg(torch.asin(centres[:, 1] / centres.norm(dim=-1)))
    assert len(torch.unique(torch.round(elev / 8))) >= 2  # two rings
    assert torch.allclose(centres.norm(dim=-1), torch.full((40,), CAMERA_RADIUS), atol=0.15)
    for cam in cameras:
        assert (cam.width, cam.height) == (96, 96)
        R = cam.world_to_camera[:3, :3]
        assert torch.allclose(R @ R.T, torch.eye(3), atol=1e-5) and torch.det(R) > 0
        # OpenCV: the target is straight ahead (+z), world up is image up (-y)
        p = cam.world_to_camera @ torch.tensor([0.0, 0.0, 0.0, 1.0])
        assert p[2] > 0 and abs(p[0]) < 1e-4 and abs(p[1]) < 1e-4
        up = cam.world_to_camera @ torch.tensor([0.0, 0.5, 0.0, 1.0])
        assert up[1] < p[1]
    assert make_cameras(40, 96, 96, seed=0)[0][7].world_to_camera.equal(cameras[7].world_to_camera)
    assert not make_cameras(40, 96, 96, seed=3)[0][7].world_to_camera.equal(cameras[7].world_to_camera)
    # the front camera sees the figure's +x on its right
    cam = min(cameras, key=lambda c: float(c.center[0].abs() + c.center[1]))
    right = cam.world_to_camera @ torch.tensor([0.3, 0.0, 0.0, 1.0])
    assert right[0] > 0


def test_source_renders_are_sane(scene, cams, front_index):
    model, labels, names = scene
    cam = cams[0][front_index]
    r = _renderer()
    obj = torch.isin(labels, torch.tensor([names.index(p) for p in OBJECT_PARTS]))
    with torch.no_grad():
        full = r.render(model, cam, background=torch.zeros(3))
        sil = r.render(model, cam, override_color=obj.float()[:, None])["rgb"][..., 0] > 0.5
        alone = r.render(_subset(model, obj), cam, background=torch.zeros(3))
    # the backdrop and the ground fill the frame, at sensible depths
    assert full["alpha"].min() > 0.9
    assert 1.0 < full["depth"].min() and full["depth"].max() < 7.0
    assert full["rgb"].std() > 0.08  # textured, not flat
    # the figure occupies the centre
    frac = sil.float().mean()
    assert 0.08 < frac < 0.5
    ys, xs = torch.nonzero(sil, as_tuple=True)
    assert abs(xs.float().mean() - 48) < 8 and abs(ys.float().mean() - 48) < 12
    # it renders solid (alpha ~ 1 over its silhouette) at the distance of the camera ring
    inner = sil & ~torch.nn.functional.max_pool2d((~sil).float()[None], 5, 1, 2)[0].bool()
    assert alone["alpha"][inner].min() > 0.98
    d = full["depth"][inner]
    assert (d > CAMERA_RADIUS - 0.7).all() and (d < CAMERA_RADIUS + 0.5).all()
    assert (full["depth"][~sil].median() > CAMERA_RADIUS + 0.5)


def test_edits_definitions(scene):
    _, labels, names = scene
    for name in EDIT_NAMES:
        gt = make_edit(name)
        assert isinstance(gt, GroundTruth)
        src, ed, region = gt.source, gt.edited, gt.region
        assert gt.name == name and gt.prompt
        assert region.dtype == torch.bool and len(region) == len(src)
        assert len(gt.new_region) == len(ed) and gt.new_region.dtype == torch.bool
        assert torch.equal(gt.front, torch.tensor([0.0, 0.0, 1.0])) and torch.equal(gt.center, torch.zeros(3))
        changed = (_colours(ed)[: len(src)] - _colours(src)).abs().amax(-1) > 1e-4
        assert torch.equal(ed.means.data[: len(src)], src.means.data)
        if name == "global":
            assert region.all() and changed.float().mean() > 0.95
            assert gt.related is None
        elif name == "empty":
            assert not region.any() and not changed.any() and len(ed) == len(src)
            assert gt.related is None
        else:
            assert 0 < region.sum() < 0.5 * len(region)
            assert torch.equal(region, labels == names.index("head"))
            assert torch.equal(gt.related, labels == names.index("body"))  # what an editor's relevance leaks into
        if name == "recolor":
            assert len(ed) == len(src) and torch.equal(changed, region)
            assert _colours(ed)[region].mean(0)[0] > 0.5 > _colours(ed)[region].mean(0)[1]  # red
        if name == "add":
            new = ed.generation == 1
            assert not changed.any() and new.sum() > 100 and new[len(src):].all()
            assert torch.equal(gt.new_region, torch.cat([region, new[len(src):]]))
    with pytest.raises(ValueError, match="recolor"):
        make_edit("paint")


def test_add_sticks_out_of_the_silhouette(scene, cams, front_index):
    model, labels, names = scene
    gt = make_edit("add")
    cam = cams[0][front_index]
    r = _renderer()
    obj = torch.isin(labels, torch.tensor([names.index(p) for p in OBJECT_PARTS]))
    head = labels == names.index("head")
    with torch.no_grad():
        src = r.render(gt.source, cam, background=torch.zeros(3))
        ed = r.render(gt.edited, cam, background=torch.zeros(3))
        maps = r.render(gt.source, cam, override_color=torch.stack([obj, head], 1).float())["rgb"]
    changed = (ed["rgb"] - src["rgb"]).abs().amax(-1) > 0.05
    outside = changed & (maps[..., 0] < 0.05)
    assert changed.sum() > 30
    assert outside.sum() >= 6, "the added geometry should stick out past the figure"
    # the change sits in front of the head, in the upper half of the image
    ys, _ = torch.nonzero(changed, as_tuple=True)
    assert ys.float().mean() < 48
    assert (maps[..., 1][changed] > 0.5).float().mean() > 0.3
    # nearer than what it covers
    assert (ed["depth"][changed] < src["depth"][changed] + 1e-3).float().mean() > 0.9


def test_datamodule(tmp_path):
    cls = find("synthetic-scene")
    assert cls is SyntheticDataModule
    cfg = {"edit": "add", "n_cameras": 10, "width": 40, "height": 40, "test_every": 4}
    dm = cls(cfg)
    _cached_source_images.cache_clear()
    dm.setup("fit")
    s = dm.scene
    # Setting up renders no photo (an edit never reads them); the first read renders every view.
    assert _cached_source_images.cache_info().currsize == 0
    assert len(s.cameras) == 10 and len(s.images) == 10
    assert s.images[0].shape == (40, 40, 3) and 0 <= s.images[0].min() and s.images[0].max() <= 1
    assert s.test_indices == [0, 4, 8] and s.train_indices == [1, 2, 3, 5, 6, 7, 9]
    assert s.source == "synthetic:add"
    gt = s.ground_truth
    assert isinstance(gt, GroundTruth) and gt.name == "add" and len(gt.region) == len(gt.source)
    assert torch.allclose(gt.front, torch.tensor([0.0, 0.0, 1.0]))
    # images are the renders of the source scene at the cameras
    with torch.no_grad():
        again = _renderer().render(gt.source, s.cameras[3], background=torch.zeros(3))["rgb"]
    assert (again.clamp(0, 1) - s.images[3]).abs().max() < 1e-4

    it = iter(dm.train_dataloader())
    seen = [next(it)["index"] for _ in range(30)]  # endless: more than the 7 training views
    assert set(int(i) for i in seen) == set(s.train_indices)
    assert [int(b["index"]) for b in dm.val_dataloader()] == s.test_indices
    assert [int(b["index"]) for b in dm.test_dataloader()] == s.test_indices

    assert _cached_source_images.cache_info().misses == 1
    # a second module with the same config reuses the cached renders
    dm2 = cls(cfg)
    dm2.setup("test")
    assert torch.equal(dm2.scene.images[5], s.images[5])
    assert _cached_source_images.cache_info().misses == 1
    assert len(s.images[2:5]) == 3 and torch.equal(s.images[2:5][1], s.images[3])
    dm2.scene.images[5].zero_()  # modules do not share image tensors
    assert s.images[5].abs().sum() > 0

    with pytest.raises(ConfigError, match="n_camera"):
        cls({"n_camera": 8})
    with pytest.raises(ValueError, match="recolor"):
        cls({"edit": "paint"})
