"""After refinement, the Gaussians an edit added that contribute nothing are pruned (issue 11 §4),
on the synthetic scene's true `add` edit: the moustache's Gaussians (generation 1) plus planted
useless ones (hidden inside the head, or transparent) that a known answer says must go."""
import torch

from gs_regional.edit.prune import useless_added
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
