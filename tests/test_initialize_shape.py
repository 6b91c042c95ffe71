"""Depth initialization adds Gaussians only where the shape changes, on the synthetic scene's known edits with the simulated editor and depth:
a recolour adds (close to) none, an addition adds next to the true new Gaussians, and a
calibration that cannot be trusted falls back to densification with a warning in metrics.json."""
from pathlib import Path
from typing import Optional

import numpy as np
import pytest
import torch

from trial_helpers import launch, metrics_of, trial_of
from gs_regional.stages.initialize import InitConfig, new_gaussians_from_depth
from gs_regional.stages.localize import render_selection
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.registry import find
from gs_regional.sim.scene import make_cameras, make_edit

VIEW = 10  # a frontal view of the face (the demo picks it as its first edited view)


def initialize(edit: str, corruption: float = 1.0, view: int = VIEW, n_cameras: int = 40, size: int = 96,
               editor_seed: int = 0, fill: bool = False, cfg: Optional[InitConfig] = None, back: bool = False):
    """new_gaussians_from_depth at `view` (a frontal one by default) of the synthetic `edit`, with
    the true 2D region (`fill`: a region covering every rendered pixel, none left to calibrate on)."""
    gt = make_edit(edit)
    cam = make_cameras(n_cameras, size, size)[0][view]
    renderer = find("torch-rasterizer")()
    editor = find("simulated-editor")({"seed": editor_seed})
    depth = find("simulated-depth")({"corruption": corruption})
    editor.attach_ground_truth(gt)
    depth.attach_ground_truth(gt)
    with torch.no_grad():
        out = renderer.render(gt.source, cam)
        edited = editor.edit(out["rgb"][None], out["rgb"][None], gt.prompt, t_start=None, seed=0, cameras=[cam])[0]
        region = render_selection(gt.source, renderer, cam, gt.region) > 0.5
        if fill:
            region = out["alpha"].reshape(region.shape) > 0.01
        disp = depth.disparity(torch.stack([out["rgb"], edited]), cameras=[cam, cam])
        params, report, _ = new_gaussians_from_depth(
            cam, out["rgb"], edited, region, out["depth"], out["alpha"], disp[0], disp[1], cfg or InitConfig(), 0,
            region_means=gt.source.means[gt.region], back=back,
        )
    return gt, params, report


def test_a_recolour_adds_no_geometry():
    _, _, report = initialize("recolor")
    print(report)
    # The colours of the region change everywhere, its depth nowhere: a handful of noise pixels
    # beyond 4 sigma at most (the simulated depth's noise is random, so not exactly zero).
    assert report["added"] <= 0.01 * report["region_pixels"]
    assert "rejected" not in report and report["calibration_residual"] < 0.05
    assert report["depth_threshold"] >= 4 * report["depth_noise"] > 0


def test_an_edit_that_changes_nothing_places_no_far_side_either():
    _, params, report = initialize("empty", back=True)
    assert report["added"] == 0 and report.get("placed_far_side", 0) == 0


def test_an_addition_adds_next_to_the_true_new_gaussians():
    gt, params, report = initialize("add")
    print(report)
    assert report["added"] >= 10
    new_means = gt.edited.means.detach()[len(gt.source):]  # the moustache: the Gaussians the true edit adds
    assert new_means.shape[0] > 0
    extent = float((new_means.max(0).values - new_means.min(0).values).norm())
    distance = torch.cdist(params["means"], new_means).min(1).values
    # Most added points lie on the moustache (within 10% of its size); depth noise puts a few farther.
    assert float(distance.median()) < 0.1 * extent
    assert float((distance < 0.2 * extent).float().mean()) >= 0.8


def test_an_addition_places_about_as_many_gaussians_at_four_times_the_resolution():
    gt, small, report_small = initialize("add", size=96)
    _, large, report_large = initialize("add", size=384)
    # 16x the pixels of changed depth, each 3 x 3 block of them one Gaussian (PLACEMENT_GRID_CELLS)
    assert report_large["placed_pixels"] > 8 * report_small["placed_pixels"]
    n_small, n_large = small["means"].shape[0], large["means"].shape[0]
    assert 0.5 * n_small <= n_large <= 2.5 * n_small, (n_small, n_large)  # one per pixel: 465 against 41
    # each stands for the pixels it merged: up to 3x the size of a pixel's Gaussian at 384²
    assert float(large["log_scales"].exp().median()) > 2 * float(small["log_scales"].exp().median()) * 96 / 384
    new_means = gt.edited.means.detach()[len(gt.source):]
    extent = float((new_means.max(0).values - new_means.min(0).values).norm())
    distance = torch.cdist(large["means"], new_means).min(1).values
    assert float(distance.median()) < 0.1 * extent  # still on the moustache


def test_a_recolour_at_four_times_the_resolution_still_adds_no_geometry():
    _, _, report = initialize("recolor", size=384)
    assert report["placed_pixels"] <= 0.01 * report["region_pixels"] and report["added"] <= report["placed_pixels"]


@pytest.mark.parametrize("corruption", [1.0, 3.0])
def test_a_recolour_whose_region_fills_the_view_is_told_without_calibration(corruption):
    """A region that covers every rendered pixel leaves none to calibrate the monocular depth on.
    Whether the shape changes is then told from the two disparities alone (edited against unedited):
    a recolour shows no change (trusted: nothing added, refinement recolours without densifying,
    where the rejected calibration densified), an addition shows one (calibrated on the pixels the
    edit leaves unchanged, the next test; rejected here, where no count of pixels is enough)."""
    _, params, report = initialize("recolor", corruption=corruption, fill=True)
    print(report)
    assert report["calibration_pixels"] < InitConfig().min_calibration_pixels
    assert "rejected" not in report and report["added"] == 0 and not params
    assert report["uncalibrated"]["shape_changed"] is False
    # The head as the region, and no calibration allowed: the same verdicts on both edits.
    no_calibration = InitConfig(min_calibration_pixels=10**9)
    _, params, report = initialize("recolor", corruption=corruption, cfg=no_calibration)
    print(report)
    assert "rejected" not in report and report["added"] == 0 and report["uncalibrated"]["shape_changed"] is False
    _, _, report = initialize("add", corruption=corruption, cfg=no_calibration)
    print(report)
    assert "rejected" in report and report["added"] == 0
    u = report["uncalibrated"]
    assert u["shape_changed"] is True and u["nearer_pixels"] > 3 * (u["farther_pixels"] + 1)


def test_uncalibrated_shape_change_on_known_disparities():
    """The uncalibrated test on disparities with a known answer: a slanted surface seen under two
    different affine maps with noise has no change of shape; the same with a nearer bump over 3 %
    of the pixels has one; a bump moved *back* (uncovered, not added) is none."""
    from gs_regional.stages.initialize import disparity_change, shape_change_verdict

    g = torch.Generator().manual_seed(0)
    h = w = 64
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    true = 1.0 / (2.0 + xx + 0.5 * yy)
    valid = torch.ones(h, w, dtype=torch.bool)
    bump = ((yy - 0.5) ** 2 + (xx - 0.5) ** 2) < 0.1 ** 2  # about 3 % of the pixels
    cfg = InitConfig()

    def mono(d, scale, shift):
        return scale * d + shift + 0.005 * float(true.max() - true.min()) * torch.randn(h, w, generator=g)

    unedited = mono(true, 2.0, 0.1)
    def verdict(edited, opaque=valid):
        return shape_change_verdict(disparity_change(unedited, edited, opaque, cfg), valid, cfg)

    same = verdict(mono(true, 3.5, -0.2))
    nearer = verdict(mono(torch.where(bump, true * 1.2, true), 3.5, -0.2))
    back = verdict(mono(torch.where(bump, true * 0.8, true), 3.5, -0.2))
    print(same, nearer, back)
    assert same["shape_changed"] is False and nearer["shape_changed"] is True and back["shape_changed"] is False
    assert nearer["nearer_pixels"] >= 0.8 * int(bump.sum())
    assert verdict(unedited, opaque=valid & False) is None  # nothing opaque


def test_a_corrupted_depth_is_rejected():
    _, params, report = initialize("add", corruption=20.0)
    print(report)
    assert report["added"] == 0 and params == {}
    assert report["calibration_residual"] > 0.05 and "fits the rendered depth poorly" in report["rejected"]


def tiny_run(tmp_path, name, *overrides):
    """The small demo at 64² (24 views, 8 of them localized): the moustache is thick enough there
    for its change of shape to show in depth, and the head's silhouette is where the depth-change
    test can be fooled."""
    return metrics_of(launch(tmp_path, name, "data.n_cameras=24", "data.width=64", "data.height=64",
                             "system.localization.max_views=8", *overrides))


def test_a_recolour_is_refined_without_adding_gaussians(tmp_path):
    """A trusted calibration that finds no change of shape: refinement recolours the Gaussians
    there are, densifies none and leaves their shape and opacity as they were (the true recolour
    adds none; densified, the region's Gaussians grow over its surroundings)."""
    # 24 cameras of 64 px: the head's silhouette there is where noise in depth over the background
    # (or a second calibration extrapolated over the region) could pass the depth-change test.
    m = tiny_run(tmp_path, "recolour", "data.edit=recolor", "system.prompt=make his head red")
    assert "rejected" not in m["init"] and m["count_added_init"] == 0
    assert len(m["init"]["views_checked"]) == InitConfig().views  # no view's depth shows a change of shape
    assert m["gaussians_added"] == 0 == m["true_gaussians_added"] and m["gaussians_after"] == m["gaussians_before"]
    assert m["warnings"] == []
    assert m["t_starts"] == [750, 500, 250]  # a recolour's schedule: t_schedule, not shape_t_schedule
    edited = GaussianModel.from_ply(Path(trial_of(tmp_path, "recolour")) / "save" / "edited.ply")
    source = make_edit("recolor").source
    for name in ("means", "quats", "log_scales", "opacity_logits"):  # PLY float32 round trip: exact
        assert torch.equal(getattr(edited, name).detach(), getattr(source, name).detach().float()), name
    changed = (edited.sh_dc.detach() != source.sh_dc.detach()).flatten(1).any(1).numpy()
    selected = np.load(Path(trial_of(tmp_path, "recolour")) / "save" / "edit_mask.npz")["mask"]
    assert changed.any() and not changed[~selected].any()  # colours change in the selection only


def test_a_recolour_saves_the_gates_blend_of_each_source_gaussian_as_the_gate_judged_it(tmp_path):
    """save/edit_mask.npz `gate_blend` (scripts/changed_gaussians.py reads it) is the blend the gate
    judged each source Gaussian on: every selected one an edited view saw and the gate took
    reaches the gate's threshold on it; of those that reach it, only the parts of their own
    (`count_recolour_distinct`) were declined."""
    from gs_regional.bench import changed_gaussians
    from gs_regional.stages.composite import gate_threshold
    from gs_regional.stages.strategies import GATE_REFERENCE_QUANTILE, RefineConfig

    m = tiny_run(tmp_path, "recolour", "data.edit=recolor", "system.prompt=make his head red")
    trial = trial_of(tmp_path, "recolour")
    with np.load(trial / "save" / "edit_mask.npz") as f:
        blend, taken, selected = (torch.from_numpy(f[k]) for k in ("gate_blend", "mask", "source_selection"))
    n = len(make_edit("recolor").source)
    assert blend.shape == taken.shape == selected.shape == (n,)  # the source's rows, in order (a recolour adds none here)
    judged = selected.bool() & ~blend.isnan()
    need = gate_threshold(blend, judged, RefineConfig().min_edit_blend, GATE_REFERENCE_QUANTILE)
    took, declined = taken.bool() & judged, ~taken.bool() & judged
    assert int(took.sum()) > 0 and int(declined.sum()) > 0
    assert float(blend[took].min()) >= need - 1e-5  # a row the gate took reached its threshold
    assert int((declined & (blend >= need + 1e-5)).sum()) <= m["count_recolour_distinct"]  # else: parts of their own
    band = changed_gaussians.report(str(trial))["editable, in the true region"]["gate blend"]
    assert len(band) == 3 and need - 1e-5 <= band[0] <= band[1] <= band[2] <= 1.0


def test_an_addition_is_found_in_a_second_view_when_the_first_edit_misses_it(tmp_path, monkeypatch):
    """One full edit can miss a thin new object: the editor draws it a few pixels off (more than
    a moustache at 64² is thick) or not at all, and the depth of that image shows no change of
    shape. The edit is not taken for a recolour on that one view: the next view's edit shows the
    moustache in depth and the Gaussians come from there. Here the first full edit returns its
    input unchanged (the editor's miss, made certain rather than left to a draw of its jitter)."""
    from gs_regional.sim.editor import SimulatedEditor

    edit, missed = SimulatedEditor._edit, []

    def first_full_edit_misses(self, images, cond_images, prompt, t_start, seeds, cameras):
        if t_start is None and not missed:
            missed.append(cameras[0].image_name)
            return images.clone()
        return edit(self, images, cond_images, prompt, t_start, seeds, cameras)

    monkeypatch.setattr(SimulatedEditor, "_edit", first_full_edit_misses)
    m = tiny_run(tmp_path, "add64", "system.refine.cycles=1")
    assert len(missed) == 1 and len(m["init"]["views_checked"]) == 2
    assert m["count_added_init"] >= 5 and m["v_first"] == m["init"]["views_checked"][1]


def test_an_addition_whose_region_fills_the_view_is_calibrated_on_what_the_edit_leaves(tmp_path):
    """A big ball put on a part that fills the view (the donut's icing seen from above): no pixel
    outside the region to calibrate the monocular depth on. The depth is calibrated on the opaque
    pixels the edit leaves unchanged instead, and the ball's Gaussians land on the true ball
    (rejected, nothing would be added, and densification alone barely draws such a ball)."""
    from gs_regional.sim.scene import make_scene
    from gs_regional.sim.splat_truth import SplatTruthDataModule

    model, labels, names = make_scene(0, n_object=2000, n_background=500)
    ply = tmp_path / "figure.ply"
    model.select(labels >= names.index("body")).save_ply(str(ply))
    dm = SplatTruthDataModule({"ply": str(ply), "up": [0.0, 1.0, 0.0], "edit": "add", "anchor": [0.0, 0.0, 0.0],
                               "add_radius": 0.25, "add_count": 400, "n_cameras": 8, "width": 64, "height": 64})
    dm.setup()
    gt, cam = dm.scene.ground_truth, dm.scene.cameras[4]  # the upper ring: it sees the ball on the head
    renderer, editor, depth = find("torch-rasterizer")(), find("simulated-editor")(), find("simulated-depth")()
    editor.attach_ground_truth(gt)
    depth.attach_ground_truth(gt)
    with torch.no_grad():
        out = renderer.render(gt.source, cam)
        edited = editor.edit(out["rgb"][None], out["rgb"][None], gt.prompt, t_start=None, seed=0, cameras=[cam])[0]
        fill = out["alpha"].reshape(out["rgb"].shape[:2]) > 0.01  # the region: every rendered pixel
        disp = depth.disparity(torch.stack([out["rgb"], edited]), cameras=[cam, cam])
        params, report, _ = new_gaussians_from_depth(
            cam, out["rgb"], edited, fill, out["depth"], out["alpha"], disp[0], disp[1], InitConfig(), 0,
            region_means=gt.source.means)
    print(report)
    assert report["calibration_pixels"] < InitConfig().min_calibration_pixels
    assert report["uncalibrated"]["shape_changed"] is True
    assert "rejected" not in report and report["calibration_pixels_unchanged"] >= InitConfig().min_calibration_pixels
    new_means = gt.edited.means.detach()[len(gt.source):]
    extent = float((new_means.max(0).values - new_means.min(0).values).norm())
    distance = torch.cdist(params["means"], new_means).min(1).values
    assert report["added"] >= 20
    assert float(distance.median()) < 0.1 * extent
    assert float((distance < 0.2 * extent).float().mean()) >= 0.8


def test_an_addition_is_placed_from_the_view_whose_depth_shows_most_of_it():
    """The first edited view is the one the 2D masks are largest in; on a round part (a head) every
    view's mask is about as large, and the first may see the new object edge-on: the moustache
    seen from the side changes the depth of a few pixels, and the object placed from there comes
    out a wisp (the demo on scene seed 3: +3.0 dB in the footprint, +9.8 placed from a frontal
    view). Initialization checks the next view too and places the object from the one whose
    depth shows the larger change of shape."""
    from gs_regional.stages.initialize import PLACED_ENOUGH, initialize_from_views

    gt = make_edit("add")
    cams = make_cameras(40, 96, 96)[0]
    renderer = find("torch-rasterizer")()
    editor = find("simulated-editor")({"seed": 0})
    depth = find("simulated-depth")({})
    editor.attach_ground_truth(gt)
    depth.attach_ground_truth(gt)
    renders = {}

    def render(u):
        if u not in renders:
            with torch.no_grad():
                renders[u] = renderer.render(gt.source, cams[u])
        return renders[u]

    def run(order, changed_px=None):
        with torch.no_grad():
            return initialize_from_views(
                order, lambda u: editor.edit(render(u)["rgb"][None], render(u)["rgb"][None], gt.prompt, t_start=None,
                                             seed=0, cameras=[cams[u]])[0],
                lambda u: render(u)["rgb"], lambda u: cams[u], render,
                lambda images, cameras: depth.disparity(images, cameras=cameras),
                lambda u: render_selection(gt.source, renderer, cams[u], gt.region) > 0.5, InitConfig(), 0,
                region_means=gt.source.means[gt.region], changed_px=changed_px)

    side, front = 0, VIEW
    reports = {u: run([u]).report for u in (side, front)}
    alone = {u: r["placed_pixels"] for u, r in reports.items()}  # pixels of changed depth (not the far side)
    assert 0 < alone[side] < alone[front]  # seen edge-on, the moustache changes the depth of fewer pixels
    found = run([side, front])
    assert found.report["views_checked"] == [side, front]
    assert found.report["views_placed"] == [reports[side]["added"], reports[front]["added"]]  # why the front was taken
    assert found.view == front and found.report["added"] == reports[front]["added"]
    # Placed from the better view whichever comes first; a view whose depth shows no change is not taken.
    assert run([front, side]).view == front
    # A first view whose depth places PLACED_ENOUGH per pixel its edit changes is not second-guessed
    # (the next view's full edit is not spent); one that places less is.
    enough = alone[front] / PLACED_ENOUGH
    assert run([front, side], changed_px=enough).report["views_checked"] == [front]
    assert run([front, side], changed_px=1.01 * enough).report["views_checked"] == [front, side]
    assert run([side, front], changed_px=alone[side] / PLACED_ENOUGH + 1).view == front


def test_a_new_point_is_kept_only_where_the_other_edited_views_see_the_edit_there():
    """seen_as_edit on a known answer: two cameras facing each other across the origin, a point
    at the origin. Kept when a view that sees it shows the edit on its pixel; dropped when that
    view sees the place and its edit shows nothing there (a floater from one view's jitter), or
    when no view sees it at all; a view whose surface lies in front of the point has no say."""
    from gs_regional.sim.scene import look_at
    from gs_regional.stages.initialize import seen_as_edit

    cams = [look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), 32, 32), look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), 32, 32)]
    point = torch.zeros(1, 3)
    u, v, z = cams[0].project(point)
    assert abs(float(u) - 16) < 1e-4 and abs(float(v) - 16) < 1e-4 and abs(float(z) - 3) < 1e-4
    far = [torch.full((32, 32), float("inf"))] * 2  # nothing rendered: every view sees the point
    shows, empty = torch.zeros(32, 32, dtype=torch.bool), torch.zeros(32, 32, dtype=torch.bool)
    shows[16, 16] = True
    assert bool(seen_as_edit(point, cams, [shows, shows], far)[0])
    assert not bool(seen_as_edit(point, cams, [shows, empty], far)[0])  # the second view saw nothing there
    assert not bool(seen_as_edit(point, cams[:0], [], [])[0])  # no view supports it
    hidden = torch.full((32, 32), 2.0)  # the second view's surface at depth 2, in front of the point
    assert bool(seen_as_edit(point, cams, [shows, empty], [far[0], hidden])[0])


def _ball_on_the_head():
    """A synthetic scene with a ball resting on the figure's head as the true edit, the cameras,
    and the ball's centre and radius."""
    from gs_regional.sim.splat_truth import resting_contact, sphere_gaussians, with_added
    from gs_regional.sim.truth import GroundTruth

    head = make_edit("recolor")
    source = head.source
    top = source.means.detach()[head.region]
    up = torch.tensor([0.0, 1.0, 0.0])
    r = 0.5 * float((top.max(0).values - top.min(0).values).max()) / 2
    through = top.mean(0)
    height, _ = resting_contact(source, through, up, r)
    centre = through + (height - 0.25 * r) * up
    ball = sphere_gaussians(centre, r, 400, [0.9, 0.1, 0.8], up, 0, source.sh_degree)
    edited, new_region = with_added(source, ball, head.region)
    gt = GroundTruth(source=source, edited=edited, region=head.region, new_region=new_region, front=head.front,
                     center=head.center, name="add", prompt="put a pink ball on his head")
    return gt, make_cameras(40, 96, 96)[0], centre, r


def _placed_in_holes(gt, cams, views, scene_rows: torch.Tensor) -> torch.Tensor:
    """(K, 3) the means of the Gaussians `new_gaussians_in_holes` places in each of `views` (camera
    indices) when the scene holds `scene_rows` of `gt.edited` (its first len(gt.source) rows the
    source's, the rest the true addition's): each view's target is the simulated editor's partial
    edit of the scene's render, composited, as a refinement cycle makes it, and the other views are
    the cycle's other edited views."""
    from gs_regional.metrics.region import render_selection
    from gs_regional.stages.composite import composite_target
    from gs_regional.stages.initialize import HOLE_MAX_DISTANCE, new_gaussians_in_holes

    n = len(gt.source)
    renderer = find("torch-rasterizer")()
    editor = find("simulated-editor")({"seed": 0})
    depth = find("simulated-depth")({})
    editor.attach_ground_truth(gt)
    depth.attach_ground_truth(gt)
    scene = gt.edited.select(scene_rows)
    added_rows = torch.arange(len(scene)) >= n
    made = []
    with torch.no_grad():
        for i in views:
            cam = cams[i]
            out = renderer.render(scene, cam)
            source = renderer.render(gt.source, cam)
            edited = editor.edit(out["rgb"][None], source["rgb"][None], gt.prompt, t_start=350, seed=0, cameras=[cam])[0]
            added = render_selection(scene, renderer, cam, added_rows)
            region = render_selection(gt.source, renderer, cam, gt.region)
            target = composite_target(edited, source["rgb"], region, added, opaque=source["alpha"] > 0.5)
            shows = (target - source["rgb"]).abs().amax(-1) > 2.0 / 255
            surface = torch.where(out["alpha"] > 0.5, out["depth"], torch.full_like(region, float("inf")))
            made.append((cam, out, target, shows, added, (region > 0.5) | (added > 0.05), surface))
        placed = []
        for k, (cam, out, target, shows, added, region, _) in enumerate(made):
            other = [v for j, v in enumerate(made) if j != k]
            current = {"rgb": out["rgb"].clamp(0, 1), "depth": out["depth"], "alpha": out["alpha"]}
            params = new_gaussians_in_holes(
                cam, current, target, shows, added, region,
                depth.disparity(torch.stack([current["rgb"], target]), cameras=[cam, cam]),
                ([v[0] for v in other], [v[3] for v in other], [v[6] for v in other]), InitConfig(), gt.source.sh_degree,
                scene.means.detach()[added_rows], HOLE_MAX_DISTANCE)
            if params:
                placed.append(params["means"])
    return torch.cat(placed) if placed else torch.zeros(0, 3)


def test_a_cycle_places_the_side_of_an_added_ball_that_the_first_view_did_not_see():
    """An addition the editor draws whole in some views and only partly in the scene: the scene
    holds the true ball's half that faces the first view, and two side views' targets (partial
    edits, composited, as a refinement cycle makes them) draw the whole ball. The Gaussians
    `new_gaussians_in_holes` places lie on the true ball's surface, on the half the scene lacked.
    With the whole ball in the scene there is nothing to place."""
    gt, cams, centre, r = _ball_on_the_head()
    n = len(gt.source)
    first = cams[VIEW].center
    towards_first = torch.nn.functional.normalize(first - centre, dim=0)
    ball_means = gt.edited.means.detach()[n:]
    facing = (ball_means - centre) @ towards_first > 0
    side = [i for i, c in enumerate(cams)
            if abs(float(torch.nn.functional.normalize(c.center - centre, dim=0) @ towards_first)) < 0.35][:2]
    assert len(side) == 2
    half = torch.cat([torch.ones(n, dtype=torch.bool), facing])
    placed = _placed_in_holes(gt, cams, side, half)
    assert len(placed) >= 5
    off_surface = ((placed - centre).norm(dim=1) - r).abs() / r
    assert float(off_surface.median()) < 0.35
    assert float((off_surface < 0.6).float().mean()) > 0.9
    lacked = (placed - centre) @ towards_first < 0.25 * r  # on the half the scene lacked (or its rim)
    assert float(lacked.float().mean()) > 0.8
    assert len(_placed_in_holes(gt, cams, side, torch.ones(len(gt.edited), dtype=torch.bool))) == 0


def test_a_cycle_paints_the_half_of_a_flat_addition_the_scene_lacks_onto_the_surface():
    """An addition that lies on the part (the synthetic moustache on the face: its depth hardly
    changes) drawn whole by the editor in two frontal views while the scene holds only its half on
    one side of the face, as a side view's depth placed it. The Gaussians a cycle places
    (`new_gaussians_in_holes`, its `painted_in_holes`) lie on the other half, on the true
    moustache (within a twentieth of its width of one of its Gaussians); with the whole moustache
    in the scene, next to none."""
    gt = make_edit("add")
    cams = make_cameras(40, 96, 96)[0]
    n = len(gt.source)
    moustache = gt.edited.means.detach()[n:]
    middle = float(moustache[:, 0].median())
    kept = moustache[:, 0] > middle
    frontal = [VIEW, VIEW + 1]
    placed = _placed_in_holes(gt, cams, frontal, torch.cat([torch.ones(n, dtype=torch.bool), kept]))
    assert len(placed) >= 10
    assert float((placed[:, 0] < middle).float().mean()) > 0.8  # the half the scene lacked
    width = float(moustache[:, 0].max() - moustache[:, 0].min())
    nearest = torch.cdist(placed, moustache).min(1).values  # (a few hundred rows: a test's all-pairs)
    assert float((nearest < 0.05 * width).float().mean()) > 0.9
    whole = _placed_in_holes(gt, cams, frontal, torch.ones(len(gt.edited), dtype=torch.bool))
    assert len(whole) <= 0.2 * len(placed)


def test_the_far_side_of_a_ball_placed_from_one_view_is_its_near_side_mirrored():
    """Known answer: a ball of radius 1 at depth 10 seen head-on (10 px across its radius, a pixel a
    tenth of it; the depth of each pixel its near surface, 10 - sqrt(1 - rho²)), a single pixel in
    front of it (the estimator's noise), and beside it a flat patch at depth 12. The ball's far side
    comes back mirrored about the plane DEPTH_TO_WIDTH radii behind its nearest point, within a
    tenth of its radius (at 1 that is the ball's own far side, 10 + sqrt(1 - rho²)); where the near
    side lies behind that plane (the ring of its silhouette), none; the stray pixel moves no part
    of it. The patch, for all one view can tell, is as deep as DEPTH_TO_WIDTH times its width."""
    from gs_regional.stages.initialize import DEPTH_TO_WIDTH, far_side_depth

    rows, cols = torch.meshgrid(torch.arange(64), torch.arange(64), indexing="ij")
    rho = ((rows - 20.0) ** 2 + (cols - 20.0) ** 2).sqrt() / 10.0  # in radii
    ball = rho < 1.0
    patch = (rows >= 36) & (cols >= 36) & (((rows - 49.5) ** 2 + (cols - 49.5) ** 2).sqrt() < 20.0)
    pixels = torch.cat([ball.nonzero(), patch.nonzero()])
    r = rho[pixels[:, 0], pixels[:, 1]]
    on_ball = ball[pixels[:, 0], pixels[:, 1]]
    depth = torch.where(on_ball, 10.0 - (1 - r.clamp(max=1) ** 2).sqrt(), torch.full_like(r, 12.0))
    depth[int((r == 0).nonzero()[0])] = 8.0  # the ball's centre pixel, a radius in front of it
    has, far = far_side_depth(pixels, depth, torch.full_like(depth, 0.1))
    mirrored = 2 * (9.0 + DEPTH_TO_WIDTH) - depth
    inner = on_ball & (r > 0) & (mirrored - depth > 0.2)
    assert bool(has[inner].all()) and float((far - mirrored)[inner].abs().max()) < 0.1
    assert not bool(has[on_ball & (mirrored < depth)].any())  # behind the plane: the silhouette's ring
    assert float(has[on_ball].float().mean()) > 0.5
    radius = (float((~on_ball).sum()) / torch.pi) ** 0.5 * 0.1
    assert bool(has[~on_ball].all()) and float((far[~on_ball] - 12.0 - 2 * DEPTH_TO_WIDTH * radius).abs().max()) < 0.1


def _ball_seen_from_the_front(size: int = 48, radius: float = 0.5):
    """The pixels of a front camera whose rays hit a ball at the origin, their depth and world
    points, and a camera looking at the ball from the side (+x)."""
    from gs_regional.sim.scene import look_at
    from gs_regional.stages.initialize import unproject

    front, side = look_at((0, 0, 3), (0, 0, 0), size, size), look_at((3, 0, 0), (0, 0, 0), size, size)

    def hits(cam):
        pix = torch.stack(torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij"), -1).reshape(-1, 2)
        centre = cam.camera_to_world[:3, 3]
        ray = unproject(cam, torch.ones(pix.shape[0]), pix) - centre  # camera depth 1
        b, a = (ray * centre).sum(-1), (ray * ray).sum(-1)
        disc = b * b - a * ((centre * centre).sum() - radius ** 2)
        depth = (-b - disc.clamp_min(0).sqrt()) / a
        return pix, disc > 0, depth, centre + depth[:, None] * ray

    pix, hit, depth, _ = hits(front)
    return front, side, pix[hit], depth[hit], hits(side)


def test_gaussians_placed_from_a_balls_depth_cover_it_seen_from_the_side():
    """One Gaussian per pixel of a ball's near side, from the front view's depth: seen from the side
    (90 degrees), the isotropic Gaussians of a pixel's width left a fifth of that half of the ball
    open (its rim, where neighbouring pixels lie several widths apart in depth); spread along the
    surface to their neighbours they cover it."""
    from gs_regional.stages.initialize import surface_covariances, unproject
    from gs_regional.utils.rotations import covariance_to_scales_quats

    front, side, pix, depth, (_, side_hit, _, side_points) = _ball_seen_from_the_front()
    means = unproject(front, depth, pix)
    width = depth / (0.5 * (front.fx + front.fy))
    renderer = find("torch-rasterizer")()
    near_half = side_hit & (side_points[:, 2] > 0.05)  # the side view's pixels of the ball's near half

    def covered(log_scales, quats):
        k = means.shape[0]
        model = GaussianModel.from_tensors(means, quats, log_scales, torch.full((k,), 2.0), torch.zeros(k, 3))
        with torch.no_grad():
            alpha = renderer.render(model, side)["alpha"].reshape(-1)
        return float((alpha[near_half] > 0.5).float().mean())

    isotropic = covered(torch.log(0.5 * width)[:, None].repeat(1, 3), torch.tensor([1.0, 0, 0, 0]).repeat(len(depth), 1))
    surface = covered(*covariance_to_scales_quats(surface_covariances(pix, means, width, front, 0.5)))
    assert isotropic < 0.85 and surface > 0.88, (isotropic, surface)


def test_gaussians_placed_from_depth_are_isotropic_facing_the_camera_and_never_bridge_a_jump():
    """On a surface facing the camera each Gaussian is the isotropic one of half a pixel's width;
    where the depth steps away by several pixel widths between neighbours (the object's edge over
    what lies behind) it does not stretch across."""
    from gs_regional.sim.scene import look_at
    from gs_regional.stages.initialize import SURFACE_REACH, surface_covariances, unproject

    cam = look_at((0, 0, 3), (0, 0, 0), 32, 32)
    pix = torch.stack(torch.meshgrid(torch.arange(8, 20), torch.arange(8, 20), indexing="ij"), -1).reshape(-1, 2)
    depth = torch.where(pix[:, 1] < 14, 2.5, 2.5 + 2 * SURFACE_REACH * 2.5 / cam.fx)  # a step behind at column 14
    width = depth / (0.5 * (cam.fx + cam.fy))
    std = torch.linalg.eigvalsh(surface_covariances(pix, unproject(cam, depth, pix), width, cam, 0.5)).sqrt()
    assert torch.allclose(std, (0.5 * width)[:, None].expand_as(std), rtol=1e-3)
