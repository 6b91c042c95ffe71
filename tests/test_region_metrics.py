"""Region-aware metrics (gs_regional.metrics.region, gs_regional.metrics.truth) on known answers."""
import copy
import math

import pytest
import torch

from gs_regional.metrics.region import (
    error_map, footprint, mask_metrics, masked_psnr, masked_ssim, region_scores, silhouette_split, unedited_scores,
)
from gs_regional.metrics.truth import TruthScoring
from gs_regional.registry import find
from gs_regional.sim.scene import make_cameras, make_edit



def _db(mse: float) -> float:
    return 10 * math.log10(1 / mse)


@pytest.fixture
def views():
    """Two 16x16 views: the edit's footprint is a 4x4 square in view 0 and absent from view 1;
    the true edit turns it white. The result gets it off by 0.1 and the rest off by 0.01."""
    source = torch.full((2, 16, 16, 3), 0.25)
    inside = torch.zeros(2, 16, 16, dtype=torch.bool)
    inside[0, 4:8, 4:8] = True
    truth = source.clone()
    truth[inside] = 1.0
    result = source + 0.01
    result[inside] = 0.9
    return source, truth, result, inside


def test_footprint_thresholds_the_rendered_weight():
    w = torch.tensor([[0.0, 0.05, 0.1, 0.11, 1.0]])
    assert footprint(w, 0.1).tolist() == [[False, False, False, True, True]]


def test_masked_scores_pool_pixels_and_say_none_when_empty(views):
    source, truth, result, inside = views
    # MSE 0.01 inside (0.9 vs 1.0), pooled over the 16 pixels of view 0 and none of view 1
    assert masked_psnr(result, truth, inside) == pytest.approx(_db(0.01), abs=1e-3)
    assert masked_psnr(result, truth, ~inside) == pytest.approx(_db(1e-4), abs=1e-2)
    empty = torch.zeros_like(inside)
    assert masked_psnr(result, truth, empty) is None and masked_ssim(result, truth, empty) is None
    assert masked_ssim(truth, truth, inside) == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(ValueError, match="mask"):
        masked_psnr(result, truth, inside.float())
    with pytest.raises(ValueError, match="shape"):
        masked_psnr(result, truth[:1], inside)


def test_region_scores_against_the_true_edit_and_doing_nothing(views):
    source, truth, result, inside = views
    s = region_scores(result, source, truth, inside)
    assert s["psnr_region_vs_true_edit"] == pytest.approx(_db(0.01), abs=1e-3)
    assert s["psnr_region_source_vs_true_edit"] == pytest.approx(_db(0.75**2), abs=1e-3)
    assert s["psnr_outside_vs_true_edit"] == pytest.approx(_db(1e-4), abs=1e-2)
    assert s["psnr_outside_source_vs_true_edit"] >= 100  # identical pixels: psnr's 1e-12 floor
    assert s["ssim_outside_source_vs_true_edit"] < 1.0  # the window reaches across the footprint's border
    assert 0 < s["ssim_region_source_vs_true_edit"] < s["ssim_region_vs_true_edit"] <= 1
    # an edit whose footprint is empty on every view: no in-region score, the rest still scored
    none = region_scores(source + 0.01, source, source, torch.zeros_like(inside))
    assert none["psnr_region_vs_true_edit"] is None and none["ssim_region_source_vs_true_edit"] is None
    assert none["psnr_outside_vs_true_edit"] == pytest.approx(_db(1e-4), abs=1e-2)



def test_region_scores_tell_an_edge_a_pixel_off_from_an_edit_leaking_into_the_scene(views):
    source, truth, _, inside = views
    # the white square drawn a pixel wider on its right: all the error outside lies next to the footprint
    wider = truth.clone()
    wider[0, 4:8, 8] = 1.0
    s = region_scores(wider, source, truth, inside)
    assert s["outside_error_near_footprint"] == pytest.approx(1.0)
    assert s["psnr_far_outside_vs_true_edit"] >= 100  # identical beyond NEAR_FOOTPRINT_PX
    # the same error 6 px away from it: the edit leaked into the scene
    leaked = truth.clone()
    leaked[0, 4:8, 14] = 1.0
    far = region_scores(leaked, source, truth, inside)
    assert far["outside_error_near_footprint"] == pytest.approx(0.0)
    assert far["psnr_outside_vs_true_edit"] == pytest.approx(s["psnr_outside_vs_true_edit"], abs=1e-3)
    assert far["psnr_far_outside_vs_true_edit"] < s["psnr_outside_vs_true_edit"]
    # nothing wrong outside: no share to give
    assert region_scores(truth, source, truth, inside)["outside_error_near_footprint"] is None

def test_unedited_scores_split_silhouette_from_background():
    """A halo: the result differs from the source on the object's edge, not on the black
    background; the whole-image PSNR hides it, the silhouette PSNR does not."""
    source = torch.zeros(1, 20, 20, 3)
    alpha = torch.zeros(1, 20, 20)
    alpha[0, 5:15, 5:15] = 1.0  # the object
    source[alpha > 0] = 0.5
    unedited = torch.ones(1, 20, 20, dtype=torch.bool)
    unedited[0, 8:12, 8:12] = False  # the edit's footprint
    result = source.clone()
    result[0, 5, 5:15] += 0.2  # a halo row along the object's top edge
    parts = silhouette_split(unedited, alpha)
    assert int(parts["silhouette"].sum()) == 100 - 16 and int(parts["background"].sum()) == 400 - 100
    assert not bool((parts["silhouette"] & parts["background"]).any())
    s = unedited_scores(result, source, unedited, alpha)
    assert s["psnr_unedited_silhouette"] == pytest.approx(_db(0.04 * 10 / 84), abs=1e-3)
    assert s["psnr_unedited_background"] >= 100
    assert s["psnr_unedited_silhouette"] < masked_psnr(result, source, unedited) - 5
    # nothing opaque: no silhouette score
    assert unedited_scores(result, source, unedited, torch.zeros_like(alpha))["psnr_unedited_silhouette"] is None


def test_error_map_shows_what_leaked_outside_the_footprint_in_red(views):
    """The image a user reads a halo from: the result's error against the truth, red outside the
    true footprint and grey inside it, scaled by `gain` and clipped at 1."""
    _, truth, result, inside = views
    img = error_map(result[0], truth[0], inside[0], gain=8.0)
    assert img.shape == (16, 16, 3)
    inner, outer = img[inside[0]], img[~inside[0]]
    assert torch.allclose(inner, torch.full_like(inner, 0.8), atol=1e-4)  # 0.1 x 8, grey
    assert torch.allclose(outer[:, 0], torch.full_like(outer[:, 0], 0.08), atol=1e-4)  # 0.01 x 8, red
    assert float(outer[:, 1:].abs().max()) == 0.0
    assert float(error_map(result[0], truth[0], inside[0], gain=100.0).max()) == 1.0  # clipped
    with pytest.raises(ValueError):
        error_map(result[0], truth[0], inside[0][:8])


def test_mask_metrics_known_and_empty():
    m = mask_metrics(torch.tensor([True, True, False, False]), torch.tensor([True, False, True, False]))
    assert m == {"mask_iou": pytest.approx(1 / 3), "mask_precision": 0.5, "mask_recall": 0.5}
    empty, some = torch.zeros(3, dtype=torch.bool), torch.tensor([True, False, False])
    assert mask_metrics(empty, some) == {"mask_iou": 0.0, "mask_precision": None, "mask_recall": 0.0}
    assert mask_metrics(some, empty) == {"mask_iou": 0.0, "mask_precision": 0.0, "mask_recall": None}
    assert mask_metrics(empty, empty) == {"mask_iou": None, "mask_precision": None, "mask_recall": None}
    with pytest.raises(ValueError, match="shape"):
        mask_metrics(some, torch.zeros(4, dtype=torch.bool))


def _scoring(edit: str):
    """(truth, its TruthScoring, views) of a small synthetic known edit seen by 6 cameras at 48²."""
    gt = make_edit(edit, n_object=1500, n_background=500)
    cams, _ = make_cameras(n=6, width=48, height=48)
    return gt, TruthScoring(gt, find("torch-rasterizer")(), cams, lambda: torch.device("cpu")), list(range(len(cams)))


def test_a_recolours_shortfall_is_laid_at_the_stage_that_lost_it():
    """`recolour_rows` on known answers: a result halfway to the true colours on every region
    Gaussian has removed 3/4 of doing nothing's error, all of what is left on the rows that
    trained; a result that is right except where the gate declined leaves all of its error there;
    one that localized nothing leaves it on the unselected rows; a result with rows added is not
    judged."""
    gt, scoring, views = _scoring("recolor")
    region = gt.region
    source, true = gt.source.sh_dc.detach(), gt.edited.sh_dc.detach()
    assert int(region.sum()) > 30 and bool(((true - source).abs().sum(-1) > 0)[region].all())

    def result(sh_dc):
        model = copy.deepcopy(gt.source)
        with torch.no_grad():
            model.sh_dc.copy_(sh_dc)
        return model

    everything, nothing = torch.ones_like(region), torch.zeros_like(region)
    # sh_to_rgb is affine in sh_dc: the DC halfway between is the colour halfway between
    half = scoring.recolour_rows(result((source + true) / 2), everything, everything, views)
    assert half["recolour_done"] == pytest.approx(0.75, abs=1e-6)
    assert half["recolour_left_taken"] == pytest.approx(1.0) and half["recolour_left_declined"] == 0.0

    declined = region & (torch.arange(len(region)) % 2 == 0)  # half the region's rows, declined
    gated = scoring.recolour_rows(result(torch.where(declined[:, None], source, true)), everything, ~declined, views)
    assert 0.0 < gated["recolour_done"] < 1.0
    assert gated["recolour_left_declined"] == pytest.approx(1.0)
    assert gated["recolour_left_unselected"] == 0.0 and gated["recolour_left_taken"] == 0.0

    missed = scoring.recolour_rows(result(source), nothing, nothing, views)
    assert missed["recolour_done"] == pytest.approx(0.0, abs=1e-6) and missed["recolour_left_unselected"] == pytest.approx(1.0)

    done = scoring.recolour_rows(result(true), region, region, views)
    assert done["recolour_done"] == pytest.approx(1.0) and done["recolour_left_taken"] is None

    pruned = copy.deepcopy(gt.source).select(torch.arange(1, len(region)))  # a result without the first row
    assert scoring.recolour_rows(pruned, everything[1:], everything[1:], views) == {}
    added, adding, _ = _scoring("add")  # a true edit that adds rows
    assert adding.recolour_rows(copy.deepcopy(added.source), everything, everything, views) == {}


def test_an_additions_cover_says_how_much_of_the_new_object_is_drawn_and_where_it_is_not():
    """`addition_cover` on known answers: the true edited scene itself covers its new object whole
    and nothing beside it; the source (nothing added) covers none of it; the object moved aside by
    its own width covers part of it and puts the rest where the truth has nothing; a recolour's
    truth (no new rows) is not judged."""
    gt, scoring, views = _scoring("add")
    n = len(gt.source)
    new = torch.arange(len(gt.edited)) >= n
    whole = scoring.addition_cover(gt.edited, new, views)
    assert whole["added_cover"] == pytest.approx(1.0, abs=1e-6) and whole["added_cover_outside"] == pytest.approx(0.0, abs=1e-6)
    none = scoring.addition_cover(gt.source, torch.zeros(n, dtype=torch.bool), views)
    assert none == {"added_cover": 0.0, "added_cover_outside": 0.0}
    moved = copy.deepcopy(gt.edited)
    obj = moved.means.detach()[new]
    with torch.no_grad():
        moved.means[new] += torch.tensor([1.0, 0.0, 0.0]) * float(obj[:, 0].max() - obj[:, 0].min())
    aside = scoring.addition_cover(moved, new, views)
    assert aside["added_cover"] < 0.6 and aside["added_cover_outside"] > 0.4
    recolour, recolouring, _ = _scoring("recolor")
    assert recolouring.addition_cover(recolour.edited, torch.zeros(len(recolour.edited), dtype=torch.bool), views) == {}
