"""Choosing views: spread subsets, nearest cameras, camera paths for videos."""
from __future__ import annotations

import math
from typing import List, Sequence

import torch

from gs_regional.data.cameras import Camera


def spread_subset(indices: Sequence[int], k: int) -> List[int]:
    """At most k of `indices`, evenly spread over the list (cameras are usually ordered in a path)."""
    indices = list(indices)
    if k <= 0 or len(indices) <= k:
        return indices
    step = len(indices) / k
    return [indices[int(i * step)] for i in range(k)]


def nearest_cameras(cameras: Sequence[Camera], center_index: int, m: int, among: Sequence[int]) -> List[int]:
    """The `m` cameras of `among` (excluding `center_index`) closest to it by centre distance,
    nearest first."""
    c0 = cameras[center_index].center
    others = [i for i in among if i != center_index]
    dist = torch.stack([(cameras[i].center - c0).norm() for i in others]) if others else torch.zeros(0)
    order = torch.argsort(dist, stable=True).tolist()
    return [others[j] for j in order[:m]]


def _quat_from_matrix(R: torch.Tensor) -> torch.Tensor:
    R = R.double()
    w = torch.sqrt(torch.clamp(1 + R[0, 0] + R[1, 1] + R[2, 2], min=1e-12)) / 2
    if w > 1e-3:
        return torch.stack([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)])
    # Rotation near 180 degrees: use the largest diagonal element.
    i = int(torch.argmax(torch.diagonal(R)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = torch.sqrt(torch.clamp(1 + R[i, i] - R[j, j] - R[k, k], min=1e-12)) * 2
    q = torch.zeros(4, dtype=torch.float64)
    q[0] = (R[k, j] - R[j, k]) / s
    q[1 + i] = s / 4
    q[1 + j] = (R[j, i] + R[i, j]) / s
    q[1 + k] = (R[k, i] + R[i, k]) / s
    return q


def _matrix_from_quat(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = (q / q.norm()).tolist()
    return torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )


def _slerp(q0: torch.Tensor, q1: torch.Tensor, t: float) -> torch.Tensor:
    dot = float((q0 * q1).sum())
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + t * (q1 - q0)
        return q / q.norm()
    theta = math.acos(dot)
    return (math.sin((1 - t) * theta) * q0 + math.sin(t * theta) * q1) / math.sin(theta)


def camera_path(cameras: Sequence[Camera], n_frames: int) -> List[Camera]:
    """A smooth path through the given cameras (in the given order): centres interpolated linearly,
    rotations by slerp, intrinsics of the first camera. Used for turntable videos."""
    cameras = list(cameras)
    if len(cameras) == 1 or n_frames <= 1:
        return cameras[:1] * max(n_frames, 1)
    out = []
    segs = len(cameras) - 1
    for f in range(n_frames):
        s = f / (n_frames - 1) * segs
        i = min(int(s), segs - 1)
        t = s - i
        a, b = cameras[i], cameras[i + 1]
        q = _slerp(_quat_from_matrix(a.world_to_camera[:3, :3]), _quat_from_matrix(b.world_to_camera[:3, :3]), t)
        R = _matrix_from_quat(q)  # world-to-camera rotation
        center = (1 - t) * a.center.double() + t * b.center.double()
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = R
        w2c[:3, 3] = -R @ center
        ref = cameras[0]
        out.append(Camera(w2c.float(), ref.fx, ref.fy, ref.cx, ref.cy, ref.width, ref.height, image_name=f"path_{f:04d}"))
    return out


def order_by_azimuth(cameras: Sequence[Camera], indices: Sequence[int]) -> List[int]:
    """Sort camera indices by azimuth around the rig's centroid (for a turntable path)."""
    centers = torch.stack([cameras[i].center for i in indices])
    rel = centers - centers.mean(0)
    # Dominant plane of the rig: the two largest principal directions.
    _, _, vh = torch.linalg.svd(rel - rel.mean(0), full_matrices=False)
    u, v = rel @ vh[0], rel @ vh[1]
    ang = torch.atan2(v, u)
    # Unwrap around the largest gap so a front-facing arc is not cut in the middle.
    order = torch.argsort(ang).tolist()
    sorted_ang = ang[order]
    gaps = torch.cat([sorted_ang[1:] - sorted_ang[:-1], (sorted_ang[:1] + 2 * math.pi) - sorted_ang[-1:]])
    start = (int(torch.argmax(gaps)) + 1) % len(order)
    order = order[start:] + order[:start]
    return [list(indices)[j] for j in order]
