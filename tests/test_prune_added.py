"""After refinement, the Gaussians an edit added that contribute nothing are pruned,
on the synthetic scene's true `add` edit: the moustache's Gaussians (generation 1) plus planted
useless ones (hidden inside the head, or transparent) that a known answer says must go."""
import torch

from gs_regional.stages.prune import useless_added
from gs_regional.geometry import rows
from gs_regional.metrics.image import psnr
from gs_regional.registry import find
from gs_regional.sim.scene import make_cameras, make_edit


def test_added_gaussians_that_contribute_nothing_are_pruned_and_renders_keep():
    gt = make_edit("add")
    model = gt.edited
    head = model.means.detach()[: len(gt.source)][gt.region]
    centre = head.mean(0)
    gen = torch.Generator().manual_seed(0)
    k = 50
    hidden = centre + 0.02 * torch.randn(k, 3, generator=gen)  # deep inside the opaque head
    params = {
        "means": torch.cat([hidden, hidden]),
        "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(2 * k, 1),
        "log_scales": torch.full((2 * k, 3), -5.0),
        "opacity_logits": torch.cat([torch.full((k,), 2.0), torch.full((k,), -9.0)]),  # opaque / transparent
        "sh_dc": torch.zeros(2 * k, 3),
        "sh_rest": torch.zeros(2 * k, 0, 3),
    }
    params["means"][k:] = model.means.detach()[len(gt.source):][:k]  # transparent ones on the moustache
    n = model.num_gaussians
    rows.append(model, params, generation=1)
    cams, _ = make_cameras(12, 48, 48)
    renderer = find("torch-rasterizer")()
    flagged = useless_added(model, renderer, cams, min_weight=0.1, min_opacity=0.005)
    assert bool(flagged[n:].all())  # every planted one
    assert not bool(flagged[: len(gt.source)].any())  # the source scene is never touched
    # (Many of the moustache's own Gaussians go too: the back of each bead faces the face and is
    # never seen. The renders below show they contributed nothing.)
    with torch.no_grad():
        before = torch.stack([renderer.render(model, c)["rgb"] for c in cams])
        rows.keep(model, ~flagged)
        after = torch.stack([renderer.render(model, c)["rgb"] for c in cams])
    # What contributes < 0.1 of a pixel over all 12 views, together: about 58 dB here (a
    # threshold of 1 pixel would cost 36 dB at this small size; 0.01 keeps 85 dB).
    assert psnr(after, before) > 50


def test_an_edits_densification_prunes_only_what_the_edit_added():
    """A trained splat holds many near-transparent Gaussians (the donut: 1,791 below opacity
    0.005). The opacity prune of 3DGS's training would delete those of the edited region; an edit
    (`prune_only_added`, the regional edit's setting) keeps every source Gaussian, and
    metrics.json's `source_deleted` counts the source rows no output row descends from."""
    from gs_regional.geometry.strategy import DensifyStrategy

    def scene():
        model = make_edit("add").source
        with torch.no_grad():
            model.opacity_logits[:100] = -9.0  # near-transparent source Gaussians
        model.mark_as_source()
        rows.append(model, {"means": model.means.detach()[:20].clone(), "quats": model.quats.detach()[:20].clone(),
                            "log_scales": model.log_scales.detach()[:20].clone(),
                            "opacity_logits": torch.full((20,), -9.0), "sh_dc": model.sh_dc.detach()[:20].clone(),
                            "sh_rest": model.sh_rest.detach()[:20].clone()}, generation=1)
        model.grad_accum.zero_()
        model.grad_count.fill_(1)
        return model

    def deleted(model, n_source):
        return n_source - model.source_index[model.source_index >= 0].unique().numel()

    for only_added, expect_pruned in ((False, 120), (True, 20)):
        model = scene()
        n_source = int((model.generation == 0).sum())
        rep = DensifyStrategy(only_trainable=False, prune_only_added=only_added).densify_and_prune(model, 1.0)
        assert rep["pruned"] == expect_pruned
        assert deleted(model, n_source) == (100 if not only_added else 0)
        assert not bool(((model.generation > 0) & (model.opacities < 0.005)).any())  # added ones still go


def test_a_source_gaussian_whose_every_descendant_would_be_pruned_keeps_its_most_opaque_one():
    model = make_edit("add").source
    model.mark_as_source()
    rows.duplicate(model, torch.tensor([0, 0, 5]))  # rows 0 and 5 densified: children share their source index
    model.generation[len(model.generation) - 3:] = 1
    with torch.no_grad():
        model.opacity_logits[-3:] = torch.tensor([-9.0, -8.0, -9.0])
    n = model.num_gaussians
    prune = torch.zeros(n, dtype=torch.bool)
    prune[-3:] = True  # every child pruned
    removed = torch.zeros(n, dtype=torch.bool)
    removed[0] = True  # row 0 was split: its children replace it
    kept = ~rows.spare_last_descendants(model, prune, removed=removed) & prune
    # row 0's descendants would all be gone: its more opaque child stays; row 5 itself remains
    assert kept.nonzero().flatten().tolist() == [n - 2]
