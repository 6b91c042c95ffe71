"""Quaternion <-> rotation-matrix conversion. Quaternions are (w, x, y, z), the layout of 3DGS
PLY files, gsplat and COLMAP."""
from __future__ import annotations

import torch


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternions (w, x, y, z), any norm -> (..., 3, 3) rotation matrices."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (w, x, y, z) with w >= 0.

    Of the four algebraically equal formulas, each row takes the one divided by its largest
    |component|, so the result stays accurate for rotations near 180 degrees."""
    batch = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    m00, m01, m02 = R[:, 0, 0], R[:, 0, 1], R[:, 0, 2]
    m10, m11, m12 = R[:, 1, 0], R[:, 1, 1], R[:, 1, 2]
    m20, m21, m22 = R[:, 2, 0], R[:, 2, 1], R[:, 2, 2]
    q_abs = torch.sqrt(
        torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1).clamp_min(0)
    )
    cands = torch.stack(
        [
            torch.stack([q_abs[:, 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, q_abs[:, 1] ** 2, m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, q_abs[:, 2] ** 2, m12 + m21], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[:, 3] ** 2], -1),
        ],
        1,
    ) / (2 * q_abs[:, :, None].clamp_min(0.1))
    q = cands[torch.arange(R.shape[0]), q_abs.argmax(-1)]
    q = q / q.norm(dim=-1, keepdim=True)
    q = q * torch.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(batch + (4,))


def covariance_to_scales_quats(cov: torch.Tensor) -> tuple:
    """(N, 3, 3) symmetric positive definite covariances -> (log-scales (N, 3), unit quaternions
    (N, 4) (w, x, y, z)): the Gaussians' own parametrisation (eigenvectors as a proper rotation)."""
    evals, evecs = torch.linalg.eigh(cov)
    evecs = evecs.clone()
    evecs[:, :, 0] *= torch.sign(torch.linalg.det(evecs))[:, None]  # a proper rotation
    return 0.5 * torch.log(evals.clamp_min(1e-14)), rotmat_to_quat(evecs)
