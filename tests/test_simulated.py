"""The simulated editor and depth estimator against the synthetic scene's known answer."""
import pytest
import torch

from gs_regional import find
from gs_regional.config import ConfigError
from gs_regional.sim.editor import SimulatedEditor, _shift, denoising_steps, edit_strength
from gs_regional.sim.scene import make_cameras, make_edit, make_scene
from gs_regional.sim.truth import GroundTruth, TruthRenderer


@pytest.fixture(scope="module")
def cams():
    cameras, front = make_cameras(40, 96, 96, seed=0)
    centres = torch.stack([c.center / c.center.norm() for c in cameras])
    order = torch.argsort(centres @ front, descending=True)
    return {"all": cameras, "front": cameras[int(order[0])], "front2": cameras[int(order[1])],
            "side": cameras[int(order[-1])]}


@pytest.fixture(scope="module")
def gt_recolor():
    return make_edit("recolor")


@pytest.fixture(scope="module")
def editor(gt_recolor):
    ed = SimulatedEditor()
    ed.attach_ground_truth(gt_recolor)
    return ed


def _src(ed, cams):
    return torch.stack([ed.truth_renderer.views(c)["src_rgb"] for c in cams])


def _iou(a, b):
    a, b = a.bool(), b.bool()
    return float((a & b).sum() / (a | b).sum().clamp_min(1))


def test_registered_and_needs_cameras(editor, cams):
    assert find("simulated-editor") is SimulatedEditor
    x = _src(editor, [cams["front"]])
    with pytest.raises(ValueError, match="cameras"):
        editor.edit(x, x, "make his head red")
    with pytest.raises(ValueError, match="cameras"):
        editor.relevance(x, "make his head red")
    with pytest.raises(ValueError, match="2 cameras"):
        editor.relevance(x, "p", cameras=[cams["front"], cams["side"]])
    with pytest.raises(ValueError, match="t_start"):
        editor.edit(x, x, "p", t_start=0, cameras=[cams["front"]])
    with pytest.raises(ValueError, match="cameras"):
        depth = find("simulated-depth")()
        depth.attach_ground_truth(editor.ground_truth)
        depth.disparity(x)


@pytest.mark.parametrize("name", ["simulated-editor", "simulated-depth"])
def test_simulator_without_ground_truth_says_what_to_do(name, cams):
    """A simulator renders a known answer: without one attached it fails at its first call, naming
    the fix, instead of inventing a scene of its own."""
    sim = find(name)()
    x = torch.zeros(1, 96, 96, 3)
    call = (lambda: sim.edit(x, x, "p", cameras=[cams["front"]])) if name == "simulated-editor" else (
        lambda: sim.disparity(x, cameras=[cams["front"]]))
    with pytest.raises(ConfigError, match=rf"{name} is a simulator.*none was attached.*synthetic-scene.*attach_ground_truth"):
        call()
    with pytest.raises(TypeError, match="needs a GroundTruth"):
        sim.attach_ground_truth({"source": None})  # the old dict form


@pytest.mark.parametrize("name", ["simulated-editor", "simulated-depth"])
@pytest.mark.parametrize("key", ["edit", "scene_seed", "n_object", "n_background"])
def test_removed_scene_fields_are_unknown_keys(name, key):
    """The scene a simulator renders comes from the data module's ground truth only: the old fields
    that named a scene of its own are gone, and setting one fails loudly instead of being ignored."""
    with pytest.raises(ConfigError, match=rf"unknown config key 'system\.\w+\.{key}'"):
        find(name)({key: 1})


def test_ground_truth_masks_must_match_their_models(gt_recolor):
    """Per-Gaussian masks are indexed by row: one entry per source (region, related) or edited
    (new_region) Gaussian, nothing else."""
    fields = dict(source=gt_recolor.source, edited=gt_recolor.edited, region=gt_recolor.region,
                  new_region=gt_recolor.new_region, front=gt_recolor.front, center=gt_recolor.center)
    GroundTruth(**fields)
    with pytest.raises(ValueError, match=r"region must be a bool tensor with one entry per source Gaussian"):
        GroundTruth(**{**fields, "region": gt_recolor.region[:-1]})
    with pytest.raises(ValueError, match=r"new_region .* per edited Gaussian"):
        GroundTruth(**{**fields, "new_region": gt_recolor.new_region.float()})
    with pytest.raises(ValueError, match=r"related .* per source Gaussian"):
        GroundTruth(**fields, related=torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match="front must be a 3-vector"):
        GroundTruth(**{**fields, "front": torch.ones(2)})


def test_relevance_front_matches_region_side_misses(editor, cams):
    views = [cams["front"], cams["side"]]
    x = _src(editor, views)
    rel = editor.relevance(x, "make his head red", cameras=views)
    assert rel.shape == (2, 96, 96) and rel.min() >= 0 and torch.allclose(rel.amax((1, 2)), torch.ones(2))
    mask = editor.mask(x, "make his head red", threshold=0.6, cameras=views)
    truth = torch.stack([editor.truth_renderer.region_maps(c)[..., 0] > 0.5 for c in views])
    front_iou, side_iou = _iou(mask[0], truth[0]), _iou(mask[1], truth[1])
    assert front_iou > 0.5, front_iou
    assert side_iou < front_iou - 0.3, (front_iou, side_iou)
    # leakage: the body lights up, but below the region's peak
    body = editor.truth_renderer.region_maps(views[0])[..., 1] > 0.9
    assert 0.15 < rel[0][body].mean() < 0.6
    # deterministic given the seed; the call's seed and the config seed both matter
    assert torch.equal(rel, editor.relevance(x, "make his head red", cameras=views))
    assert not torch.equal(rel, editor.relevance(x, "make his head red", seed=1, cameras=views))
    other = SimulatedEditor({"seed": 5})
    other.attach_ground_truth(editor.ground_truth)
    assert not torch.equal(rel, other.relevance(x, "make his head red", cameras=views))


def test_global_relevance_covers_everything(cams):
    ed = SimulatedEditor()
    ed.attach_ground_truth(make_edit("global", n_object=1500, n_background=1000))
    cam = cams["front"].scaled(0.5)
    x = _src(ed, [cam])
    assert ed.mask(x, "sepia", cameras=[cam]).mean() > 0.9
    assert ed.mask(x, "sepia", threshold=0.0, cameras=[cam]).mean() == 1.0


def test_edit_strength_grows_with_t_start(editor, cams):
    views = [cams["front"], cams["front2"]]
    x = _src(editor, views)
    target = torch.stack([editor.truth_renderer.views(c)["edit_rgb"] for c in views])
    changed = (target - x).abs().amax(-1) > 0.05
    # beyond the per-view shift and the bleed, the image must come back unchanged
    far = ~torch.nn.functional.max_pool2d(changed.float()[:, None], 17, 1, 8)[:, 0].bool()
    outs = {t: editor.edit(x, x, "make his head red", t_start=t, cameras=views) for t in (250, 750, None)}
    dist = {t: float((o - x).abs()[changed].mean()) for t, o in outs.items()}
    assert dist[250] < dist[750] < dist[None], dist
    assert edit_strength(250) < edit_strength(750) < edit_strength(None) == 1.0
    for o in outs.values():
        assert o.shape == x.shape and o.min() >= 0 and o.max() <= 1
    # away from the edit, only the re-generation of the whole image changes it, less at lower t
    far_dist = {t: float((o - x).abs()[far].mean()) for t, o in outs.items()}
    assert 0 < far_dist[250] < far_dist[750] < far_dist[None] < 0.05, far_dist
    # without re-generation, the image comes back unchanged beyond the per-view shift and the bleed
    exact = SimulatedEditor({"regen_blur": 0.0, "regen_drift": 0.0})
    exact.attach_ground_truth(editor.ground_truth)
    for t in (250, 750, None):
        o = exact.edit(x, x, "make his head red", t_start=t, cameras=views)
        assert (o - x).abs()[far].max() < 0.02
    # a full edit lands near the true edit where it changed
    assert float((outs[None] - target).abs()[changed].mean()) < 0.12
    # deterministic given the seed, different with another seed
    assert torch.equal(outs[750], editor.edit(x, x, "make his head red", t_start=750, cameras=views))
    assert not torch.equal(outs[750], editor.edit(x, x, "make his head red", t_start=750, seed=3, cameras=views))


def test_per_view_jitter(editor, cams):
    a, b = cams["front"], cams["front2"]
    ja, jb = editor.view_jitter(a), editor.view_jitter(b)
    assert not torch.allclose(ja["shift"], jb["shift"]) and not torch.allclose(ja["gain"], jb["gain"])
    assert torch.equal(ja["shift"], editor.view_jitter(a)["shift"])
    # jitter grows with t_start
    small = editor.view_jitter(a, t_start=250)
    assert small["shift"].norm() < ja["shift"].norm() and (small["gain"] - 1).abs().sum() < (ja["gain"] - 1).abs().sum()
    # the output really is the true edit moved by that shift
    sharp = SimulatedEditor({"color_jitter": 0.0, "bleed": 0.0, "residual_noise": 0.0, "position_jitter": 3.0})
    sharp.attach_ground_truth(editor.ground_truth)
    for cam in (a, b):
        x = _src(sharp, [cam])
        out = sharp.edit(x, x, "p", cameras=[cam])[0]
        j = sharp.view_jitter(cam)["shift"]
        v = sharp.truth_renderer.views(cam)
        moved = _shift(v["edit_rgb"], float(j[0]), float(j[1]))
        diff = (v["edit_rgb"] - v["src_rgb"]).abs().amax(-1) > 0.1
        core = _shift(diff.float()[..., None], float(j[0]), float(j[1]))[..., 0] > 0.99
        assert core.sum() > 20
        assert (out[core] - moved[core]).abs().max() < 1e-4


def test_unet_counting(editor, cams):
    views = [cams["front"], cams["front2"]]
    x = _src(editor, views)
    editor.reset_counters()
    editor.edit(x, x, "p", t_start=250, cameras=views)
    assert editor.counters() == {"unet_evals": 3 * 2 * 5, "vae_encodes": 4, "vae_decodes": 2}
    editor.edit(x, x, "p", t_start=None, cameras=views)
    assert editor.unet_evals == 30 + 3 * 2 * 20
    editor.reset_counters()
    editor.relevance(x, "p", samples=3, cameras=views)
    assert editor.counters() == {"unet_evals": 2 * 2 * 3, "vae_encodes": 2, "vae_decodes": 0}
    # the steps a DDIM run with diffusers' Stable Diffusion set-up takes from each t_start
    assert [denoising_steps(t) for t in (1, 250, 500, 750, 999, None)] == [1, 5, 10, 15, 20, 20]
    assert denoising_steps(0) == 0


def test_region_render_fallback_matches_features(gt_recolor, cams):
    cam = cams["front"].scaled(0.5)
    truth = TruthRenderer(gt_recolor)
    maps = truth.region_maps(cam)
    src = gt_recolor.source
    _, labels, names = make_scene(0)
    feats = torch.stack([gt_recolor.region.float(), (labels == names.index("body")).float()], 1)
    with torch.no_grad():
        colour_coded = truth._render_as_colours(src, cam, feats)
    assert maps[..., 0].max() > 0.9 and maps[..., 1].max() > 0.9
    assert (colour_coded - maps).abs().max() < 1e-3

    # a renderer without `override_color` takes the colour-coded path by itself
    class NoFeatures:
        def __init__(self, inner):
            self.inner = inner

        def render(self, model, camera, background=None, override_color=None):
            if override_color is not None:
                raise NotImplementedError("no per-Gaussian features")
            return self.inner.render(model, camera, background=background)

    plain = TruthRenderer(gt_recolor)
    plain.renderer = NoFeatures(plain.renderer)
    assert (plain.region_maps(cam) - maps).abs().max() < 1e-3


def _fit(pred, true, valid):
    A = torch.stack([pred[valid], torch.ones(int(valid.sum()))], 1)
    sol = torch.linalg.lstsq(A, true[valid][:, None]).solution[:, 0]
    return pred * sol[0] + sol[1]


def test_the_simulators_of_a_system_share_their_renders_of_the_truth(cams):
    """A system hands its simulators one dict: those that render the truth alike share one
    TruthRenderer, so a view the editor rendered is not rendered again for the depth."""
    gt, shared = make_edit("add"), {}
    editor, depth = SimulatedEditor(), find("simulated-depth")()
    editor.attach_ground_truth(gt, shared)
    depth.attach_ground_truth(gt, shared)
    assert depth.truth_renderer is editor.truth_renderer
    views = editor.truth_renderer.views(cams["front"])
    assert depth.truth_renderer.views(cams["front"]) is views  # rendered once
    white = find("simulated-depth")({"background": [1.0, 1.0, 1.0]})
    white.attach_ground_truth(gt, shared)
    assert white.truth_renderer is not editor.truth_renderer  # another background: other renders
    alone = SimulatedEditor()
    alone.attach_ground_truth(gt)
    assert alone.truth_renderer is not editor.truth_renderer


def test_simulated_depth_recovers_true_depth(cams):
    gt = make_edit("add")
    depth = find("simulated-depth")()
    depth.attach_ground_truth(gt)
    views = [cams["front"], cams["side"]]
    src = torch.stack([depth.truth_renderer.views(c)["src_rgb"] for c in views])
    disp = depth.disparity(src, cameras=views)
    assert disp.shape == (2, 96, 96) and depth.last_choice == ["source", "source"]
    for i, cam in enumerate(views):
        v = depth.truth_renderer.views(cam)
        true = depth.true_disparity(v["src_depth"], v["src_alpha"])
        valid = true > 0
        assert valid.float().mean() > 0.9
        # the map is affine-ambiguous: a robust-enough least-squares fit recovers it up to the noise
        assert not torch.allclose(disp[i], true, atol=0.05)
        fit = _fit(disp[i], true, valid)
        rel = ((fit - true).abs() / true)[valid]
        assert rel.median() < 0.03, float(rel.median())
        depth_err = (1 / fit[valid].clamp_min(1e-3) - v["src_depth"][valid]).abs() / v["src_depth"][valid]
        assert depth_err.median() < 0.03
    # without corruption it is exactly affine
    exact = find("simulated-depth")({"corruption": 0.0})
    exact.attach_ground_truth(gt)
    d0 = exact.disparity(src[:1], cameras=views[:1])[0]
    v = exact.truth_renderer.views(views[0])
    true = exact.true_disparity(v["src_depth"], v["src_alpha"])
    assert (_fit(d0, true, true > 0) - true)[true > 0].abs().max() < 1e-4
    # an image of the edited scene gets the edited scene's depth (the moustache is nearer)
    edited = torch.stack([depth.truth_renderer.views(views[0])["edit_rgb"]])
    d_edit = depth.disparity(edited, cameras=views[:1])[0]
    assert depth.last_choice == ["edited"]
    moved = (v["edit_depth"] - v["src_depth"]).abs() > 0.02
    assert moved.sum() > 10
    assert (d_edit[moved] > disp[0][moved]).float().mean() > 0.8  # same map per view: nearer = larger
    # deterministic given the seed
    assert torch.equal(disp, depth.disparity(src, cameras=views))
    other = find("simulated-depth")({"seed": 4})
    other.attach_ground_truth(gt)
    assert not torch.allclose(disp, other.disparity(src, cameras=views))


def test_simulated_depth_edit_bias_moves_only_the_new_geometry(cams):
    """edit_scale_bias / edit_shift_bias change the disparity only where the image shows the edit's
    new geometry, so a calibration outside the edit cannot see them (the stability sweep's depth bias)."""
    gt = make_edit("add")
    plain = find("simulated-depth")({"corruption": 0.0})
    biased = find("simulated-depth")({"corruption": 0.0, "edit_scale_bias": 0.5, "edit_shift_bias": 0.1})
    for d in (plain, biased):
        d.attach_ground_truth(gt)
    cam = cams["front"]
    v = plain.truth_renderer.views(cam)
    d0, d1 = (d.disparity(v["edit_rgb"][None], cameras=[cam])[0] for d in (plain, biased))
    disp_src = plain.true_disparity(v["src_depth"], v["src_alpha"])
    new_geometry = (plain.true_disparity(v["edit_depth"], v["edit_alpha"]) - disp_src).abs() > 1e-3 * disp_src.max()
    changed = (d1 - d0).abs() > 1e-6
    assert changed.sum() > 10 and not (changed & ~new_geometry).any()
    assert (d1[changed] > d0[changed]).all()  # larger disparity: the new geometry comes nearer
    # an image of the source shows no new geometry: untouched
    src = v["src_rgb"][None]
    assert torch.equal(plain.disparity(src, cameras=[cam]), biased.disparity(src, cameras=[cam]))


def test_simulated_depth_following_the_drawn_edit_sees_an_object_where_the_image_draws_it(cams):
    """An editor draws the object a few pixels off its true place (position jitter): with
    `follow_drawn_px` the estimator reports the new geometry's depth where the image shows it, and
    the source's where the truth has the object but the image does not, as a real estimator would;
    compared in place (0, the default) it mostly sees the object only where the drawing overlaps the truth."""
    from gs_regional.sim.depth import shifted

    gt = make_edit("add")
    depth = find("simulated-depth")({"corruption": 0.0, "follow_drawn_px": 6})
    in_place_only = find("simulated-depth")({"corruption": 0.0})
    depth.attach_ground_truth(gt)
    in_place_only.attach_ground_truth(gt)
    cam = cams["front"]
    v = depth.truth_renderer.views(cam)
    layer = ((v["edit_rgb"] - v["src_rgb"]).abs().amax(-1) > 1e-3) | ((v["edit_depth"] - v["src_depth"]).abs() > 1e-6)
    dx, dy = 3, -2
    drawn = torch.where(shifted(layer, dx, dy)[..., None], shifted(v["edit_rgb"], dx, dy), v["src_rgb"])
    source = depth.disparity(v["src_rgb"][None], cameras=[cam])[0]
    in_place = depth.disparity(v["edit_rgb"][None], cameras=[cam])[0]  # the moustache where the truth has it
    seen = depth.disparity(drawn[None], cameras=[cam])[0]
    assert depth.last_shift == [(dx, dy)]
    nearer = (v["src_depth"] - v["edit_depth"]) > 0.02
    at_drawn = shifted(nearer, dx, dy) & ~nearer
    left_bare = nearer & ~shifted(layer, dx, dy)
    assert at_drawn.sum() > 10 and left_bare.sum() > 10
    # where it is drawn: the moustache's own disparity, moved with it
    assert ((seen - shifted(in_place, dx, dy))[at_drawn].abs() < 1e-5).float().mean() > 0.9
    assert ((seen - source)[at_drawn].abs() > 1e-3).float().mean() > 0.9
    assert (seen[left_bare] - source[left_bare]).abs().max() < 1e-5  # where it is not drawn: the source
    # compared in place: the drawn object clear of the true one shows the source's depth
    assert ((in_place_only.disparity(drawn[None], cameras=[cam])[0] - source)[at_drawn].abs() < 1e-5).float().mean() > 0.6
    assert in_place_only.last_shift == [(0, 0)]
