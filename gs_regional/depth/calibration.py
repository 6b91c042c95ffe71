"""Aligning monocular disparity to the scene's depth (DESIGN §3.2, steps 3–4).

Monocular disparity is known only up to scale and shift. It is aligned to the 3DGS disparity on
pixels outside the edit mask with the scale/shift-invariant statistics of MiDaS / the paper:
`f = median`, `s(δ) = mean |δ − f(δ)|`, `a = s(δ_ref) / s(δ_mono)`, `b = f(δ_ref) − a·f(δ_mono)`.
"""
from __future__ import annotations

from typing import Tuple

import torch


def _stats(x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    f = x.median()  # the lower median for even counts: order-preserving, so exact under a > 0
    return f, (x - f).abs().mean()


def _fit(m: torch.Tensor, r: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    fm, sm = _stats(m)
    fr, sr = _stats(r)
    if sm <= 0:
        raise ValueError("robust_affine: the monocular disparity is constant on the calibration pixels")
    a = sr / sm
    return a, fr - a * fm


def robust_affine(
    delta_mono: torch.Tensor,
    delta_ref: torch.Tensor,
    pixels: torch.Tensor,
    reject: float = 5.0,
    max_iters: int = 20,
) -> Tuple[float, float]:
    """Scale and shift (a, b) with `a·δ_mono + b ≈ δ_ref` on the pixels where `pixels` is True.

    The paper's estimator (median / mean absolute deviation) is computed on the given pixels; then,
    because the mean absolute deviation is pulled far off by gross outliers (3DGS floaters, wrong
    monocular depth at occlusion edges), it is re-estimated on the inliers, pixels whose residual
    |a·δ_mono + b − δ_ref| is at most `reject` × the median residual, until the inlier set stops
    changing. Data without outliers keeps (nearly) all pixels, so the result is the plain estimator;
    `reject=0` disables the re-estimation. Non-finite values are ignored.
    """
    if delta_mono.shape != delta_ref.shape or pixels.shape != delta_mono.shape:
        raise ValueError(
            f"robust_affine: delta_mono {tuple(delta_mono.shape)}, delta_ref {tuple(delta_ref.shape)} and "
            f"pixels {tuple(pixels.shape)} must have the same shape"
        )
    m = delta_mono.detach().double().flatten()
    r = delta_ref.detach().double().flatten()
    sel = pixels.detach().bool().flatten() & torch.isfinite(m) & torch.isfinite(r)
    m, r = m[sel], r[sel]
    if m.numel() < 2:
        raise ValueError(f"robust_affine: need at least 2 valid calibration pixels, got {m.numel()}")
    a, b = _fit(m, r)
    if reject > 0:
        keep = torch.ones_like(m, dtype=torch.bool)
        for _ in range(max_iters):
            res = (a * m + b - r).abs()
            # The tiny floor keeps exactly fitting pixels when the median residual is zero.
            new = res <= reject * res[keep].median() + 1e-9 * _stats(r[keep])[1]
            if new.sum() < 2 or torch.equal(new, keep):
                break
            keep = new
            a, b = _fit(m[keep], r[keep])
    return float(a), float(b)


def calibrated_depth(delta_mono: torch.Tensor, a: float, b: float, min_disparity: float = 1e-6) -> torch.Tensor:
    """Metric-like depth `1 / (a·δ_mono + b)`.

    Where the aligned disparity is ≤ `min_disparity` (the fit puts the point at or beyond
    infinity), it is clamped to `min_disparity`: such pixels come out very far (1/min_disparity)
    rather than negative or infinite; callers should treat them as invalid.
    """
    return 1.0 / (a * delta_mono + b).clamp_min(min_disparity)


def transfer_depth(
    d_mono_edit: torch.Tensor, d_mono_unedit: torch.Tensor, d_3dgs: torch.Tensor, eps: float = 1e-8
) -> torch.Tensor:
    """New depth `d_mono_edit / d_mono_unedit · d_3dgs`: the relative change one estimator sees
    between the unedited and the edited image, applied to the scene's own depth."""
    return d_mono_edit / d_mono_unedit.clamp_min(eps) * d_3dgs
