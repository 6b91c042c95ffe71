"""§3.1: lift per-view 2D masks to a per-Gaussian mask and render it back."""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F

from gs_regional.data.cameras import Camera
from gs_regional.geometry import neighbors
from gs_regional.renderers.base import PixelWeights
from gs_regional.utils.image import gaussian_blur


@torch.no_grad()
def snap_masks_to_edges(masks: torch.Tensor, images: torch.Tensor, ratio: float = 0.5, sigma: float = 1.0) -> torch.Tensor:
    """Drop from each 2D mask (B, H, W) the pixels of its one-pixel edge that look like the outside.

    Why: relevance maps are blobby (they come from 64x64 latents and are blurred), so a mask's edge
    lies about a pixel outside the object's. A pixel there is mostly the neighbouring surface, and a
    surface seen at a grazing angle next to the region (a neck under a head) projects into that
    one-pixel seam in every view: the lift would select all of it. An edge pixel is dropped when
    its colour in `images` (B, H, W, 3) is closer, by at least 1 / `ratio`, to the local mean colour
    of the outside than to that of the mask's interior (Gaussian-weighted means, `sigma` px); a
    blended or ambiguous rim pixel (dark shading against a dark background) stays. Image-sized
    work only: the cost does not depend on the number of Gaussians. `ratio` <= 0 changes nothing."""
    if ratio <= 0:
        return masks
    inside = masks > 0.5
    interior = F.max_pool2d((~inside).float()[:, None], 3, 1, 1)[:, 0] < 0.5  # not next to the outside
    edge = inside & ~interior
    img = images.to(masks.device).float().permute(0, 3, 1, 2)  # (B, 3, H, W)

    def distance_to_local_mean(where: torch.Tensor) -> tuple:
        w = where.float()
        den = gaussian_blur(w, sigma)
        mean = torch.stack([gaussian_blur(img[:, c] * w, sigma) for c in range(3)], 1) / den[:, None].clamp_min(1e-6)
        return (img - mean).norm(dim=1), den > 1e-3  # no such pixels nearby: no verdict

    d_in, has_in = distance_to_local_mean(interior)
    d_out, has_out = distance_to_local_mean(~inside)
    outside_like = edge & has_in & has_out & (d_out < ratio * d_in)
    return (inside & ~outside_like).to(masks.dtype)


def view_weights(model, renderer, cameras: Sequence[Camera]) -> list:
    """The compositing weights of every view (`Renderer.pixel_weights`): found once, then every
    lift and render-back of a localization reuses them (the geometry does not change meanwhile)."""
    return [renderer.pixel_weights(model, cam) for cam in cameras]


def mask_votes(views: Sequence[PixelWeights], masks: Sequence[torch.Tensor]) -> tuple:
    """Per-view votes (V, N) of every Gaussian: numerator Σ_x w_i(v,x)·M_v(x) and denominator
    Σ_x w_i(v,x), where w_i is the Gaussian's alpha-compositing weight."""
    num = torch.stack([v.gather(m.float()) for v, m in zip(views, masks)])
    den = torch.stack([v.gather(torch.ones(m.shape, device=m.device)) for v, m in zip(views, masks)])
    return num, den


def weighted_scores(num: torch.Tensor, den: torch.Tensor, view_weights: torch.Tensor) -> torch.Tensor:
    """s_i = Σ_v a_v·num_vi / Σ_v a_v·den_vi (0 for Gaussians no view sees)."""
    n = (view_weights[:, None] * num).sum(0)
    d = (view_weights[:, None] * den).sum(0)
    return torch.where(d > 1e-8, n / d.clamp_min(1e-8), torch.zeros_like(n))


def lift_masks(model, renderer, cameras: Sequence[Camera], masks: Sequence[torch.Tensor]) -> torch.Tensor:
    """The plain rendering-weight vote of §3.1 step 4: s_i = Σ_v Σ_x w_i M_v / Σ_v Σ_x w_i."""
    num, den = mask_votes(view_weights(model, renderer, cameras), masks)
    return weighted_scores(num, den, torch.ones(len(cameras), device=num.device))


def mask_agreement(views: Sequence[PixelWeights], masks: Sequence[torch.Tensor], selected: torch.Tensor) -> torch.Tensor:
    """IoU, per view, of the 2D mask with the render of the 3D selection (V,)."""
    out = []
    for view, m in zip(views, masks):
        r = splat_selection(view, selected) > 0.5
        m = m.to(r.device) > 0.5
        out.append(float((r & m).sum()) / max(float((r | m).sum()), 1.0))
    return torch.tensor(out, device=selected.device)


def neighbourhoods(means: torch.Tensor, k: int) -> torch.Tensor:
    """(N, min(k, N)) row indices: each Gaussian itself, then its k - 1 nearest other Gaussians
    (exact; a voxel-grid search, no N x N distances)."""
    others = neighbors.knn(means, k - 1)[1] if k > 1 else means.new_zeros((means.shape[0], 0), dtype=torch.long)
    return torch.cat([torch.arange(means.shape[0], device=means.device)[:, None], others], 1)


def knn_pool(num: torch.Tensor, den: torch.Tensor, neighbourhood: torch.Tensor) -> tuple:
    """Sum votes over each Gaussian's neighbourhood (rows of `neighbourhoods`), so a Gaussian that
    few views see well takes the verdict of its well-seen neighbours."""
    return num[neighbourhood].sum(1), den[neighbourhood].sum(1)


def localize_gaussians(
    model, renderer, cameras: Sequence[Camera], masks: Sequence[torch.Tensor], threshold: float = 0.5,
    reweight_iters: int = 2, agreement_power: float = 2.0, knn: int = 16,
) -> dict:
    """§3.1 step 4 with two robustness steps of our own (both can be switched off):

    * view reweighting: a 2D editor fails in some views (side views, leakage). After a first lift,
      each view's vote is weighted by (IoU of its 2D mask with the render of the 3D mask) **
      `agreement_power`, and
      the lift is repeated `reweight_iters` times; views that disagree with the consensus fade.
    * neighbour pooling (point expansion): votes are summed over the `knn` nearest Gaussians, so
      rarely seen Gaussians follow their neighbourhood.
    Returns {"selected": (N,) bool, "scores": (N,), "view_weights": (V,), "views": the
    `PixelWeights` of the cameras, to render selections back without new renders}.
    """
    views = view_weights(model, renderer, cameras)
    num, den = mask_votes(views, masks)
    # the neighbours do not change between reweighting passes: found once
    neighbourhood = neighbourhoods(model.means.detach(), knn) if knn > 1 else None
    weights = torch.ones(len(cameras), device=num.device)
    for it in range(reweight_iters + 1):
        s_num = (weights[:, None] * num).sum(0)
        s_den = (weights[:, None] * den).sum(0)
        if neighbourhood is not None:
            s_num, s_den = knn_pool(s_num, s_den, neighbourhood)
        scores = torch.where(s_den > 1e-8, s_num / s_den.clamp_min(1e-8), torch.zeros_like(s_num))
        selected = scores > threshold
        if it < reweight_iters and bool(selected.any()):
            weights = mask_agreement(views, masks, selected) ** agreement_power
            if float(weights.sum()) <= 0:
                break
    return {"selected": selected, "scores": scores, "view_weights": weights, "views": views}


def expand_selection(means: torch.Tensor, selected: torch.Tensor, radius: float) -> torch.Tensor:
    """Point expansion: also select every Gaussian within `radius` of a selected one."""
    if radius <= 0 or not bool(selected.any()) or bool(selected.all()):
        return selected
    out = selected.clone()
    out[~selected] = neighbors.within_radius(means[~selected], means[selected], radius)
    return out


@torch.no_grad()
def render_selection(model, renderer, camera: Camera, selected: torch.Tensor) -> torch.Tensor:
    """Render a per-Gaussian selection back into a view: (H, W) in [0, 1], the fraction of the
    pixel's colour that comes from selected Gaussians."""
    feat = selected.float()[:, None].to(model.means.device)
    return renderer.render(model, camera, override_color=feat)["rgb"][..., 0].clamp(0, 1)


@torch.no_grad()
def splat_selection(view: PixelWeights, selected: torch.Tensor) -> torch.Tensor:
    """`render_selection` from a view's kept weights (no new render)."""
    return view.splat(selected.float()[:, None])[..., 0].clamp(0, 1)
