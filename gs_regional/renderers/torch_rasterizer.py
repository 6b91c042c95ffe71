"""The `torch-rasterizer`: a differentiable 3DGS rasterizer in pure PyTorch (CPU and GPU).

Semantics follow gsplat (classic mode, `render_mode="RGB+ED"`):
  * EWA projection with the Jacobian of the perspective projection, camera-space x/y clamped to
    the image extent plus 30 % of the half field of view (gsplat's `persp_proj`; for a centred
    principal point this is 1.3 * tan(fov/2) * z), a 0.3 px low-pass on the 2D covariance
    diagonal, Gaussians with z < near_plane culled;
  * radius = ceil(3.33 * sqrt(largest eigenvalue)) (no contribution with alpha >= 1/255 lies
    outside it);
  * alpha = min(0.999, o * exp(-sigma)), sigma = 1/2 d^T Sigma^-1 d, d = mean2d - pixel centre
    (x + 0.5, y + 0.5); contributions with alpha < 1/255 (or sigma < 0) are skipped;
  * front-to-back compositing that stops *before* the Gaussian that would bring the
    transmittance to <= 1e-4.

Tiling. Pixels are grouped in `tile_size` x `tile_size` tiles and each tile row is cut into
strips of `strip_width` pixels. Every Gaussian is binned into the strips that its opacity-aware
ellipse (the region where alpha >= 1/255 is possible, computed exactly row by row) touches; the
(strip, Gaussian) entries are sorted by strip, then depth. Each entry evaluates its strip's pixels
at once, so the work is proportional to the real footprints, never to pixels x Gaussians. Entries
are generated per band of tile rows and composited in chunks of about `chunk_size` pixel
evaluations, which bounds the temporary memory whatever the scene; for the backward pass only the
entries that still contribute after early termination are kept. Transmittance comes from a
segmented log-space scan down each strip's depth-ordered entries (running sum in float64, so it
matches sequential compositing to ~1e-7). The backward pass is a hand-written
`torch.autograd.Function` (the gradients gsplat's kernels compute, including none through
clamped or skipped alphas), not autograd over per-pixel tensors.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Dict, List, Optional, Tuple

import torch
from torch.autograd.function import once_differentiable

from gs_regional.data.cameras import Camera
from gs_regional.registry import register
from gs_regional.renderers.base import PixelWeights, Renderer
from gs_regional.utils.rotations import quat_to_rotmat
from gs_regional.utils.sh import sh_to_color

ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped (gsplat)
ALPHA_MAX = 0.999
T_MIN = 1e-4  # compositing stops before the transmittance would reach this
LOG_T_MIN = math.log(T_MIN)
RADIUS_SIGMAS = 3.33  # sqrt(2 ln 255) = 3.329: beyond this, alpha < 1/255 even at opacity 1


@dataclass
class Projection:
    means2d: torch.Tensor  # (N, 2) pixel coordinates
    cov2d: torch.Tensor  # (N, 3) a, b, c of [[a, b], [b, c]] incl. the low-pass
    conics: torch.Tensor  # (N, 3) the same for the inverse
    det: torch.Tensor  # (N,)
    depths: torch.Tensor  # (N,) camera-space z


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    viewmat: torch.Tensor,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    eps2d: float = 0.3,
) -> Projection:
    """EWA projection of 3D Gaussians (gsplat's `persp_proj`), differentiable, no culling."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    mc = means @ R.T + t
    x, y, z = mc.unbind(-1)
    # Camera-space covariance = M M^T with M = R_view R_q diag(s).
    M = R @ quat_to_rotmat(quats) * scales[:, None, :]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    rz = 1.0 / z
    # Clamping keeps the Jacobian of far off-screen Gaussians from exploding (as 3DGS/gsplat).
    tx = z * torch.clamp(x * rz, -lim_x_neg, lim_x_pos)
    ty = z * torch.clamp(y * rz, -lim_y_neg, lim_y_pos)
    # Rows of J M, J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]].
    j0 = (fx * rz)[:, None] * (M[:, 0, :] - (tx * rz)[:, None] * M[:, 2, :])
    j1 = (fy * rz)[:, None] * (M[:, 1, :] - (ty * rz)[:, None] * M[:, 2, :])
    a = (j0 * j0).sum(-1) + eps2d
    b = (j0 * j1).sum(-1)
    c = (j1 * j1).sum(-1) + eps2d
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)
    return Projection(means2d, torch.stack([a, b, c], dim=-1), conics, det, z)


def cull(
    proj: Projection, width: int, height: int, near_plane: float = 0.01, far_plane: float = 1e10
) -> Tuple[torch.Tensor, torch.Tensor]:
    """gsplat's culling: returns (radii int32 (N,), visible bool (N,))."""
    a, _, c = proj.cov2d.unbind(-1)
    det = proj.det
    half = 0.5 * (a + c)
    lam_max = half + torch.sqrt(torch.clamp_min(half * half - det, 0.0))
    radius = torch.ceil(RADIUS_SIGMAS * torch.sqrt(lam_max))
    mx, my = proj.means2d.unbind(-1)
    z = proj.depths
    visible = (
        (z >= near_plane)
        & (z <= far_plane)
        & (det > 0)
        & (radius > 0)
        & (mx + radius > 0)
        & (mx - radius < width)
        & (my + radius > 0)
        & (my - radius < height)
    )
    visible &= torch.isfinite(proj.means2d).all(-1) & torch.isfinite(proj.conics).all(-1)
    radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)
    return radii, visible


# ----------------------------------------------------------------------------------------------
# Binning: Gaussians -> (pixel strip, Gaussian) entries


@dataclass
class _Layout:
    """How the image is cut up.

    `tile_size` x `tile_size` tiles, each tile row cut into strips of `strip_width` pixels; pixel
    buffers are stored tile-major (tile, row in tile, strip, column in strip), one buffer row per
    strip. Work is done in bands of whole tile rows and, inside a band, in chunks of whole strips.
    """

    width: int
    height: int
    tile_size: int
    strip_width: int
    chunk_size: int  # pixel evaluations per chunk
    band_size: int  # (estimated) pixel evaluations per band

    @property
    def tiles_x(self) -> int:
        return -(-self.width // self.tile_size)

    @property
    def tiles_y(self) -> int:
        return -(-self.height // self.tile_size)

    @property
    def num_strips(self) -> int:
        return self.tiles_x * self.tiles_y * self.tile_size * (self.tile_size // self.strip_width)


@dataclass
class _Bins:
    """Per-Gaussian binning data (float64) and the bands of image rows to process."""

    order: torch.Tensor  # Gaussians that can contribute, in depth order
    mx: torch.Tensor
    my: torch.Tensor
    a: torch.Tensor  # conic (a, b, c) and its determinant
    b: torch.Tensor
    det: torch.Tensor
    lim: torch.Tensor  # alpha >= 1/255 needs sigma <= lim
    y0: torch.Tensor  # rows [y0, y1) that the ellipse reaches
    y1: torch.Tensor
    bands: List[Tuple[int, int]]  # image row ranges, multiples of tile_size


def _take(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    return x.index_select(0, idx)  # much faster than x[idx] on CPU


def _ramp(counts: torch.Tensor) -> torch.Tensor:
    """0, 1, .., counts[0]-1, 0, 1, .., counts[1]-1, ...: the position inside each repeat."""
    total = int(counts.sum())
    starts = torch.cumsum(counts, 0) - counts
    return torch.arange(total, device=counts.device) - torch.repeat_interleave(starts, counts)


def _bin(means2d, conics, opacities, depths, layout: _Layout) -> _Bins:
    f64 = torch.float64
    ts, height = layout.tile_size, layout.height
    mx, my = means2d[:, 0].to(f64), means2d[:, 1].to(f64)
    a, b, c = (conics[:, i].to(f64) for i in range(3))
    det = a * c - b * b
    # alpha >= 1/255 needs sigma <= ln(255 o): the ellipse d^T conic d <= 2 lim. The small margins
    # absorb float rounding so that no contribution the compositing would keep is left out.
    o = opacities.to(f64)
    lim = torch.log(torch.clamp_min(o * 255.0, 1.0)) * (1 + 1e-5) + 1e-4
    ey = torch.sqrt(2 * lim * a / det)  # half height of the ellipse: sqrt(2 lim Sigma_yy)
    # Rows whose pixel centre y + 0.5 lies within [my - ey, my + ey].
    y0 = torch.ceil(my - ey - 0.5).clamp(0, height).long()
    y1 = (torch.floor(my + ey - 0.5) + 1).clamp(0, height).long()
    keep = (o * 255.0 >= 1.0) & (det > 0) & (y1 > y0)
    order = torch.sort(depths, stable=True).indices
    order = _take(order, _take(keep, order).nonzero().squeeze(1))
    # Bands: estimate the pixel evaluations of every tile row (rows covered x strips per row)
    # and cut greedily, so that memory stays bounded even when splats are huge.
    ex = torch.sqrt(2 * lim * c / det)
    per_row = (_take(2 * ex, order) / layout.strip_width + 2) * layout.strip_width
    gy0, gy1 = _take(y0, order), _take(y1, order)
    ty0 = torch.div(gy0, ts, rounding_mode="floor")
    n_tr = torch.div(gy1 - 1, ts, rounding_mode="floor") - ty0 + 1
    pair = torch.repeat_interleave(torch.arange(order.numel(), device=order.device), n_tr)
    tr = _take(ty0, pair) + _ramp(n_tr)
    rows = torch.minimum(_take(gy1, pair), (tr + 1) * ts) - torch.maximum(_take(gy0, pair), tr * ts)
    work = torch.zeros(layout.tiles_y, dtype=f64, device=order.device)
    work.index_add_(0, tr, rows * _take(per_row, pair))
    band_of = ((torch.cumsum(work, 0) - work) / max(layout.band_size, 1)).floor().long().tolist()
    bands, start = [], 0
    for i in range(1, layout.tiles_y + 1):
        if i == layout.tiles_y or band_of[i] != band_of[start]:
            bands.append((start * ts, min(i * ts, height)))
            start = i
    return _Bins(order, mx, my, a, b, det, lim, y0, y1, bands)


def _band_entries(bins: _Bins, layout: _Layout, band: Tuple[int, int], dtype: torch.dtype):
    """(strip, Gaussian) entries of the rows in `band`, sorted by strip then depth.

    Returns gauss, key (strip index in the layout), ex (mean x - 0.5 - x of the strip's first
    pixel), dy (mean y - (y + 0.5)) and the chunks (entry ranges of whole strips).
    """
    ts, sw, width = layout.tile_size, layout.strip_width, layout.width
    spt = ts // sw  # strips per tile row
    band0, band1 = band
    order = bins.order
    r0 = torch.clamp_min(_take(bins.y0, order), band0)
    r1 = torch.clamp_max(_take(bins.y1, order), band1)
    inside = (r1 > r0).nonzero().squeeze(1)
    order, r0, r1 = _take(order, inside), _take(r0, inside), _take(r1, inside)
    # Rows of every Gaussian in the band, Gaussians in depth order ...
    nrows = r1 - r0
    g = torch.repeat_interleave(order, nrows)
    y = torch.repeat_interleave(r0, nrows) + _ramp(nrows)
    # ... and the span of pixels on each row where the ellipse can reach alpha >= 1/255.
    ag, dy = _take(bins.a, g), _take(bins.my, g) - (y + 0.5)
    disc = 2 * ag * _take(bins.lim, g) - _take(bins.det, g) * dy * dy
    half = torch.sqrt(torch.clamp_min(disc, 0.0)) / ag
    centre = _take(bins.mx, g) - 0.5 + _take(bins.b, g) * dy / ag  # pixel x where sigma is smallest
    xa = torch.ceil(centre - half - 1e-3)
    xb = torch.floor(centre + half + 1e-3)
    hit = (disc >= 0) & (xb >= 0) & (xa <= width - 1) & (xa <= xb)
    sa = torch.div(xa.clamp(0, width - 1).long(), sw, rounding_mode="floor")
    sb = torch.div(xb.clamp(0, width - 1).long(), sw, rounding_mode="floor")
    nstrips = torch.where(hit, sb - sa + 1, 0)
    # One entry per strip the span touches.
    row = torch.repeat_interleave(torch.arange(g.numel(), device=g.device), nstrips)
    s = _take(sa, row) + _ramp(nstrips)  # strip column in the image
    g, y, dy = _take(g, row), _take(y, row), _take(dy, row)
    tx, ty = s // spt, y // ts
    key = ((ty * layout.tiles_x + tx) * ts + (y - ty * ts)) * spt + (s - tx * spt)
    # Stable sort by strip keeps the depth order inside each strip (int32 sorts twice as fast).
    key, perm = torch.sort(key.int() if layout.num_strips < 2**31 else key, stable=True)
    key = key.long()
    g, s, dy = _take(g, perm), _take(s, perm), _take(dy, perm)
    ex = (_take(bins.mx, g) - 0.5 - (s * sw).to(torch.float64)).to(dtype)
    # Chunks of about chunk_size pixel evaluations, cut only between strips.
    per_chunk = max(1, layout.chunk_size // sw)
    n = key.numel()
    cuts = [0]
    if n > per_chunk:
        targets = torch.arange(per_chunk, n, per_chunk, device=key.device)
        for start in torch.searchsorted(key, _take(key, targets), side="left").tolist():
            if start > cuts[-1]:
                cuts.append(start)
    cuts.append(n)
    chunks = [(c0, c1) for c0, c1 in zip(cuts[:-1], cuts[1:]) if c1 > c0]
    return g, key, ex, dy.to(dtype), chunks


def _segments(key: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For entries sorted by key: segment id of each entry, first and last entry of each segment."""
    n = key.numel()
    first = torch.ones(n, dtype=torch.bool, device=key.device)
    first[1:] = key[1:] != key[:-1]
    seg = torch.cumsum(first, 0) - 1
    starts = first.nonzero().squeeze(1)
    ends = torch.cat([starts[1:] - 1, starts.new_tensor([n - 1])]) if n else starts
    return seg, starts, ends


# ----------------------------------------------------------------------------------------------
# Rasterization with a hand-written backward


def _entry_params(conics, opacities, g):
    """Per-entry conic coefficients and opacity (1-D gathers are much faster than row gathers)."""
    return [conics[:, i].contiguous().index_select(0, g) for i in range(3)] + [opacities.index_select(0, g)]


def _composite_chunk(g, key, ex, dy, conics, opacities, feats, cols, out, alpha_out, log_t_final):
    """Composite one chunk of entries (whole strips) into the output buffers, in place.

    Returns the entries to keep for the backward pass: (gauss, key, ex, dy, alpha, T). With
    `log_t_final` None (a render nothing is differentiated through) it keeps nothing and returns None.
    """
    a, b, c, o = _entry_params(conics, opacities, g)
    dx = ex[:, None] - cols  # (E, strip_width): mean x - pixel centre x
    # -sigma = (-a/2 dx - b dy) dx - c/2 dy^2, evaluated with two fused multiply-adds.
    inner = torch.addcmul((-b * dy)[:, None], (-0.5 * a)[:, None], dx)
    neg_sigma = torch.addcmul((-0.5 * c * dy * dy)[:, None], inner, dx)
    alpha = torch.clamp_max(o[:, None] * torch.exp(neg_sigma), ALPHA_MAX)
    alpha = torch.where((neg_sigma <= 0) & (alpha >= ALPHA_MIN), alpha, 0.0)
    # Transmittance by a segmented scan of log(1 - alpha) down each strip's entries; the running
    # sum is float64 because it runs over the whole chunk.
    log1m = torch.log1p(-alpha)
    cs = torch.cumsum(log1m, 0, dtype=torch.float64)
    seg, starts, _ = _segments(key)
    base = cs.index_select(0, starts) - log1m.index_select(0, starts)
    log_t_next = (cs - base.index_select(0, seg)).to(alpha.dtype)
    t = torch.exp(log_t_next - log1m)
    # Stop before the Gaussian that brings T to <= 1e-4 (a prefix of each pixel's list).
    valid = log_t_next > LOG_T_MIN
    alpha = alpha * valid
    w = alpha * t
    fg = feats.index_select(0, g)
    out.index_add_(0, key, (w[:, :, None] * fg[:, None, :]).reshape(key.numel(), out.shape[1]))
    alpha_out.index_add_(0, key, w)
    if log_t_final is None:
        return None
    log_t_final.index_add_(0, key, torch.where(valid, log1m, 0.0))
    entry = (g, key, ex, dy, alpha, t)
    # Behind opaque surfaces many entries end up with no contribution at all: dropping them
    # keeps the saved state proportional to what is actually visible.
    live = (alpha > 0).any(1)
    if int(live.sum()) < 0.9 * live.numel():
        idx = live.nonzero().squeeze(1)
        entry = tuple(_take(x, idx) for x in entry)
    return entry


def _composite_all(means2d, conics, opacities, feats, depths, layout: _Layout, out, alpha_out, log_t_final) -> list:
    """Bin, sort and composite every entry into the buffers (in place); returns the kept entries
    of every chunk (see `_composite_chunk`; none with `log_t_final` None)."""
    cols = torch.arange(layout.strip_width, dtype=feats.dtype, device=feats.device)
    bins = _bin(means2d, conics, opacities, depths, layout)
    kept = []
    for band in bins.bands:
        gauss, keys, exs, dys, chunks = _band_entries(bins, layout, band, feats.dtype)
        for r0, r1 in chunks:
            entry = _composite_chunk(
                gauss[r0:r1], keys[r0:r1], exs[r0:r1], dys[r0:r1], conics, opacities, feats,
                cols, out, alpha_out, log_t_final,
            )
            if entry is not None:
                kept.append(entry)
    return kept


def _strips_to_image(buf: torch.Tensor, layout: _Layout) -> torch.Tensor:
    """Tile-major strip buffer (strips, strip_width * C) -> image (H, W, C)."""
    ts, ty, tx = layout.tile_size, layout.tiles_y, layout.tiles_x
    img = buf.reshape(ty, tx, ts, ts, -1).permute(0, 2, 1, 3, 4).reshape(ty * ts, tx * ts, -1)
    return img[: layout.height, : layout.width]


def _image_to_strips(image: torch.Tensor, layout: _Layout) -> torch.Tensor:
    """Image (H, W, C) -> tile-major strips (strips, strip_width, C), zero outside the image."""
    ts, ty, tx = layout.tile_size, layout.tiles_y, layout.tiles_x
    pad = image.new_zeros(ty * ts, tx * ts, image.shape[-1])
    pad[: layout.height, : layout.width] = image
    return pad.reshape(ty, ts, tx, ts, -1).permute(0, 2, 1, 3, 4).reshape(layout.num_strips, layout.strip_width, -1)


class SparsePixelWeights(PixelWeights):
    """The weights w = alpha T of every contributing (strip, Gaussian) entry of one view, kept from
    a single forward pass: `splat` and `gather` are then sparse sums, no new render. Memory is
    ~48 bytes per contributing entry (each covers `strip_width` pixels)."""

    def __init__(self, gauss: torch.Tensor, key: torch.Tensor, weights: torch.Tensor, layout: _Layout, n: int) -> None:
        self.gauss, self.key, self.weights, self.layout, self.n = gauss, key, weights, layout, n

    def splat(self, feats: torch.Tensor) -> torch.Tensor:
        f = feats.to(self.weights.dtype).index_select(0, self.gauss)
        buf = self.weights.new_zeros(self.layout.num_strips, self.layout.strip_width * f.shape[1])
        # The same entries in the same order as the forward pass: the same sums as a render.
        buf.index_add_(0, self.key, (self.weights[:, :, None] * f[:, None, :]).reshape(self.key.numel(), -1))
        return _strips_to_image(buf, self.layout)

    def gather(self, image: torch.Tensor) -> torch.Tensor:
        flat = image.dim() == 2
        img = (image[..., None] if flat else image).to(self.weights)
        px = _image_to_strips(img, self.layout).index_select(0, self.key)  # (E, strip_width, C)
        out = self.weights.new_zeros(self.n, img.shape[-1])
        out.index_add_(0, self.gauss, torch.einsum("ex,exc->ec", self.weights, px))
        return out[:, 0] if flat else out


class _Rasterize(torch.autograd.Function):
    """Front-to-back compositing of (strip, Gaussian) entries, each over its strip of pixels.

    Outputs, in the tile-major strip layout: features (strips, strip_width * C) = sum_i w_i f_i
    and alpha (strips, strip_width) = sum_i w_i with w_i = alpha_i T_i.
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, depths, layout: _Layout):
        sw, channels = layout.strip_width, feats.shape[1]
        dtype, device = feats.dtype, feats.device
        n_strips = layout.num_strips
        out = torch.zeros(n_strips, sw * channels, dtype=dtype, device=device)
        alpha_out = torch.zeros(n_strips, sw, dtype=dtype, device=device)
        # A render nothing is differentiated through (most of an edit's) keeps no state for backward.
        differentiable = any(ctx.needs_input_grad)
        log_t_final = torch.zeros(n_strips, sw, dtype=dtype, device=device) if differentiable else None
        conics, opacities, fd = conics.detach(), opacities.detach(), feats.detach()
        # Kept for the backward pass, per chunk: the entries that contribute to some pixel, with
        # their alpha (0 where skipped or after the stop) and T.
        ctx.kept = _composite_all(means2d.detach(), conics, opacities, fd, depths.detach(), layout, out, alpha_out, log_t_final)
        if differentiable:
            ctx.save_for_backward(conics, opacities, fd, torch.exp(log_t_final))
        return out, alpha_out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out, grad_alpha):
        conics, opacities, feats, t_final = ctx.saved_tensors
        n, channels = feats.shape
        sw = t_final.shape[1]
        dtype, device = feats.dtype, feats.device
        cols = torch.arange(sw, dtype=dtype, device=device)
        grad_out = grad_out.contiguous()
        grad_alpha = grad_alpha.contiguous()
        # Columns: d mean x, d mean y, d conic a, b, c, d opacity, d features.
        grads = torch.zeros(6 + channels, n, dtype=dtype, device=device)
        for g, key, ex, dy, alpha, t in ctx.kept:
            if key.numel() == 0:
                continue
            a, b, c, o = _entry_params(conics, opacities, g)
            w = alpha * t
            gout = grad_out.index_select(0, key).view(-1, sw, channels)
            gf = torch.einsum("rxc,rc->rx", gout, feats.index_select(0, g))
            # sum_{j after i} w_j (G . f_j) within the same pixel: a segmented suffix sum.
            cs = torch.cumsum(w * gf, 0, dtype=torch.float64)
            seg, _, ends = _segments(key)
            suffix = (cs.index_select(0, ends).index_select(0, seg) - cs).to(dtype)
            tail = grad_alpha.index_select(0, key) * t_final.index_select(0, key)
            d_alpha = t * gf + (tail - suffix) / (1.0 - alpha)
            # Only kept contributions get gradients, and none where alpha was clamped (as gsplat).
            d_alpha = torch.where((alpha > 0) & (alpha < ALPHA_MAX), d_alpha, 0.0)
            d_sigma = -alpha * d_alpha
            dx = ex[:, None] - cols
            s0 = d_sigma.sum(1)
            s1 = (dx * d_sigma).sum(1)
            s2 = (dx * dx * d_sigma).sum(1)
            per_entry = [
                a * s1 + b * dy * s0,  # d sigma / d mean x = a dx + b dy
                b * s1 + c * dy * s0,  # d sigma / d mean y = b dx + c dy
                0.5 * s2,
                dy * s1,
                0.5 * dy * dy * s0,
                (alpha * d_alpha).sum(1) / o,  # d alpha / d o = exp(-sigma) = alpha / o
            ]
            d_feat = torch.einsum("rx,rxc->cr", w, gout)
            for i, v in enumerate(per_entry):
                grads[i].scatter_add_(0, g, v)
            for i in range(channels):
                grads[6 + i].scatter_add_(0, g, d_feat[i])
        return grads[0:2].T, grads[2:5].T, grads[5], grads[6:].T, None, None


def rasterize(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    feats: torch.Tensor,
    depths: torch.Tensor,
    width: int,
    height: int,
    tile_size: int = 16,
    strip_width: int = 8,
    chunk_size: int = 1 << 20,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Composite projected Gaussians front to back.

    means2d (N, 2), conics (N, 3) = (a, b, c) of the inverse 2D covariance, opacities (N,) and
    feats (N, C) are differentiable; depths (N,) only orders them. Returns the feature image
    (H, W, C) = sum_i w_i f_i and alpha (H, W) = sum_i w_i, w_i = alpha_i T_i.
    """
    layout = _Layout(width, height, tile_size, strip_width, int(chunk_size), 8 * int(chunk_size))
    out, alpha = _Rasterize.apply(means2d, conics, opacities, feats, depths, layout)
    return _strips_to_image(out, layout), _strips_to_image(alpha, layout)[..., 0]


# ----------------------------------------------------------------------------------------------


@register("torch-rasterizer")
class TorchRasterizer(Renderer):
    """Pure-PyTorch tiled rasterizer with gsplat's semantics (see the module docstring)."""

    @dataclass
    class Config(Renderer.Config):
        # Pixels of a tile row evaluated together per Gaussian; must divide tile_size. Narrow
        # strips waste less work on small splats, wide ones have less per-entry overhead.
        strip_width: int = 8
        # (pixel, Gaussian) evaluations handled at once; bounds peak memory (~100 B each).
        chunk_size: int = 1 << 20

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where)
        if self.cfg.strip_width < 1 or self.cfg.tile_size % self.cfg.strip_width:
            raise ValueError(
                f"renderer.strip_width must divide renderer.tile_size ({self.cfg.tile_size}), "
                f"got {self.cfg.strip_width}"
            )
        if self.cfg.chunk_size < 1:
            raise ValueError(f"renderer.chunk_size must be >= 1, got {self.cfg.chunk_size}")

    def _project_visible(self, model, camera: Camera):
        """Cull, then project the visible Gaussians differentiably (culled ones may divide by 0).
        Returns (idx of the visible rows, their Projection, radii (N,), visible (N,))."""
        means = model.means
        device, dtype = means.device, means.dtype
        width, height = int(camera.width), int(camera.height)
        viewmat = camera.world_to_camera.to(device=device, dtype=dtype)
        intr = (camera.fx, camera.fy, camera.cx, camera.cy, width, height, self.cfg.eps2d)
        with torch.no_grad():
            proj = project_gaussians(means, model.quats, torch.exp(model.log_scales), viewmat, *intr)
            radii, visible = cull(proj, width, height, self.cfg.near_plane, self.cfg.far_plane)
        idx = visible.nonzero().squeeze(1)
        take = lambda x: x.index_select(0, idx)  # noqa: E731  (faster than x[idx] on CPU)
        if torch.is_grad_enabled() and any(p.requires_grad for p in (means, model.quats, model.log_scales)):
            proj = project_gaussians(take(means), take(model.quats), torch.exp(take(model.log_scales)), viewmat, *intr)
        else:  # nothing to differentiate: the visible rows of the projection above are the same values
            proj = Projection(*(take(getattr(proj, f.name)) for f in fields(Projection)))
        return idx, proj, radii, visible

    def _layout(self, camera: Camera) -> _Layout:
        chunk = int(self.cfg.chunk_size)
        return _Layout(int(camera.width), int(camera.height), self.cfg.tile_size, self.cfg.strip_width, chunk, 8 * chunk)

    def _render(
        self, model, camera: Camera, bg: Optional[torch.Tensor], override_color: Optional[torch.Tensor]
    ) -> Dict[str, torch.Tensor]:
        means = model.means
        n = means.shape[0]
        device, dtype = means.device, means.dtype
        width, height = int(camera.width), int(camera.height)
        channels = 3 if override_color is None else override_color.shape[1]
        idx, proj, radii, visible = self._project_visible(model, camera)
        take = lambda x: x.index_select(0, idx)  # noqa: E731
        opacities = torch.sigmoid(take(model.opacity_logits))
        if override_color is not None:
            colors = take(override_color).to(dtype)
        else:
            sh = torch.cat([take(model.sh_dc)[:, None, :], take(model.sh_rest)], dim=1)
            colors = sh_to_color(model.sh_degree, sh, take(means), camera.center.to(device=device, dtype=dtype))
        feats = torch.cat([colors, proj.depths[:, None]], dim=1)  # depth rides along as a channel

        means2d = proj.means2d.new_zeros(n, 2).index_put((idx,), proj.means2d)
        if means2d.requires_grad:
            means2d.retain_grad()
        image, alpha = rasterize(
            take(means2d), proj.conics, opacities, feats, proj.depths,
            width, height, self.cfg.tile_size, self.cfg.strip_width, self.cfg.chunk_size,
        )
        rgb = image[..., :channels]
        if bg is not None:
            rgb = rgb + (1.0 - alpha)[..., None] * bg
        depth = image[..., channels] / alpha.clamp_min(1e-10)
        return {
            "rgb": rgb,
            "depth": depth,
            "alpha": alpha,
            "means2d": means2d,
            "radii": radii,
            "visible": visible,
        }

    @torch.no_grad()
    def pixel_weights(self, model, camera: Camera) -> SparsePixelWeights:
        """One forward pass that keeps w = alpha T of every contributing entry (see
        `SparsePixelWeights`): later splats and gathers of this view need no render."""
        camera = camera.to(model.means.device)
        idx, proj, _, _ = self._project_visible(model, camera)
        opacities = torch.sigmoid(model.opacity_logits.index_select(0, idx))
        layout = self._layout(camera)
        dtype, device = proj.means2d.dtype, proj.means2d.device
        sw = layout.strip_width
        alpha_out = torch.zeros(layout.num_strips, sw, dtype=dtype, device=device)
        log_t_final = torch.zeros_like(alpha_out)
        kept = _composite_all(
            proj.means2d, proj.conics, opacities, proj.means2d.new_zeros(idx.numel(), 0), proj.depths, layout,
            proj.means2d.new_zeros(layout.num_strips, 0), alpha_out, log_t_final,
        )
        gauss = torch.cat([k[0] for k in kept]) if kept else idx.new_zeros(0)
        key = torch.cat([k[1] for k in kept]) if kept else idx.new_zeros(0)
        weights = torch.cat([k[4] * k[5] for k in kept]) if kept else alpha_out.new_zeros(0, sw)
        live = (weights > 0).any(1).nonzero().squeeze(1)
        return SparsePixelWeights(
            idx.index_select(0, gauss.index_select(0, live)), key.index_select(0, live),
            weights.index_select(0, live), layout, model.num_gaussians,
        )
