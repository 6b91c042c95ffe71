"""Exact k-nearest-neighbour distances of a point cloud without an all-pairs matrix (used for the
3DGS initial scales of `GaussianModel.from_points`)."""
from __future__ import annotations

import math

import torch

from gs_regional.geometry.neighbors import morton_order


def knn_sq_dists(points: torch.Tensor, k: int = 3, window: int = 16, max_pairs: int = 1 << 20) -> torch.Tensor:
    """Exact squared distances (N, min(k, N-1)) from each point to its k nearest other points.

    No O(N^2) matrix: at most ~`max_pairs` candidate distances are held at a time.
    1. Neighbours along a Z-order curve give each point an upper bound u on its k-th distance.
    2. Points are grouped by the power of two h >= sqrt(u); for each group a grid of cell side h
       is built and each query only looks at the 3x3x3 cells around it, which hold every point
       within distance h, hence its k nearest.
    """
    n = points.shape[0]
    k = min(k, n - 1)
    if k <= 0:
        return points.new_zeros((n, 0), dtype=torch.float32)
    dev = points.device
    p = points.float()
    p = p - p.mean(0)

    order = morton_order(p)
    ps = p[order]
    w = max(window, k)
    d = torch.full((n, 2 * w), math.inf, device=dev)
    for off in range(1, min(w, n - 1) + 1):
        dd = ((ps[off:] - ps[:-off]) ** 2).sum(1)
        d[:-off, off - 1] = dd  # the point `off` places later
        d[off:, w + off - 1] = dd  # the point `off` places earlier
    ub = torch.empty(n, device=dev)
    ub[order] = d.topk(k, dim=1, largest=False).values[:, -1]

    extent = float((p.max(0).values - p.min(0).values).max().clamp_min(1e-12))
    lmin = math.floor(math.log2(extent)) - 19  # <= 2^20 cells per axis: keys < 2^61 fit in int64
    level = torch.ceil(torch.log2(ub.sqrt() * 1.001 + 1e-30)).clamp_min(lmin).long()
    offsets = torch.stack(torch.meshgrid(*[torch.arange(-1, 2, device=dev)] * 3, indexing="ij"), -1).reshape(27, 3)
    out = torch.empty((n, k), device=dev)
    for lv in torch.unique(level).tolist():
        h = 2.0**lv
        queries = (level == lv).nonzero().squeeze(1)
        # Only points near these queries can be their neighbours.
        lo, hi = p[queries].min(0).values - h, p[queries].max(0).values + h
        pts = ((p >= lo) & (p <= hi)).all(1).nonzero().squeeze(1)
        cell = torch.floor(p[pts] / h).long()
        cmin = cell.min(0).values - 1  # neighbours of the extreme cells stay >= 0
        cell -= cmin
        dims = cell.max(0).values + 2

        def key(c: torch.Tensor) -> torch.Tensor:
            return (c[..., 0] * dims[1] + c[..., 1]) * dims[2] + c[..., 2]

        skey, sorder = torch.sort(key(cell))
        sorted_pts = pts[sorder]
        uniq, counts = torch.unique_consecutive(skey, return_counts=True)
        starts = torch.cumsum(counts, 0) - counts
        qcell = torch.floor(p[queries] / h).long() - cmin
        nkey = key(qcell[:, None, :] + offsets[None])  # (Q, 27)
        pos = torch.searchsorted(uniq, nkey).clamp_max(uniq.numel() - 1)
        cnt = torch.where(uniq[pos] == nkey, counts[pos], 0)
        st = starts[pos]
        total, srt = torch.sort(cnt.sum(1))  # similar sizes together: tight padded matrices
        queries, cnt, st = queries[srt], cnt[srt], st[srt]
        q0 = 0
        while q0 < queries.numel():
            rows = torch.arange(1, queries.numel() - q0 + 1, device=dev) * total[q0:]
            q1 = q0 + max(1, int(torch.searchsorted(rows, max_pairs, right=True)))
            qi, c_flat, s_flat = queries[q0:q1], cnt[q0:q1].reshape(-1), st[q0:q1].reshape(-1)
            m = int(c_flat.sum())
            grp = torch.repeat_interleave(torch.arange(c_flat.numel(), device=dev), c_flat)
            first = torch.cumsum(c_flat, 0) - c_flat
            cand = sorted_pts[s_flat[grp] + torch.arange(m, device=dev) - first[grp]]
            owner = grp // 27
            dist = ((p[qi[owner]] - p[cand]) ** 2).sum(1).masked_fill(cand == qi[owner], math.inf)
            tot = total[q0:q1]
            col = torch.arange(m, device=dev) - (torch.cumsum(tot, 0) - tot)[owner]
            mat = torch.full((qi.numel(), int(tot.max())), math.inf, device=dev)
            mat[owner, col] = dist
            out[qi] = mat.topk(k, dim=1, largest=False).values
            q0 = q1
    return out
