"""Real spherical harmonics of degree 0-3 with the constants used by 3DGS and gsplat: the one home
of `SH_C0`, the SH basis, view-dependent colour and the rgb <-> DC-coefficient conversion.

A Gaussian's colour seen from a camera is ``max(SH(dir) + 0.5, 0)`` where ``dir`` is the unit vector
from the camera centre to the Gaussian's mean and SH sums the coefficients (..., K, C) against the
real SH basis, K = (degree + 1)^2.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def num_sh_coeffs(degree: int) -> int:
    """K = (degree + 1)^2 coefficients per channel."""
    if not 0 <= int(degree) <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be 0..{MAX_SH_DEGREE}, got {degree}")
    return (int(degree) + 1) ** 2


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Real SH basis (3DGS sign conventions) at unit directions (..., 3) -> (..., (degree+1)^2)."""
    k = num_sh_coeffs(degree)
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    basis = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        basis += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        basis += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    assert len(basis) == k
    return torch.stack(basis, dim=-1)


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Sum of SH coefficients `coeffs` (..., K>=(degree+1)^2, C) along unit directions `dirs` (..., 3).

    Returns (..., C). Coefficients beyond the requested degree are ignored.
    """
    k = num_sh_coeffs(degree)
    if coeffs.shape[-2] < k:
        raise ValueError(
            f"SH degree {degree} needs {k} coefficients per channel, got coefficients of shape "
            f"{tuple(coeffs.shape)}"
        )
    if degree == 0:
        return SH_C0 * coeffs[..., 0, :]
    # One contraction (not a sum of K slices): its backward is one op instead of K.
    basis = sh_basis(degree, dirs).to(coeffs.dtype)
    return torch.einsum("...k,...kc->...c", basis, coeffs[..., :k, :])


def sh_to_color(
    degree: int, coeffs: torch.Tensor, means: torch.Tensor, camera_center: torch.Tensor
) -> torch.Tensor:
    """View-dependent colour max(SH(normalize(mean - centre)) + 0.5, 0), as 3DGS/gsplat do.

    coeffs (N, K, C), means (N, 3), camera_center (3,) -> (N, C).
    """
    if degree > 0:
        dirs = F.normalize(means - camera_center.to(means), dim=-1)
    else:  # the DC term does not depend on the direction
        dirs = means
    return torch.clamp_min(eval_sh(degree, coeffs, dirs) + 0.5, 0.0)


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient whose colour is `rgb` (inverse of the degree-0 colour)."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh_dc: torch.Tensor) -> torch.Tensor:
    """Colour of the DC coefficient alone (before the clamp at 0)."""
    return sh_dc * SH_C0 + 0.5
