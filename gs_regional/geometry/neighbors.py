"""Exact nearest-neighbour and radius queries on 3D points, without an all-pairs matrix.

Both queries bin the reference points into a voxel grid (cells sorted by an integer cell key, looked up
with `searchsorted`), so a query only looks at the 3x3x3 cells around its own cell. Pure torch: runs
on the points' device, no extra dependency (scipy's cKDTree is not installed, and it would need a
round trip through the CPU). Candidate distances are evaluated in blocks of about `max_pairs`, so
memory stays bounded whatever N is; only one cell's queries x candidates must fit at once, which
is large only when very many points share one position (exact duplicates).

Ties: distances are exact (float32, the same arithmetic as a brute-force `((a - b) ** 2).sum(-1)`);
when several points lie at exactly the k-th distance, which of them is returned is unspecified.
"""
from __future__ import annotations

import math
from typing import Iterator, Tuple

import torch



def column_quantile(x: torch.Tensor, q: float) -> torch.Tensor:
    """Per-column q-quantile of (N, D) by order statistic (torch.quantile refuses > 16M entries)."""
    k = min(max(int(round(q * (x.shape[0] - 1))) + 1, 1), x.shape[0])
    return x.kthvalue(k, dim=0).values


def quantile_box(points: torch.Tensor, q: float = 0.02) -> Tuple[torch.Tensor, torch.Tensor]:
    """(lo, hi): the box of the q and 1 - q quantiles of (N, D) points per axis, which a few
    stray points cannot stretch as they do the min-max box."""
    return column_quantile(points, q), column_quantile(points, 1 - q)


def morton_order(points: torch.Tensor) -> torch.Tensor:
    """Permutation sorting points along a Z-order curve (10 bits per axis)."""
    lo, hi = points.min(0).values, points.max(0).values
    q = ((points - lo) / (hi - lo).clamp_min(1e-12) * 1023).long().clamp(0, 1023)

    def spread(v: torch.Tensor) -> torch.Tensor:  # insert two zero bits between the bits of v
        v = (v | (v << 16)) & 0x030000FF
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        return (v | (v << 2)) & 0x09249249

    code = spread(q[:, 0]) | (spread(q[:, 1]) << 1) | (spread(q[:, 2]) << 2)
    return torch.argsort(code, stable=True)


class VoxelGrid:
    """Reference points binned into cubic cells of side `cell` and sorted by cell key; the 3x3x3
    cells around a query hold every reference point within distance `cell` of it.

    `cell` should be a power of two: then `x / cell` is exact and so is the cell a point falls in,
    which makes that guarantee hold in floating point too. Keys are row-major with z fastest, so
    the three cells (x, y, z-1..z+1) are one contiguous run of the sorted points: 9 runs per cell.
    """

    def __init__(self, points: torch.Tensor, cell: float, index: torch.Tensor = None) -> None:
        self.cell = float(cell)
        index = torch.arange(points.shape[0], device=points.device) if index is None else index
        cells = self.cell_of(points)
        # one empty cell on every side: a neighbour key that wraps around a row end lands in one
        self.lo = cells.min(0).values - 1
        self.dims = cells.max(0).values - self.lo + 2
        keys, order = torch.sort(self.key(cells))
        self.sorted_index = index[order]  # reference point indices, grouped by cell
        self.keys, counts = torch.unique_consecutive(keys, return_counts=True)
        self.bounds = torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)])  # cell j: bounds[j]..bounds[j+1]

    def cell_of(self, points: torch.Tensor) -> torch.Tensor:
        return torch.floor(points / self.cell).long()

    def key(self, cells: torch.Tensor) -> torch.Tensor:
        c = cells - self.lo
        return (c[..., 0] * self.dims[1] + c[..., 1]) * self.dims[2] + c[..., 2]

    def contains(self, cells: torch.Tensor) -> torch.Tensor:
        """Whether cells lie in the grid's range (the points' cells and one more on each side)."""
        return ((cells >= self.lo) & (cells < self.lo + self.dims)).all(-1)

    def neighbour_runs(self, cells: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """(starts, counts), each (M, 9): the runs of `sorted_index` holding the reference points
        of the 27 cells around each of M cells (in the grid's range, see `contains`)."""
        xy = torch.tensor([(i, j, 0) for i in (-1, 0, 1) for j in (-1, 0, 1)], device=cells.device)
        key = self.key(cells[:, None, :] + xy)  # (M, 9): the middle cell of each z-run
        first = torch.searchsorted(self.keys, key - 1)
        end = torch.searchsorted(self.keys, key + 1, right=True)
        starts = self.bounds[first]
        return starts, self.bounds[end] - starts

    def candidate_blocks(self, queries: torch.Tensor, max_pairs: int, pad: int) -> Iterator[tuple]:
        """Yields (rows, cell_of_row, candidates): query rows, for each the block-local index of its
        cell, and per cell of the block the reference points of its 27 neighbouring cells, padded
        with `pad` to the block's widest cell: (cells, width). Queries of one cell share one
        candidate list, and cells of similar candidate counts are blocked together so that the
        (len(rows), width) distance matrices stay tight and under about `max_pairs` entries."""
        dev = queries.device
        qkey, qorder = torch.sort(self.key(self.cell_of(queries)))
        ukey, qcount = torch.unique_consecutive(qkey, return_counts=True)
        qstart = torch.cumsum(qcount, 0) - qcount
        starts, counts = self.neighbour_runs(self.cell_of(queries[qorder[qstart]]))
        width, cell_order = torch.sort(counts.sum(1))
        cost = torch.cumsum(qcount[cell_order], 0)  # queries in cells 0..j of `cell_order`
        c0 = 0
        while c0 < cell_order.numel():
            # a block of cells c0..c1-1 costs (their queries) * (widest cell) distances
            before = int(cost[c0 - 1]) if c0 else 0
            fits = (cost[c0:] - before) * width[c0:] <= max_pairs
            c1 = c0 + max(1, int(fits.sum()))  # `fits` is monotone: width and cost only grow
            block = cell_order[c0:c1]
            w = int(width[c1 - 1])
            run_counts, run_starts = counts[block].reshape(-1), starts[block].reshape(-1)
            m = int(run_counts.sum())
            run = torch.repeat_interleave(torch.arange(run_counts.numel(), device=dev), run_counts, output_size=m)
            run_first = torch.cumsum(run_counts, 0) - run_counts
            ramp = torch.arange(m, device=dev)
            source = run_starts[run] + ramp - run_first[run]  # position in sorted_index
            owner = run // 9
            cell_first = torch.cumsum(width[c0:c1], 0) - width[c0:c1]
            target = owner * w + ramp - cell_first[owner]  # position in the padded (cells, w) matrix
            candidates = torch.full((block.numel() * w,), pad, dtype=torch.long, device=dev)
            candidates.index_copy_(0, target, self.sorted_index.index_select(0, source))
            # the queries of these cells, each with its cell's block-local index
            nq = qcount[block]
            cell_of_row = torch.repeat_interleave(torch.arange(block.numel(), device=dev), nq)
            q_first = torch.cumsum(nq, 0) - nq
            rows = qorder[qstart[block][cell_of_row] + torch.arange(int(nq.sum()), device=dev) - q_first[cell_of_row]]
            yield rows, cell_of_row, candidates.view(block.numel(), w)
            c0 = c1


def _finest_cell_exponent(points: torch.Tensor) -> int:
    """Smallest power-of-two cell exponent whose cell keys fit in int64: at most 2^20 cells
    across the points' extent (3 x 20 bits of key) and cell indices far below 2^63."""
    extent = float((points.max(0).values - points.min(0).values).max())
    scale = max(extent, float(points.abs().max()) * 2.0**-40, 1e-30)
    return math.floor(math.log2(scale)) - 19


def _padded_columns(points: torch.Tensor) -> torch.Tensor:
    """(3, N + 1): the coordinates one axis per row (gathers and arithmetic on contiguous rows),
    followed by a column of inf that the padding index N picks."""
    return torch.cat([points, points.new_full((1, 3), math.inf)]).T.contiguous()


def _sq_dists_to_candidates(columns: torch.Tensor, queries: torch.Tensor, cell_of_row: torch.Tensor, candidates: torch.Tensor) -> torch.Tensor:
    """(Q, width) squared distances from each query to its cell's candidates (inf for padding),
    summed over x, y, z in that order like a brute-force `((a - b) ** 2).sum(-1)`."""
    out = None
    for axis in range(3):
        # index_select: several times faster on CPU than advanced indexing
        cand = columns[axis].index_select(0, candidates.reshape(-1)).view(candidates.shape)  # once per cell
        d = cand.index_select(0, cell_of_row) - queries[:, axis, None]
        out = d * d if out is None else out.add_(d.mul_(d))
    return out


def knn(points: torch.Tensor, k: int, window: int = 32, max_pairs: int = 1 << 22) -> Tuple[torch.Tensor, torch.Tensor]:
    """The k nearest *other* points of every point, exactly.

    Returns (sq_dists, indices), each (N, min(k, N-1)), nearest first. Duplicated points count as
    neighbours at distance 0.

    1. Neighbours along a Z-order curve give each point an upper bound u on its k-th distance.
    2. Points are grouped by the power of two h >= sqrt(u); for each group a voxel grid of cell h
       is built over the points near the group, and each query only looks at its 27 neighbouring
       cells, which hold every point within distance h, hence its k nearest.
    Memory: O(N·k) for the result plus `max_pairs` candidate distances at a time.
    """
    n = points.shape[0]
    k = min(k, n - 1)
    dev = points.device
    if k <= 0:
        return points.new_zeros((n, 0), dtype=torch.float32), torch.zeros((n, 0), dtype=torch.long, device=dev)
    p = points.detach().float()

    # 1. upper bound of the k-th distance from the points just before/after along the curve
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
    del d, ps

    lmin = _finest_cell_exponent(p)
    # (cells of 2^(lmin + 20) and more span all points: the bound for squared distances that
    # overflow float32)
    level = torch.ceil(torch.log2(ub.sqrt() * 1.001 + 1e-30)).clamp(lmin, lmin + 20).long()
    p_columns = _padded_columns(p)
    out_d = torch.empty((n, k), device=dev)
    out_i = torch.empty((n, k), dtype=torch.long, device=dev)
    for lv in torch.unique(level).tolist():
        h = 2.0**lv
        group = (level == lv).nonzero().squeeze(1)
        # Only points within h of the group's bounding box can be neighbours of its queries.
        lo, hi = p[group].min(0).values - h, p[group].max(0).values + h
        near = ((p >= lo) & (p <= hi)).all(1).nonzero().squeeze(1)
        grid = VoxelGrid(p[near], h, index=near)
        for rows, cell_of_row, candidates in grid.candidate_blocks(p[group], max_pairs, pad=n):
            qi = group[rows]
            dist = _sq_dists_to_candidates(p_columns, p[qi], cell_of_row, candidates)
            # Only candidates within the upper bound can be among the k nearest (the query and
            # at least k others are): a few dozen of the hundreds per row. Compacting them first
            # makes the top-k cheap. The slack covers rounding of the bound.
            width = dist.shape[1]
            flat = (dist <= ub[qi, None] * (1 + 1e-6)).view(-1).nonzero().squeeze(1)
            row = flat // width
            per_row = torch.bincount(row, minlength=qi.numel())
            target = row * int(per_row.max()) + torch.arange(row.numel(), device=dev) - (torch.cumsum(per_row, 0) - per_row)[row]
            near_d = torch.full((qi.numel() * int(per_row.max()),), math.inf, device=dev)
            near_i = torch.full_like(near_d, n, dtype=torch.long)
            near_d.index_copy_(0, target, dist.view(-1).index_select(0, flat))
            cand_flat = cell_of_row.index_select(0, row) * width + flat - row * width
            near_i.index_copy_(0, target, candidates.view(-1).index_select(0, cand_flat))
            near_d, near_i = near_d.view(qi.numel(), -1), near_i.view(qi.numel(), -1)
            # k + 1 nearest, then drop the query itself (or, if it is not among them because
            # more than k duplicates tie at distance 0, the last one)
            vals, pos = near_d.topk(k + 1, dim=1, largest=False)
            idx = near_i.gather(1, pos)
            is_self = idx == qi[:, None]
            keep = ~is_self
            keep[:, -1] &= is_self.any(1)
            out_d[qi] = vals[keep].view(-1, k)
            out_i[qi] = idx[keep].view(-1, k)
    return out_d, out_i


def within_radius(points: torch.Tensor, seeds: torch.Tensor, radius: float, max_pairs: int = 1 << 22) -> torch.Tensor:
    """(N,) bool: whether each point lies within `radius` (inclusive) of at least one seed.

    Grids of cell r/8, r/4, r/2 and then the power of two >= r: a point close to the seeds is
    settled on a fine grid by a seed within `radius` among few candidates; only the points still
    open go on to the coarser grids, and the last one (cell >= radius) covers the whole ball, so
    every point left without a seed within `radius` there has none.
    """
    n = points.shape[0]
    near = torch.zeros(n, dtype=torch.bool, device=points.device)
    if n == 0 or seeds.shape[0] == 0 or not radius >= 0:
        return near
    p, s = points.detach().float(), seeds.detach().float().to(points.device)
    r2 = float(radius) ** 2
    s_columns = _padded_columns(s)
    finest = _finest_cell_exponent(s)
    last = max(math.ceil(math.log2(max(float(radius), 1e-30))), finest)
    # Points beyond the seeds' bounding box + radius have none (the box test also keeps far
    # points' cell indices from overflowing).
    reach = 2.0**last
    open_ = ((p >= s.min(0).values - reach) & (p <= s.max(0).values + reach)).all(1).nonzero().squeeze(1)
    for level in range(max(last - 3, finest), last + 1):
        grid = VoxelGrid(s, 2.0**level)
        queries = open_[grid.contains(grid.cell_of(p[open_]))]  # the others have no seed around
        for rows, cell_of_row, seed_blocks in grid.candidate_blocks(p[queries], max_pairs, pad=s.shape[0]):
            qi = queries[rows]
            near[qi] = (_sq_dists_to_candidates(s_columns, p[qi], cell_of_row, seed_blocks) <= r2).any(1)
        open_ = open_[~near[open_]]
    return near


def connected_components(n: int, src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """(n,) component label of each node of the undirected graph with edges (src, dst): the
    smallest node id of its component. Union-find as array rounds: every edge hooks the larger of
    its two roots onto the smaller (scatter-min on the roots), then pointer jumping flattens the
    trees; O(E) per round, about log(n) rounds, no Python loop over nodes or edges."""
    labels = torch.arange(n, device=src.device)
    if src.numel() == 0:
        return labels
    while True:
        a, b = labels[src], labels[dst]
        m = torch.minimum(a, b)
        new = labels.scatter_reduce(0, a, m, "amin").scatter_reduce(0, b, m, "amin")
        while True:  # pointer jumping: a node's label is a node of its component with a smaller id
            jumped = new[new]
            if torch.equal(jumped, new):
                break
            new = jumped
        if torch.equal(new, labels):
            return labels
        labels = new


def components(neighbourhood: torch.Tensor, member: torch.Tensor) -> torch.Tensor:
    """(N,) the connected component of each `member` row (bool (N,)) in the graph whose edges join a
    row to each of its `neighbourhood` rows ((N, k) indices, e.g. `knn`'s) when both are members,
    either way round (`connected_components`): its smallest member row; -1 for the others."""
    src = torch.arange(member.shape[0], device=member.device)[:, None].expand_as(neighbourhood)
    both = member[src] & member[neighbourhood]
    label = connected_components(member.shape[0], src[both], neighbourhood[both])
    return torch.where(member, label, torch.full_like(label, -1))
