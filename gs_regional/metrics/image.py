"""Image quality metrics on (..., H, W, 3) tensors in [0, 1]."""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F


def psnr(a: torch.Tensor, b: torch.Tensor, mask: Optional[torch.Tensor] = None) -> float:
    """PSNR in dB; `mask` (..., H, W) restricts it to a region (e.g. the unedited one)."""
    err = (a.float() - b.float()) ** 2
    if mask is not None:
        m = mask.float()[..., None].expand_as(err)
        mse = (err * m).sum() / m.sum().clamp_min(1)
    else:
        mse = err.mean()
    return float(10 * torch.log10(1.0 / mse.clamp_min(1e-12)))


def _ssim_map(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """SSIM map (B, H, W) for (B, H, W, C) images, Gaussian window as in the 3DGS code."""
    x = a.permute(0, 3, 1, 2).float()
    y = b.permute(0, 3, 1, 2).float()
    c = x.shape[1]
    g = torch.exp(-((torch.arange(window, device=x.device) - window // 2) ** 2) / (2 * sigma**2))
    g = (g / g.sum()).float()
    k = (g[:, None] @ g[None, :]).expand(c, 1, window, window).contiguous()
    conv = lambda t: F.conv2d(t, k, padding=window // 2, groups=c)  # noqa: E731
    mu_x, mu_y = conv(x), conv(y)
    sxx = conv(x * x) - mu_x**2
    syy = conv(y * y) - mu_y**2
    sxy = conv(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return s.mean(1)


def ssim_loss_value(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Differentiable mean SSIM of (H, W, 3) or (B, H, W, 3) images."""
    if a.dim() == 3:
        a, b = a[None], b[None]
    return _ssim_map(a, b).mean()


def ssim(a: torch.Tensor, b: torch.Tensor, mask: Optional[torch.Tensor] = None) -> float:
    if a.dim() == 3:
        a, b = a[None], b[None]
        mask = None if mask is None else mask[None]
    s = _ssim_map(a, b)
    if mask is not None:
        m = mask.float()
        return float((s * m).sum() / m.sum().clamp_min(1))
    return float(s.mean())
