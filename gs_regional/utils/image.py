"""Image helpers shared by every floor: checking and converting image batches, resizing, blurring
and dilating maps. Images are (B, H, W, 3) float tensors in [0, 1]; maps and masks are (B, H, W)."""
from __future__ import annotations

import math
from typing import Any, List, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F


def check_images(images: torch.Tensor, what: str = "images") -> torch.Tensor:
    """Validate a (B, H, W, 3) float batch in [0, 1]; a single (H, W, 3) image is batched."""
    if not isinstance(images, torch.Tensor):
        raise TypeError(f"{what} must be a torch.Tensor of shape (B, H, W, 3), got {type(images).__name__}")
    if images.dim() == 3:
        images = images[None]
    if images.dim() != 4 or images.shape[-1] != 3:
        raise ValueError(f"{what} must have shape (B, H, W, 3), got {tuple(images.shape)}")
    if not images.is_floating_point():
        raise TypeError(f"{what} must be float in [0, 1], got dtype {images.dtype}")
    lo, hi = (float(v) for v in torch.aminmax(images.detach()))
    if lo < -1e-3 or hi > 1 + 1e-3:
        raise ValueError(f"{what} must be in [0, 1], got values in [{lo:.3g}, {hi:.3g}]")
    return images.clamp(0, 1)


def check_cameras(cameras: Optional[Sequence[Any]], n_images: int, where: str, required: bool = False) -> Optional[List[Any]]:
    """One camera per image as a list, or None when none were given and none are `required`."""
    if cameras is None:
        if required:
            raise ValueError(f"{where} needs cameras=[one Camera per image]")
        return None
    cameras = list(cameras)
    if len(cameras) != n_images:
        raise ValueError(f"{where}: {n_images} images but {len(cameras)} cameras")
    return cameras


def to_nchw(images: torch.Tensor) -> torch.Tensor:
    """(B, H, W, C) -> (B, C, H, W) float32, the layout of torch's image ops and of vision models."""
    return images.permute(0, 3, 1, 2).float()


def resize(x: torch.Tensor, size: Tuple[int, int], mode: str = "bilinear") -> torch.Tensor:
    """Resize (B, C, H, W); antialiased when shrinking (as PIL does), a no-op at the same size."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    shrink = size[0] < x.shape[-2] or size[1] < x.shape[-1]
    if mode in ("bilinear", "bicubic"):
        return F.interpolate(x, size=size, mode=mode, align_corners=False, antialias=shrink)
    return F.interpolate(x, size=size, mode=mode)


def gaussian_blur(maps: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian filter of (B, H, W) maps, reflect-padded."""
    if sigma <= 0:
        return maps
    radius = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=maps.dtype, device=maps.device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    m = maps[:, None]
    h, w = m.shape[-2:]
    pad_w, pad_h = min(radius, w - 1), min(radius, h - 1)
    m = F.pad(m, (pad_w, pad_w, 0, 0), mode="reflect" if pad_w > 0 else "replicate")
    m = F.conv2d(m, k[radius - pad_w : radius + pad_w + 1].view(1, 1, 1, -1))
    m = F.pad(m, (0, 0, pad_h, pad_h), mode="reflect" if pad_h > 0 else "replicate")
    m = F.conv2d(m, k[radius - pad_h : radius + pad_h + 1].view(1, 1, -1, 1))
    return m[:, 0]


def dilate(mask: torch.Tensor, px: int) -> torch.Tensor:
    """Grow an (..., H, W) mask by `px` pixels (a square structuring element), each (H, W) on its
    own; returns bool."""
    if px <= 0:
        return mask.bool()
    m = mask.float().reshape(-1, 1, *mask.shape[-2:])
    return (F.max_pool2d(m, 2 * px + 1, stride=1, padding=px) > 0.5).reshape(mask.shape)


def components(mask: torch.Tensor) -> torch.Tensor:
    """(H, W) int64 labels of the 8-connected components of `mask` (-1 outside it): each pixel
    ends with the largest pixel index of its component. Each pass takes the largest label among
    the 8 neighbours, then jumps to the label of the pixel its label names (that pixel lies in
    the same component and its label is at least as large), so a long thin blob takes about
    log2 of its length in passes instead of its length."""
    h, w = mask.shape
    inside = mask.reshape(-1)
    labels = torch.where(inside, torch.arange(h * w, device=mask.device), torch.full_like(inside, -1, dtype=torch.long))
    while True:
        pooled = torch.nn.functional.max_pool2d(labels.reshape(1, 1, h, w).double(), 3, 1, 1).reshape(-1).long()
        grown = torch.where(inside, torch.maximum(labels, pooled), labels)
        grown = torch.where(inside, grown[grown.clamp_min(0)], grown)
        if bool((grown == labels).all()):
            return labels.reshape(h, w)
        labels = grown


def check_output_shape(out: torch.Tensor, shape: Sequence[int], where: str) -> torch.Tensor:
    """What a plugin returned must have `shape`: a clear error here rather than a shape mismatch
    far downstream."""
    if not isinstance(out, torch.Tensor) or tuple(out.shape) != tuple(shape):
        got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        raise ValueError(f"{where} returned {got}; expected a tensor of shape {tuple(shape)}")
    return out
