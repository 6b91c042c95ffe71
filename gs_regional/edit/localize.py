"""§3.1: lift per-view 2D masks to a per-Gaussian mask and render it back."""
from __future__ import annotations

from typing import Sequence

import torch

from gs_regional.data.cameras import Camera


def lift_masks(model, renderer, cameras: Sequence[Camera], masks: Sequence[torch.Tensor]) -> torch.Tensor:
    """Per-Gaussian score s_i = Σ_v Σ_x w_i(v,x)·M_v(x) / Σ_v Σ_x w_i(v,x), by autograd.

    Rendering a per-Gaussian feature f gives Σ_i w_i f_i at each pixel, so the gradient of
    Σ_x M(x)·render(f)(x) with respect to f_i is Σ_x w_i(x)·M(x). Two channels give the numerator
    (weighted by the mask) and the denominator (weighted by 1) in one backward pass.
    Gaussians that contribute to no pixel score 0.
    """
    n = model.num_gaussians
    device = model.means.device
    num = torch.zeros(n, device=device)
    den = torch.zeros(n, device=device)
    for cam, m in zip(cameras, masks):
        feat = torch.ones(n, 2, device=device, requires_grad=True)
        with torch.enable_grad():
            out = renderer.render(model, cam, override_color=feat)["rgb"]
            m = m.to(device).float()
            loss = (out[..., 0] * m).sum() + out[..., 1].sum()
            (grad,) = torch.autograd.grad(loss, feat)
        num += grad[:, 0]
        den += grad[:, 1]
    return torch.where(den > 1e-8, num / den.clamp_min(1e-8), torch.zeros_like(num))


def expand_selection(means: torch.Tensor, selected: torch.Tensor, radius: float, chunk: int = 4096) -> torch.Tensor:
    """Point expansion: also select every Gaussian within `radius` of a selected one."""
    if radius <= 0 or not bool(selected.any()) or bool(selected.all()):
        return selected
    seeds = means[selected]
    out = selected.clone()
    for s in range(0, means.shape[0], chunk):
        part = means[s : s + chunk]
        near = torch.zeros(part.shape[0], dtype=torch.bool, device=means.device)
        for t in range(0, seeds.shape[0], chunk):
            near |= (torch.cdist(part, seeds[t : t + chunk]) <= radius).any(dim=1)
        out[s : s + chunk] |= near
    return out


@torch.no_grad()
def render_selection(model, renderer, camera: Camera, selected: torch.Tensor) -> torch.Tensor:
    """Render a per-Gaussian selection back into a view: (H, W) in [0, 1], the fraction of the
    pixel's colour that comes from selected Gaussians."""
    feat = selected.float()[:, None].to(model.means.device)
    return renderer.render(model, camera, override_color=feat)["rgb"][..., 0].clamp(0, 1)


def mask_metrics(pred: torch.Tensor, truth: torch.Tensor) -> dict:
    """IoU, precision, recall of two boolean per-Gaussian masks."""
    pred, truth = pred.bool(), truth.bool()
    inter = float((pred & truth).sum())
    union = float((pred | truth).sum())
    return {
        "mask_iou": inter / union if union else 1.0,
        "mask_precision": inter / float(pred.sum()) if pred.any() else 0.0,
        "mask_recall": inter / float(truth.sum()) if truth.any() else 1.0,
    }
