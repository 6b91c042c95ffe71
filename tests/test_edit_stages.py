"""The edit stages as plain functions: view choice, camera paths, unprojection, depth init."""
import math

import pytest
import torch

from gs_regional.data.cameras import Camera
from gs_regional.stages.initialize import InitConfig, new_gaussians_from_depth, unproject
from gs_regional.stages.localize import expand_selection, mask_agreement
from gs_regional.stages.views import camera_path, frontier_view, nearest_cameras, order_by_azimuth, spread_subset
from gs_regional.metrics.region import mask_metrics
from gs_regional.renderers.base import PixelWeights
from gs_regional.utils.image import dilate
from gs_regional.utils.sh import sh_to_rgb


def look_at(center, target=(0.0, 0.0, 0.0), up=(0.0, -1.0, 0.0), size=32, f=40.0, name=""):
    c = torch.tensor(center, dtype=torch.float64)
    z = torch.tensor(target, dtype=torch.float64) - c
    z = z / z.norm()
    x = torch.linalg.cross(torch.tensor(up, dtype=torch.float64), z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ c
    return Camera(w2c.float(), f, f, size / 2, size / 2, size, size, image_name=name)


def ring(n=12, radius=3.0):
    return [look_at((radius * math.sin(a), 0.0, -radius * math.cos(a)), name=f"{k:02d}")
            for k, a in enumerate(torch.linspace(-1.5, 1.5, n).tolist())]


def test_spread_subset_and_nearest():
    assert spread_subset(list(range(10)), 5) == [0, 2, 4, 6, 8]
    assert spread_subset([3, 4], 5) == [3, 4]
    cams = ring()
    near = nearest_cameras(cams, 5, 4, range(12))
    assert 5 not in near and set(near) == {3, 4, 6, 7}
    assert near[0] in (4, 6) and near[-1] in (3, 7)


def test_frontier_cycles_cover_more_views_than_random_ones():
    """On a ring of 24 cameras, 3 cycles of (frontal + its 4 nearest) edited views: starting each
    later cycle at the frontier of the edited views covers 9 views, the paper's random edited
    view at most that and, on average over seeds, clearly fewer."""
    cams, among = ring(24), list(range(24))

    def covered(choose):
        edited = sorted({11, *nearest_cameras(cams, 11, 4, among)})
        for cycle in (1, 2):
            v = choose(edited, torch.Generator().manual_seed(cycle))
            edited = sorted(set(edited) | {v, *nearest_cameras(cams, v, 4, among)})
        return len(edited)

    assert covered(lambda edited, gen: frontier_view(cams, edited, 4, among, gen)) == 9
    randoms = [covered(lambda edited, gen: edited[int(torch.randint(len(edited), (1,), generator=gen.manual_seed(s)))])
               for s in range(20)]
    assert max(randoms) <= 9 and sum(randoms) / len(randoms) < 8


def test_camera_path_passes_through_keyframes_and_azimuth_order():
    cams = ring(6)
    path = camera_path(cams, 11)
    assert len(path) == 11
    assert torch.allclose(path[0].world_to_camera, cams[0].world_to_camera, atol=1e-5)
    assert torch.allclose(path[-1].world_to_camera, cams[-1].world_to_camera, atol=1e-5)
    assert torch.allclose(path[2].world_to_camera, cams[1].world_to_camera, atol=1e-5)
    shuffled = [3, 0, 5, 1, 4, 2]
    order = order_by_azimuth(cams, shuffled)
    assert order in ([0, 1, 2, 3, 4, 5], [5, 4, 3, 2, 1, 0])


def test_unproject_lands_on_the_pixel_ray():
    cam = look_at((0.3, -0.2, -3.0), size=40)
    pixels = torch.tensor([[0, 0], [10, 30], [39, 39]])
    depth = torch.tensor([1.0, 2.5, 4.0])
    pts = unproject(cam, depth, pixels)
    cam_pts = pts @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    assert torch.allclose(cam_pts[:, 2], depth, atol=1e-5)
    u = cam_pts[:, 0] / cam_pts[:, 2] * cam.fx + cam.cx
    v = cam_pts[:, 1] / cam_pts[:, 2] * cam.fy + cam.cy
    assert torch.allclose(u, pixels[:, 1].float() + 0.5, atol=1e-4)
    assert torch.allclose(v, pixels[:, 0].float() + 0.5, atol=1e-4)


def test_depth_initialization_recovers_a_known_bump():
    """A wall at depth 4 with a block at depth 3 added in the edit; the monocular estimator sees
    disparity under a different unknown affine map for each image. The new Gaussians must sit at
    depth 3 where the block is, and nothing is added where nothing changed."""
    h = w = 32
    cam = look_at((0.0, 0.0, -4.0), size=w)
    d3 = torch.full((h, w), 4.0)
    alpha = torch.ones(h, w)
    unedited = torch.full((h, w, 3), 0.5)
    edited = unedited.clone()
    block = torch.zeros(h, w, dtype=torch.bool)
    block[10:20, 12:22] = True
    edited[block] = torch.tensor([0.9, 0.1, 0.1])
    true_edit_depth = torch.where(block, torch.tensor(3.0), d3)
    # Unknown affine maps of the true disparity (plus a ramp elsewhere so the fit is determined).
    ramp = torch.linspace(0, 1, w)[None].expand(h, w)
    d3 = 4.0 + ramp
    true_edit_depth = torch.where(block, torch.tensor(3.0), d3)
    disp_u = 2.0 * (1 / d3) + 0.3
    disp_e = 5.0 * (1 / true_edit_depth) - 0.1
    region = torch.zeros(h, w, dtype=torch.bool)
    region[8:22, 10:24] = True
    params, report, d_new = new_gaussians_from_depth(
        cam, unedited, edited, region, d3, alpha, disp_u, disp_e, InitConfig(dilate_px=0, median=1, scale_factor=1.0), sh_degree=0
    )
    assert report["added"] == int(block.sum())
    assert torch.allclose(d_new[block], torch.full((int(block.sum()),), 3.0), rtol=1e-4)
    cam_pts = params["means"] @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    assert torch.allclose(cam_pts[:, 2], torch.full_like(cam_pts[:, 2], 3.0), rtol=1e-4)
    rgb = sh_to_rgb(params["sh_dc"])
    assert torch.allclose(rgb, torch.tensor([0.9, 0.1, 0.1]).expand_as(rgb), atol=1e-5)
    capped, rep2, _ = new_gaussians_from_depth(
        cam, unedited, edited, region, d3, alpha, disp_u, disp_e, InitConfig(dilate_px=0, median=1, scale_factor=1.0, max_new=7), sh_degree=0
    )
    assert capped["means"].shape[0] == 7 and rep2["skipped_by_cap"] == int(block.sum()) - 7


def test_expand_selection_and_mask_metrics():
    means = torch.tensor([[0.0, 0, 0], [0.05, 0, 0], [1.0, 0, 0]])
    sel = torch.tensor([True, False, False])
    assert expand_selection(means, sel, 0.1).tolist() == [True, True, False]
    assert expand_selection(means, sel, 0.0).tolist() == [True, False, False]
    m = mask_metrics(torch.tensor([True, True, False]), torch.tensor([True, False, False]))
    assert m["mask_iou"] == 0.5 and m["mask_precision"] == 0.5 and m["mask_recall"] == 1.0


def test_an_object_beside_the_parts_silhouette_is_placed_on_the_part_not_behind_it():
    """A part (depth 2) in front of a wall (depth 5 + a ramp); the edit adds an object at depth 1.8
    that reaches past the part's silhouette over the wall. As with a small object seen by a real
    estimator, its disparity over the wall is mostly lost (30 % of the change kept): the transferred
    depth there is about 3.4, far behind the part, where it would be dropped as far from the
    region, and with it half the object. It takes the depth of the geometry beside it instead (the
    part at 2.0, the object's accepted pixels at 1.8), while over the part the transferred 1.8 stands."""
    h = w = 32
    cam = look_at((0.0, 0.0, -4.0), size=w)
    ramp = torch.linspace(0, 1, w)[None].expand(h, w)
    part = torch.zeros(h, w, dtype=torch.bool)
    part[10:22, 8:17] = True
    d3 = torch.where(part, torch.tensor(2.0), 5.0 + ramp)
    obj = torch.zeros(h, w, dtype=torch.bool)
    obj[12:16, 14:20] = True
    over_part, over_wall = obj & part, obj & ~part
    alpha = torch.ones(h, w)
    unedited = torch.full((h, w, 3), 0.5)
    edited = unedited.clone()
    edited[obj] = torch.tensor([0.9, 0.1, 0.1])
    disp_true = torch.where(obj, 1 / torch.tensor(1.8), 1 / d3)
    disp_seen = torch.where(over_wall, 0.3 * disp_true + 0.7 / d3, disp_true)  # the object's disparity lost over the wall
    disp_u = 2.0 * (1 / d3) + 0.3
    disp_e = 5.0 * disp_seen - 0.1
    cfg = InitConfig(dilate_px=3, median=1, scale_factor=1.0)
    part_means = unproject(cam, d3[part], part.nonzero())
    params, report, d_new = new_gaussians_from_depth(cam, unedited, edited, part, d3, alpha, disp_u, disp_e, cfg,
                                                     sh_degree=0, region_means=part_means)
    reach = over_wall & dilate(part, cfg.dilate_px)  # the object's pixels the (dilated) region reaches
    assert report["added"] == int(over_part.sum() + reach.sum()) and int(reach.sum()) == 12
    assert report["moved_onto_part"] == 12 and report["skipped_far_from_region"] == 0
    assert torch.allclose(d_new[over_part], torch.full((int(over_part.sum()),), 1.8), rtol=1e-4)
    transferred = 0.3 / 1.8 + 0.7 / 5.6  # what the lost disparity alone would give: about 3.3 deep
    assert 1 / transferred > 3.0
    assert float(d_new[reach].min()) >= 1.8 - 1e-4 and float(d_new[reach].max()) <= 2.0 + 1e-4
    z = params["means"] @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    assert float(z[:, 2].max()) <= 2.0 + 1e-4
    # Depth alone is not an object: where the edited view shows nothing new beside the part (a
    # silhouette's depth noise), those pixels are still dropped.
    plain = edited.clone()
    plain[over_wall] = unedited[over_wall]
    _, report, _ = new_gaussians_from_depth(cam, unedited, plain, part, d3, alpha, disp_u, disp_e, cfg,
                                            sh_degree=0, region_means=part_means)
    assert report["moved_onto_part"] == 0 and report["added"] == int(over_part.sum())


def _ball_on_part(part_box, ball_box, other_depths=(), region_px=0):
    """A part at depth 2 in front of a wall at 5-6 (32 x 32 px, looked at from 4 away), and an edit
    that puts a green ball at depth 1.9 over the box `ball_box` (rows, cols); `other_depths` sets
    the edited view's depth at some pixels ([((rows, cols), depth)]). Returns the camera, the
    part's 2D mask, the ball's, and `new_gaussians_from_depth`'s answer with the part's Gaussians
    as the region (its 2D mask the part's grown by `region_px`)."""
    h = w = 32
    cam = look_at((0.0, 0.0, -4.0), size=w)
    part = torch.zeros(h, w, dtype=torch.bool)
    part[part_box] = True
    d3 = torch.where(part, torch.tensor(2.0), 5.0 + torch.linspace(0, 1, w)[None].expand(h, w))
    ball = torch.zeros(h, w, dtype=torch.bool)
    ball[ball_box] = True
    true_depth = torch.where(ball, torch.tensor(1.9), d3)
    for where, depth in other_depths:
        true_depth[where] = depth
    unedited = torch.full((h, w, 3), 0.5)
    edited = unedited.clone()
    edited[ball] = torch.tensor([0.2, 0.8, 0.1])
    cfg = InitConfig(dilate_px=3, median=1, scale_factor=1.0)
    out = new_gaussians_from_depth(cam, unedited, edited, dilate(part, region_px), d3, torch.ones(h, w), 2.0 / d3 + 0.3,
                                   2.0 / true_depth + 0.3, cfg, sh_degree=0,
                                   region_means=unproject(cam, d3[part], part.nonzero()))
    return cam, part, ball, out


def test_an_objects_rim_blurred_with_what_lies_behind_it_is_not_placed_behind_it():
    """A ball (depth 1.9, 5 x 5 px) on a part (depth 2) at the part's silhouette: its last column
    lies over the wall behind (depth 5), still inside the 2D region (the selection's render reaches
    a pixel or two past the part). The estimator blurs the ball's disparity there with the wall's:
    the transferred depth is 2.6, behind the ball by more than the ball's size, yet near the part,
    so nothing else drops it. Gaussians placed there would float behind the ball, in the open in
    every other view; the ball's other 20 pixels are placed at its depth."""
    rim = (slice(12, 17), 16)
    cam, part, ball, (params, report, _) = _ball_on_part((slice(4, 28), slice(2, 16)), (slice(12, 17), slice(12, 17)),
                                                         other_depths=[(rim, 2.6)], region_px=2)
    z = (params["means"] @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3])[:, 2]
    assert float(z.max()) < 1.95, z  # on the ball (1.9), none at the blurred 2.6
    assert report["added"] == int((ball & part).sum()) == 20
    assert report["skipped_blurred_rim"] == int((ball & ~part).sum()) == 5


def test_an_object_larger_than_its_part_is_placed_whole():
    """A ball put on a nose is larger than the nose: measured by the part's size alone, the
    distance that drops depth outliers (max_distance x the part's diagonal) dropped every pixel of
    the ball. It scales with the object's own size (its pixels' box at their depth) when that is
    larger, so the ball is placed whole, while a pixel whose depth lands far behind is still dropped."""
    # the nose 2 x 2 px, the ball 6 x 6 px; its corner's depth lost to the wall behind: 4.5 deep
    cam, _, ball, (params, report, _) = _ball_on_part(
        (slice(15, 17), slice(15, 17)), (slice(12, 18), slice(13, 19)), [((12, 13), 4.5)])
    assert report["added"] == int(ball.sum()) - 1 and report["skipped_far_from_region"] == 1
    z = params["means"] @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    assert torch.allclose(z[:, 2], torch.full_like(z[:, 2], 1.9), rtol=1e-3)


def test_an_object_standing_clear_of_its_parts_silhouette_is_placed_whole_less_its_blurred_rim():
    """A big ball on a head stands out of the head's silhouette, over the wall far behind: only the
    pixels within `dilate_px` of the region were candidates (290016 c23's ball: 43 of its 78
    changed pixels, under the depth noise's count over its large region, so nothing was placed). A
    blob of change of shape that reaches into the region is taken whole, but for the blur on its
    rim beyond the region: there the estimator mixes the ball with the wall (here a ring at depth
    3 on two sides, between them), and Gaussians placed on it floated off the ball (145951 c23); the
    rim at the ball's own depth (its right side) is the ball. A blob that does not reach the region
    (elsewhere in the view) is not taken."""
    # the head 8 x 24 px; the ball on it, its rows 10-16 beyond the 3 px the region is grown by;
    # the blurred ring above and left of it, down to the head; a change of shape away from the region
    ring = [((9, slice(11, 21)), 3.0), ((slice(9, 20), 11), 3.0)]
    cam, part, ball, (params, report, _) = _ball_on_part(
        (slice(20, 28), slice(4, 28)), (slice(10, 20), slice(12, 21)), ring + [((slice(1, 4), slice(1, 5)), 3.0)])
    assert report["grown_out_of_region"] == int((ball & ~dilate(part, 3)).sum()) == 7 * 9
    uvz = params["means"] @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    placed = torch.zeros_like(ball)
    placed[(uvz[:, 1] / uvz[:, 2] * cam.fy + cam.cy - 0.5).round().long(),
           (uvz[:, 0] / uvz[:, 2] * cam.fx + cam.cx - 0.5).round().long()] = True
    # the whole ball and nothing of its ring (the ring's pixels in the region land far behind the
    # ball and are dropped as such)
    assert torch.equal(placed, ball) and report["added"] == int(ball.sum())
    assert torch.allclose(uvz[:, 2], torch.full_like(uvz[:, 2], 1.9), rtol=1e-3)


class _Cover(PixelWeights):
    """A view whose render of any non-empty selection is the coverage map `cover` (H, W)."""

    def __init__(self, cover):
        self.cover = cover

    def splat(self, feats):
        return self.cover[..., None] * float(feats.max())


def test_view_agreement_of_a_region_under_a_pixel():
    """A selection that covers no pixel by half (a region a pixel or two across at the view's
    resolution) is compared by the pixels it covers most: a 2D mask around it agrees, one
    elsewhere does not. Counted by the pixels above half, its IoU would be 0 whatever the mask,
    and a run on a patch of a few dozen Gaussians would stop with "views disagree"."""
    cover = torch.zeros(8, 8)
    cover[3:5, 3:5] = 0.3  # no pixel above half
    around, elsewhere = torch.zeros(8, 8), torch.zeros(8, 8)
    around[2:5, 2:5] = 1
    elsewhere[6:8, 0:3] = 1
    selected = torch.ones(3, dtype=torch.bool)
    iou = mask_agreement([_Cover(cover), _Cover(cover)], [around, elsewhere], selected, faint=True)
    assert iou.tolist() == pytest.approx([4 / 9, 0.0])
    assert mask_agreement([_Cover(cover)], [around], selected).tolist() == [0.0]  # the lift's view weights: no say
    # A selection that covers some pixel by more than half: the pixels above half, as before.
    cover[4, 4] = 0.9
    assert mask_agreement([_Cover(cover)], [around], selected, faint=True).tolist() == pytest.approx([1 / 9])
    assert mask_agreement([_Cover(torch.zeros(8, 8))], [around], selected, faint=True).tolist() == [0.0]  # not in view


def test_view_agreement_tolerates_a_mask_a_pixel_off_a_part_a_few_pixels_across():
    """The views-disagree stop (localization.agreement_tolerance_px = 1): relevance maps reach a
    pixel or two past the region, so on a part 2 px across the editor's mask a pixel off has a
    plain IoU under the stop's 0.3 (a face patch of a few dozen Gaussians would stop although its
    selection is right). Counted within 1 px, it agrees fully; a
    mask elsewhere still does not, and a blob round the part counts by its share near the part."""
    cover = torch.zeros(8, 8)
    cover[3:5, 3:5] = 0.9
    off, elsewhere, blob = torch.zeros(8, 8), torch.zeros(8, 8), torch.zeros(8, 8)
    off[4:6, 4:6] = 1
    elsewhere[6:8, 0:2] = 1
    blob[2:8, 2:8] = 1
    selected = torch.ones(3, dtype=torch.bool)
    views = [_Cover(cover)] * 3
    plain = mask_agreement(views, [off, elsewhere, blob], selected, faint=True)
    assert plain.tolist() == pytest.approx([1 / 7, 0.0, 4 / 36])
    tolerant = mask_agreement(views, [off, elsewhere, blob], selected, faint=True, tolerance_px=1)
    # blob: 16 of its 36 pixels lie within 1 px of the part, all 4 of the part's within 1 px of it
    assert tolerant.tolist() == pytest.approx([1.0, 0.0, 1 / (36 / 16 + 1 - 1)])
    assert mask_agreement([_Cover(torch.zeros(8, 8))], [off], selected, faint=True, tolerance_px=1).tolist() == [0.0]
