"""Choosing views: spread subsets, nearest cameras, camera paths for videos."""
from __future__ import annotations

import math
from typing import List, Sequence

import torch

from gs_regional.data.cameras import Camera
from gs_regional.utils.rotations import quat_to_rotmat, rotmat_to_quat


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


def frontier_view(cameras: Sequence[Camera], edited: Sequence[int], m: int, among: Sequence[int],
                  generator: torch.Generator = None) -> int:
    """The edited view whose `m` nearest cameras of `among` include the most views not edited yet:
    the next cycle starts at the edge of what is edited and carries the edit outwards, so that
    `cycles` x `m` edits cover as many views as they can (ties: a random one of them, with
    `generator`; all tied once every view is edited)."""
    done = set(edited)
    fresh = torch.tensor([sum(j not in done for j in nearest_cameras(cameras, v, m, among)) for v in edited])
    best = (fresh == fresh.max()).nonzero().squeeze(1)
    return list(edited)[int(best[torch.randint(len(best), (1,), generator=generator)])]


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
        qa, qb = (rotmat_to_quat(c.world_to_camera[:3, :3].double()) for c in (a, b))
        R = quat_to_rotmat(_slerp(qa, qb, t))  # world-to-camera rotation
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


def cycle_views(cameras: Sequence[Camera], cycle: int, first: int, edited: Sequence[int], m: int, among: Sequence[int],
                seed: int) -> tuple:
    """(frontal view, its `m` nearest cameras of `among`, nearest first) of refinement cycle
    `cycle`: cycle 0 starts at the `first` edited view, later cycles at the `frontier_view` of the
    `edited` views (ties drawn with `seed`), so the edit spreads outwards."""
    if cycle == 0:
        frontal = first
    else:
        frontal = frontier_view(cameras, edited, m, among, torch.Generator().manual_seed(seed * 7919 + cycle))
    return frontal, nearest_cameras(cameras, frontal, m, among)
