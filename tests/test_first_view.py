"""The first-view choice and the safe stop (gs_regional/stages/first_view.py) as plain functions:
known answers on three synthetic views, no system, no Lightning."""
import torch

from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.metrics.region import render_selection
from gs_regional.registry import find
from gs_regional.sim.scene import look_at
from gs_regional.stages.first_view import check_edit, choose_first_view, stop_message
from gs_regional.stages.localize import covered

H = W = 32


def _views(inside):
    """Three views of a grey scene whose selection is a square at the centre; `inside[v]`: whether
    view v's full edit paints the square (True), a square as large in a corner (False) or one
    beside it, a quarter of it within 2 px of the square ("beside": an edit that only just missed)."""
    source = torch.full((H, W, 3), 0.5)
    region = torch.zeros(H, W, dtype=torch.bool)
    region[12:20, 12:20] = True
    edits = {}
    for v, ok in enumerate(inside):
        out = source.clone()
        if ok == "beside":
            out[12:20, 20:28] = torch.tensor([0.9, 0.1, 0.1])
        elif ok:
            out[12:20, 12:20] = torch.tensor([0.9, 0.1, 0.1])
        else:
            out[0:8, 0:8] = torch.tensor([0.9, 0.1, 0.1])
        edits[v] = out
    return source, region, edits


def _choose(inside, min_edit_coverage=0.5):
    source, region, edits = _views(inside)
    views = list(range(len(inside)))
    edited = []

    def edit(v):
        edited.append(v)
        return edits[v]

    first = choose_first_view(
        views, torch.full((len(views),), 64.0), {v: region for v in views}, [region] * len(views), 0, edit,
        lambda v, out: check_edit(v, out, source, region, torch.ones(H, W), torch.ones(H, W)), min_edit_coverage)
    return first, edited


def test_an_edit_in_the_selection_goes_on_from_the_first_view():
    first, edited = _choose([True, True, True])
    assert first.view == 0 and not first.stop and edited == [0]
    assert first.decided is first.checks[0] and first.decided.coverage > 0.9
    assert first.checks[0].as_dict()["decides"] is True and "too_small_to_judge" not in first.checks[0].as_dict()


def test_an_edit_elsewhere_in_every_view_stops_with_one_message():
    first, edited = _choose([False, False, False])
    assert first.stop and edited == [0, 1]  # the second view is edited too: one view never decides alone
    assert first.decided.coverage < 0.1
    assert "system.localization.min_edit_coverage=0.5" in stop_message(first, 0.5)


def test_a_first_edit_that_only_just_missed_lets_the_next_view_decide_and_the_stop_names_both():
    first, edited = _choose(["beside", False, False])
    assert first.stop and edited == [0, 1] and first.view == 0  # initialization would stay with the first view
    assert first.own.coverage == 0.25 and first.decided.view == 1
    message = stop_message(first, 0.5)
    assert message.startswith("initialize: view 1, where the editor's 2D masks and the selection overlap most")
    assert "(view 0, edited first, puts 0.25 in it)" in message and "showed almost nothing" not in message


def test_a_first_edit_placed_elsewhere_is_outvoted_by_two_views_that_agree():
    first, edited = _choose([False, True, True])
    assert not first.stop and first.view == 1 and edited == [0, 1, 2]
    assert first.decided.view == 1 and len(first.checks) == 3


def test_a_coverage_check_of_zero_never_stops():
    first, _ = _choose([False, False, False], min_edit_coverage=0.0)
    assert not first.stop and first.view == 0


def test_a_part_the_selection_renders_faintly_is_checked_where_it_shows():
    """A small part whose render covers no pixel by half (a patch of translucent Gaussians in front
    of a wall, like the face splat's patches of a few Gaussians): checked against the pixels the
    selection covers by half of its most (`covered(..., faint=True)`, as the views-disagree stop
    does), an edit painted on the patch lies in the selection (against the pixels covered by half,
    the region is empty and every edit would stop the run), and an edit as large painted in a
    corner still lies elsewhere."""
    ys, xs = torch.meshgrid(torch.linspace(-1, 1, 24), torch.linspace(-1, 1, 24), indexing="ij")
    wall = torch.stack([xs.flatten(), ys.flatten(), torch.zeros(24 * 24)], 1)
    py, px = torch.meshgrid(torch.linspace(-0.08, 0.08, 3), torch.linspace(-0.08, 0.08, 3), indexing="ij")
    patch = torch.stack([px.flatten(), py.flatten(), torch.full((9,), 0.2)], 1)
    n = len(wall) + len(patch)
    opacity = torch.cat([torch.full((len(wall),), 0.99), torch.full((len(patch),), 0.15)])
    model = GaussianModel.from_tensors(
        means=torch.cat([wall, patch]), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        log_scales=torch.full((n, 3), -3.0), opacity_logits=torch.logit(opacity),
        sh_dc=torch.cat([torch.zeros(len(wall), 3), torch.tensor([[1.0, -1.0, -1.0]]).repeat(len(patch), 1)]))
    selected = torch.arange(n) >= len(wall)
    renderer = find("torch-rasterizer")()
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), H, W)
    with torch.no_grad():
        out = renderer.render(model, cam)
        cover = render_selection(model, renderer, cam, selected)
    assert 0.1 < float(cover.max()) < 0.5  # faint: no pixel covered by half
    source = out["rgb"].clamp(0, 1)
    on_patch, in_corner = source.clone(), source.clone()
    on_patch[cover > 0.1] = torch.tensor([0.2, 0.2, 0.9])
    in_corner[:4, :4] = torch.tensor([0.2, 0.2, 0.9])
    alpha, depth = out["alpha"].reshape(H, W), out["depth"].reshape(H, W)

    def check(edited, faint):
        return check_edit(0, edited, source, covered(cover, faint), alpha, depth)

    assert not bool(covered(cover).any()) and check(on_patch, False).elsewhere(0.5)  # by half: empty
    assert check(on_patch, True).agrees(0.5)
    assert check(in_corner, True).elsewhere(0.5)
    # a selection covering pixels by half is checked against those, faint or not
    assert torch.equal(covered(cover * 2, True), covered(cover * 2))
