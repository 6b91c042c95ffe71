"""Metrics that see the edited region, as pure functions of images and masks.

Images are (..., H, W, 3) in [0, 1]; pixel masks are (..., H, W) bool over the same views. Scores
pool every masked pixel of every view (one PSNR over all of them, not a mean of per-view PSNRs).
A score over an empty set of pixels is None, never NaN or an infinite PSNR.

  footprint     pixels the true edit is about: the rendered weight of the true region (and of
                the Gaussians the edit adds) above a threshold.
  inside/outside the footprint: the result against the true edit, and the same for doing nothing
                (the source renders against the true edit), so every number has its baseline;
                outside split into the pixels within NEAR_FOOTPRINT_PX of the footprint (an edge
                a pixel off) and those beyond (the edit leaking into the scene).
  silhouette/background: the unedited pixels split by where the source renders opaque, so that a
                black background cannot hide a halo of changes around the object.
"""
from __future__ import annotations

from typing import Dict, Optional

import torch

from gs_regional.metrics.image import psnr, ssim
from gs_regional.utils.image import dilate


SEEN_MIN_WEIGHT = 0.01  # pixels of rendering weight over a set of views: a Gaussian they see
# region_scores splits the error outside the footprint at this distance from it (pixels): nearer,
# an edge a pixel off (the footprint is where the true edit's weight passes 0.1, and objects and
# parts are anti-aliased over a pixel or two); further, the edit leaking into the scene.
NEAR_FOOTPRINT_PX = 2


@torch.no_grad()
def render_selection(model, renderer, camera, selected: torch.Tensor) -> torch.Tensor:
    """Render a per-Gaussian selection into a view: (H, W) in [0, 1], the fraction of the pixel's
    colour that comes from selected Gaussians."""
    feat = selected.float()[:, None].to(model.means.device)
    return renderer.render(model, camera, override_color=feat)["rgb"][..., 0].clamp(0, 1)


@torch.no_grad()
def splat_selection(view, selected: torch.Tensor) -> torch.Tensor:
    """`render_selection` from a view's kept pixel weights (a `PixelWeights`; no new render)."""
    return view.splat(selected.float()[:, None])[..., 0].clamp(0, 1)


def footprint(weights: torch.Tensor, threshold: float = 0.1) -> torch.Tensor:
    """(..., H, W) bool: pixels whose rendered weight of the true edited region exceeds `threshold`."""
    return weights > threshold


def _checked(images: Dict[str, torch.Tensor], mask: torch.Tensor) -> None:
    shapes = {k: tuple(v.shape) for k, v in images.items()}
    first = next(iter(shapes.values()))
    if any(s != first for s in shapes.values()) or first[-1] != 3:
        raise ValueError(f"images must share one (..., H, W, 3) shape, got {shapes}")
    if tuple(mask.shape) != first[:-1] or mask.dtype != torch.bool:
        raise ValueError(f"mask must be a bool tensor of shape {first[:-1]}, got {mask.dtype} {tuple(mask.shape)}")


def masked_psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> Optional[float]:
    """PSNR (dB) of a against b over the pixels of `mask`; None if the mask is empty."""
    _checked({"a": a, "b": b}, mask)
    return psnr(a, b, mask) if bool(mask.any()) else None


def masked_ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> Optional[float]:
    """Mean of the SSIM map (11x11 Gaussian window over the whole image) over the pixels of
    `mask`; None if the mask is empty."""
    _checked({"a": a, "b": b}, mask)
    return ssim(a, b, mask) if bool(mask.any()) else None


def region_scores(result: torch.Tensor, source: torch.Tensor, truth: torch.Tensor, inside: torch.Tensor) -> Dict[str, Optional[float]]:
    """PSNR and SSIM of the result and of doing nothing (`source`) against the true edit, inside
    the footprint `inside` and outside it; and where the error outside lies: the PSNR of the
    pixels more than NEAR_FOOTPRINT_PX from the footprint (`psnr_far_outside_vs_true_edit`: the
    edit leaking into the rest of the scene) and the share of the outside's squared error within
    that distance (`outside_error_near_footprint`: the edge of the edited part or object a pixel
    off, its colour spilled onto the next pixel)."""
    _checked({"result": result, "source": source, "truth": truth}, inside)
    out: Dict[str, Optional[float]] = {}
    near = dilate(inside, NEAR_FOOTPRINT_PX)
    for where, mask in (("region", inside), ("outside", ~inside)):
        for name, images in (("", result), ("_source", source)):
            out[f"psnr_{where}{name}_vs_true_edit"] = masked_psnr(images, truth, mask)
            out[f"ssim_{where}{name}_vs_true_edit"] = masked_ssim(images, truth, mask)
    out["psnr_far_outside_vs_true_edit"] = masked_psnr(result, truth, ~near)
    err = ((result - truth).double() ** 2).mean(-1)  # float64 sums: a share of 1 stays 1
    total = float(err[~inside].sum())
    out["outside_error_near_footprint"] = float(err[near & ~inside].sum()) / total if total > 0 else None
    return out


def error_map(result: torch.Tensor, truth: torch.Tensor, inside: torch.Tensor, gain: float = 8.0) -> torch.Tensor:
    """(H, W, 3) image of where and how much `result` differs from `truth` (largest channel, x
    `gain`): red outside the footprint `inside` (what the edit should have left alone), grey in
    it. A halo, or an added object a pixel off, shows as a red ring."""
    _checked({"result": result, "truth": truth}, inside)
    err = ((result - truth).abs().amax(-1) * gain).clamp(0, 1)
    keep = inside.to(err.dtype)  # 1 in the footprint: grey; 0 outside: red only
    return torch.stack([err, err * keep, err * keep], -1)


def silhouette_split(unedited: torch.Tensor, source_alpha: torch.Tensor, opaque: float = 0.5) -> Dict[str, torch.Tensor]:
    """The unedited pixels where the source renders opaque (alpha > `opaque`: the object's
    silhouette, minus the edit) and the rest of them (the background)."""
    if tuple(source_alpha.shape) != tuple(unedited.shape):
        raise ValueError(f"source_alpha {tuple(source_alpha.shape)} and unedited {tuple(unedited.shape)} differ in shape")
    solid = source_alpha > opaque
    return {"silhouette": unedited & solid, "background": unedited & ~solid}


def unedited_scores(result: torch.Tensor, source: torch.Tensor, unedited: torch.Tensor, source_alpha: torch.Tensor,
                    opaque: float = 0.5) -> Dict[str, Optional[float]]:
    """PSNR and SSIM of the result against the source renders on the unedited pixels, on the
    object's silhouette and on the background separately."""
    _checked({"result": result, "source": source}, unedited)
    out: Dict[str, Optional[float]] = {}
    for where, mask in silhouette_split(unedited, source_alpha, opaque).items():
        out[f"psnr_unedited_{where}"] = masked_psnr(result, source, mask)
        out[f"ssim_unedited_{where}"] = masked_ssim(result, source, mask)
    return out


def mask_metrics(pred: torch.Tensor, truth: torch.Tensor) -> Dict[str, Optional[float]]:
    """IoU, precision and recall of a boolean per-Gaussian mask against the true one; a ratio
    whose denominator is empty (nothing predicted, nothing true, neither) is None."""
    pred, truth = pred.bool(), truth.bool()
    if pred.shape != truth.shape:
        raise ValueError(f"mask_metrics: masks differ in shape, {tuple(pred.shape)} vs {tuple(truth.shape)}")
    inter = float((pred & truth).sum())
    union = float((pred | truth).sum())
    return {
        "mask_iou": inter / union if union else None,
        "mask_precision": inter / float(pred.sum()) if pred.any() else None,
        "mask_recall": inter / float(truth.sum()) if truth.any() else None,
    }
