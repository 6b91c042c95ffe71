"""The `gaussian-model` geometry: a set of 3D Gaussians as an nn.Module.

Parameter layout (N Gaussians, SH degree D, K = (D+1)^2 coefficients):
  means          (N, 3)
  quats          (N, 4)  (w, x, y, z), not necessarily normalised
  log_scales     (N, 3)
  opacity_logits (N,)    opacity = sigmoid(logit)
  sh_dc          (N, 3)     SH coefficient 0 per colour channel
  sh_rest        (N, K-1, 3) SH coefficients 1..K-1 per channel (empty when D = 0)
Buffers (all resized with the parameters):
  mask           (N,) bool  selected for editing
  generation     (N,) long  0 = original, >0 = added by an edit
  grad_accum     (N,) float densification statistics: summed view-space gradient norms,
  grad_count     (N,) float   the number of views they were summed over,
  max_radii2d    (N,) float   and the largest screen radius seen
  extras         (N, E) float64  extra PLY vertex properties (names in `extra_names`; non-zero
                 normals are kept here as nx, ny, nz), 0 for new Gaussians

Structural operations (prune, append, densify, checkpoint loading) change the number of rows by
assigning `param.data`, so the nn.Parameter objects never change and an optimizer built on them
stays valid; pass the optimizer to have its per-row state (Adam moments) resized along.
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Union

import numpy as np
import torch
import torch.nn as nn

from gs_regional.geometry.ply import PlyGaussians, read_ply, write_ply
from gs_regional.registry import register
from gs_regional.utils.base import BaseModule
from gs_regional.utils.io import check_not_overwriting
from gs_regional.utils.rotations import quat_to_rotmat
from gs_regional.utils.sh import rgb_to_sh

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
ROW_BUFFERS = ("mask", "generation", "grad_accum", "grad_count", "max_radii2d", "extras")
EDITABLE = "editable"  # trainable-row rule: mask | generation > 0, evaluated at backward time

# Learning rates of the original 3DGS trainer; `means` is multiplied by the scene extent.
DEFAULT_LR = {
    "means": 1.6e-4,
    "quats": 1e-3,
    "log_scales": 5e-3,
    "opacity_logits": 0.05,
    "sh_dc": 2.5e-3,
    "sh_rest": 2.5e-3 / 20.0,
}

Optimizers = Union[None, torch.optim.Optimizer, List[torch.optim.Optimizer]]


def _morton_order(points: torch.Tensor) -> torch.Tensor:
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

    order = _morton_order(p)
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


def _inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    return torch.log(x / (1 - x))


def _unwrap_optimizers(optimizer: Optimizers) -> List[torch.optim.Optimizer]:
    opts = optimizer if isinstance(optimizer, (list, tuple)) else [optimizer]
    out = []
    for opt in opts:
        if opt is None:
            continue
        if not isinstance(opt, torch.optim.Optimizer) and hasattr(opt, "optimizer"):
            opt = opt.optimizer  # Lightning's LightningOptimizer wrapper
        out.append(opt)
    return out


def _edit_optimizer_rows(optimizer: Optimizers, param: nn.Parameter, fn) -> None:
    """Apply `fn` to every per-row state tensor (e.g. Adam's exp_avg) of `param`.

    Must run before `param.data` is resized: a state tensor is per-row when its first dimension
    equals the parameter's current row count (Adam's scalar `step` is left alone).
    """
    n = param.shape[0]
    for opt in _unwrap_optimizers(optimizer):
        state = opt.state.get(param)
        if not state:
            continue
        for key, value in list(state.items()):
            if torch.is_tensor(value) and value.dim() > 0 and value.shape[0] == n and value.shape == param.shape:
                state[key] = fn(value)


def _degree_from_rest(k_minus_1: int) -> int:
    degree = int(round(math.sqrt(k_minus_1 + 1))) - 1
    if (degree + 1) ** 2 != k_minus_1 + 1:
        raise ValueError(f"sh_rest has {k_minus_1} coefficients per channel, not (D+1)^2-1 for any degree D")
    return degree


@register("gaussian-model")
class GaussianModel(BaseModule):
    @dataclass
    class Config:
        ply: Optional[str] = None  # load the scene from this INRIA-layout PLY
        sh_degree: int = 3  # for scenes created from points; a PLY's own degree wins
        drop_nonfinite: bool = False  # drop Gaussians with NaN/inf values instead of failing

    def __init__(self, cfg=None, n: int = 0, sh_degree: Optional[int] = None) -> None:
        super().__init__(cfg)
        degree = self.cfg.sh_degree if sh_degree is None else sh_degree
        self.sh_degree = int(degree)
        k = (self.sh_degree + 1) ** 2
        self.means = nn.Parameter(torch.zeros(n, 3))
        self.quats = nn.Parameter(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1))
        self.log_scales = nn.Parameter(torch.zeros(n, 3))
        self.opacity_logits = nn.Parameter(torch.zeros(n))
        self.sh_dc = nn.Parameter(torch.zeros(n, 3))
        self.sh_rest = nn.Parameter(torch.zeros(n, k - 1, 3))
        self.register_buffer("mask", torch.zeros(n, dtype=torch.bool))
        self.register_buffer("generation", torch.zeros(n, dtype=torch.long))
        self.register_buffer("grad_accum", torch.zeros(n))
        self.register_buffer("grad_count", torch.zeros(n))
        self.register_buffer("max_radii2d", torch.zeros(n))
        self.register_buffer("extras", torch.zeros(n, 0, dtype=torch.float64))
        self.extra_names: List[str] = []
        self.extra_dtypes: List[str] = []  # numpy dtype strings, to write extras back unchanged
        self.source_path: Optional[str] = None  # the PLY this model was loaded from
        self._trainable: Union[None, str, torch.Tensor] = None
        self._grad_hooks: list = []
        if self.cfg.ply:
            self.load_ply(self.cfg.ply, drop_nonfinite=self.cfg.drop_nonfinite)

    # ------------------------------------------------------------------ basic properties
    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def num_gaussians(self) -> int:
        return self.means.shape[0]

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def normalized_quats(self) -> torch.Tensor:
        return self.quats / self.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    @property
    def sh(self) -> torch.Tensor:
        """All SH coefficients, (N, K, 3)."""
        return torch.cat([self.sh_dc[:, None, :], self.sh_rest], dim=1)

    def editable_rows(self) -> torch.Tensor:
        """(N,) bool: Gaussians an edit may change, selected (mask) or added (generation > 0)."""
        return self.mask | (self.generation > 0)

    def extra_repr(self) -> str:
        return f"num_gaussians={self.num_gaussians}, sh_degree={self.sh_degree}, masked={int(self.mask.sum())}"

    # ------------------------------------------------------------------ construction
    def _empty_like(self) -> "GaussianModel":
        """A new empty model of the same class and degree that does not load any PLY."""
        cfg = dataclasses.replace(self.cfg, ply=None) if dataclasses.is_dataclass(self.cfg) else None
        other = type(self)(cfg, n=0, sh_degree=self.sh_degree)
        other.extra_names, other.extra_dtypes = list(self.extra_names), list(self.extra_dtypes)
        return other

    def _set_rows(
        self,
        params: Mapping[str, torch.Tensor],
        mask: Optional[torch.Tensor] = None,
        generation: Optional[torch.Tensor] = None,
        extras: Optional[torch.Tensor] = None,
    ) -> None:
        """Replace every row (any N, any SH degree) keeping the Parameter objects."""
        means = params["means"]
        n, dev = means.shape[0], means.device
        for name in PARAM_NAMES:
            p = getattr(self, name)
            p.data = params[name].detach().to(device=dev, dtype=p.dtype).clone()
            p.grad = None
        self.sh_degree = _degree_from_rest(self.sh_rest.shape[1])
        self.mask = torch.zeros(n, dtype=torch.bool, device=dev) if mask is None else mask.to(dev, torch.bool).clone()
        self.generation = (
            torch.zeros(n, dtype=torch.long, device=dev) if generation is None else generation.to(dev, torch.long).clone()
        )
        self.grad_accum = torch.zeros(n, device=dev)
        self.grad_count = torch.zeros(n, device=dev)
        self.max_radii2d = torch.zeros(n, device=dev)
        e = len(self.extra_names)
        self.extras = (
            torch.zeros(n, e, dtype=torch.float64, device=dev) if extras is None else extras.to(dev, torch.float64).clone()
        )
        self._check_rows()

    def _check_rows(self) -> None:
        n = self.num_gaussians
        k1 = (self.sh_degree + 1) ** 2 - 1
        expected = {
            "means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,),
            "sh_dc": (n, 3), "sh_rest": (n, k1, 3), "mask": (n,), "generation": (n,),
            "grad_accum": (n,), "grad_count": (n,), "max_radii2d": (n,), "extras": (n, len(self.extra_names)),
        }
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"GaussianModel: '{name}' has shape {got}, expected {shape}")

    @classmethod
    def from_ply(cls, path, drop_nonfinite: bool = False) -> "GaussianModel":
        """Load an INRIA-layout 3DGS PLY (raises PlyError naming the file on bad input)."""
        model = cls({"sh_degree": 0}, n=0)
        model.load_ply(path, drop_nonfinite=drop_nonfinite)
        return model

    def load_ply(self, path, drop_nonfinite: bool = False) -> None:
        """Replace this model's Gaussians by those of a PLY (the file's SH degree wins)."""
        g = read_ply(path, drop_nonfinite=drop_nonfinite)
        extras = dict(g.extras)
        if g.normals is not None:  # non-zero normals are kept and written back in place
            for i, name in enumerate(("nx", "ny", "nz")):
                extras[name] = g.normals[:, i]
        self.extra_names = list(extras)
        self.extra_dtypes = [np.dtype(a.dtype).str for a in extras.values()]
        extra_t = torch.from_numpy(
            np.stack([a.astype(np.float64) for a in extras.values()], 1)
            if extras
            else np.zeros((g.num_gaussians, 0))
        )
        self._set_rows(
            {
                "means": torch.from_numpy(g.means),
                "quats": torch.from_numpy(g.quats),
                "log_scales": torch.from_numpy(g.log_scales),
                "opacity_logits": torch.from_numpy(g.opacity_logits),
                "sh_dc": torch.from_numpy(g.sh_dc),
                "sh_rest": torch.from_numpy(g.sh_rest),
            },
            extras=extra_t,
        )
        self.source_path = os.path.abspath(os.fspath(path))

    def to_ply_gaussians(self) -> PlyGaussians:
        """The model as numpy arrays in the PLY layout (extras cast back to their file types)."""

        def np32(t: torch.Tensor) -> np.ndarray:
            return t.detach().to("cpu", torch.float32).numpy()

        extras_np = self.extras.detach().cpu().numpy()
        extras = {
            name: extras_np[:, i].astype(np.dtype(dt)) for i, (name, dt) in enumerate(zip(self.extra_names, self.extra_dtypes))
        }
        normals = None
        if all(n in extras for n in ("nx", "ny", "nz")):
            normals = np.stack([extras.pop(n) for n in ("nx", "ny", "nz")], 1).astype(np.float32)
        return PlyGaussians(
            means=np32(self.means),
            sh_dc=np32(self.sh_dc),
            sh_rest=np32(self.sh_rest),
            opacity_logits=np32(self.opacity_logits),
            log_scales=np32(self.log_scales),
            quats=np32(self.quats),
            normals=normals,
            extras=extras,
        )

    def save_ply(self, path) -> None:
        """Write the INRIA PLY layout atomically; never over the PLY this model was loaded from."""
        check_not_overwriting(path, [self.source_path, self.cfg.ply])
        write_ply(path, self.to_ply_gaussians())

    @classmethod
    def from_tensors(
        cls,
        means: torch.Tensor,
        quats: torch.Tensor,
        log_scales: torch.Tensor,
        opacity_logits: torch.Tensor,
        sh_dc: torch.Tensor,
        sh_rest: Optional[torch.Tensor] = None,
        mask: Optional[torch.Tensor] = None,
        generation: Optional[torch.Tensor] = None,
    ) -> "GaussianModel":
        """A model holding copies of the given tensors (on the device of `means`).

        `sh_rest` (N, K-1, 3) sets the SH degree; None means degree 0. `opacity_logits` may be
        (N,) or (N, 1), `sh_dc` (N, 3) or (N, 1, 3).
        """
        n = means.shape[0]
        params = {
            "means": means,
            "quats": quats,
            "log_scales": log_scales,
            "opacity_logits": opacity_logits.reshape(-1) if opacity_logits.dim() == 2 else opacity_logits,
            "sh_dc": sh_dc.reshape(n, 3) if sh_dc.dim() == 3 else sh_dc,
            "sh_rest": sh_rest if sh_rest is not None else means.new_zeros((n, 0, 3)),
        }
        model = cls({"sh_degree": 0}, n=0)
        model._set_rows(
            cls._check_new_params(params, None, "from_tensors"),
            mask=None if mask is None else torch.as_tensor(mask),
            generation=None if generation is None else torch.as_tensor(generation),
        )
        return model

    @staticmethod
    def _check_new_params(params: Mapping[str, torch.Tensor], sh_degree: Optional[int], where: str) -> Dict[str, torch.Tensor]:
        unknown = sorted(set(params) - set(PARAM_NAMES))
        if unknown:
            raise ValueError(f"{where}: unknown parameter names {unknown}; expected {list(PARAM_NAMES)}")
        missing = [p for p in PARAM_NAMES if p not in params and p != "sh_rest"]
        if missing:
            raise ValueError(f"{where}: missing parameters {missing}")
        out = {k: torch.as_tensor(v) for k, v in params.items()}
        m = out["means"].shape[0]
        if "sh_rest" not in out:
            k1 = (sh_degree + 1) ** 2 - 1 if sh_degree is not None else 0
            out["sh_rest"] = out["means"].new_zeros((m, k1, 3))
        k1 = out["sh_rest"].shape[1] if out["sh_rest"].dim() == 3 else -1
        if sh_degree is not None and k1 != (sh_degree + 1) ** 2 - 1:
            raise ValueError(
                f"{where}: sh_rest has shape {tuple(out['sh_rest'].shape)}, expected "
                f"({m}, {(sh_degree + 1) ** 2 - 1}, 3) for SH degree {sh_degree}"
            )
        expected = {
            "means": (m, 3), "quats": (m, 4), "log_scales": (m, 3), "opacity_logits": (m,),
            "sh_dc": (m, 3), "sh_rest": (m, max(k1, 0), 3),
        }
        for name, shape in expected.items():
            if tuple(out[name].shape) != shape:
                raise ValueError(f"{where}: '{name}' has shape {tuple(out[name].shape)}, expected {shape}")
        if k1 >= 0:
            _degree_from_rest(k1)
        return out

    @classmethod
    def from_points(cls, xyz, rgb, sh_degree: int = 3, opacity: float = 0.1) -> "GaussianModel":
        """3DGS initialisation from a coloured point cloud.

        rgb in [0, 1] (uint8 is divided by 255); sh_dc = (rgb - 0.5) / C0, higher SH zero;
        isotropic scale = sqrt(mean squared distance to the 3 nearest neighbours) as in the
        original trainer (clamped at 1e-7 squared); identity rotations; opacity `opacity`.
        """
        xyz = torch.as_tensor(np.asarray(xyz) if not torch.is_tensor(xyz) else xyz)
        rgb = torch.as_tensor(np.asarray(rgb) if not torch.is_tensor(rgb) else rgb)
        if xyz.dim() != 2 or xyz.shape[1] != 3 or xyz.shape[0] == 0:
            raise ValueError(f"from_points: xyz must be (N, 3) with N > 0, got {tuple(xyz.shape)}")
        if tuple(rgb.shape) != tuple(xyz.shape):
            raise ValueError(f"from_points: rgb must be {tuple(xyz.shape)} like xyz, got {tuple(rgb.shape)}")
        rgb = rgb.float() / 255.0 if rgb.dtype == torch.uint8 else rgb.float()
        xyz = xyz.float()
        if not torch.isfinite(xyz).all():
            raise ValueError(f"from_points: {int((~torch.isfinite(xyz)).any(1).sum())} points have NaN/inf coordinates")
        if not 0.0 < opacity < 1.0:
            raise ValueError(f"from_points: opacity must be in (0, 1), got {opacity}")
        n = xyz.shape[0]
        d2 = knn_sq_dists(xyz, k=3)
        if d2.shape[1] == 0:  # a single point has no neighbours
            mean_d2 = xyz.new_full((n,), 1e-4)
        else:
            mean_d2 = d2.mean(1).clamp_min(1e-7)
        k1 = (sh_degree + 1) ** 2 - 1
        params = {
            "means": xyz,
            "quats": torch.tensor([1.0, 0.0, 0.0, 0.0], device=xyz.device).repeat(n, 1),
            "log_scales": torch.log(torch.sqrt(mean_d2))[:, None].repeat(1, 3),
            "opacity_logits": torch.full((n,), math.log(opacity / (1 - opacity)), device=xyz.device),
            "sh_dc": rgb_to_sh(rgb),
            "sh_rest": xyz.new_zeros((n, k1, 3)),
        }
        model = cls({"sh_degree": sh_degree}, n=0)
        model._set_rows(params)
        return model

    def select(self, index_or_bool) -> "GaussianModel":
        """A detached copy holding the selected rows (bool mask or indices), e.g. for mask.ply."""
        idx = self._as_index(index_or_bool, "select")
        other = self._empty_like()
        other._set_rows(
            {name: getattr(self, name).detach()[idx] for name in PARAM_NAMES},
            mask=self.mask[idx],
            generation=self.generation[idx],
            extras=self.extras[idx],
        )
        other.grad_accum = self.grad_accum[idx].clone()
        other.grad_count = self.grad_count[idx].clone()
        other.max_radii2d = self.max_radii2d[idx].clone()
        return other

    def _as_index(self, index_or_bool, where: str) -> torch.Tensor:
        idx = torch.as_tensor(index_or_bool, device=self.means.device)
        if idx.dtype == torch.bool:
            if tuple(idx.shape) != (self.num_gaussians,):
                raise ValueError(f"{where}: boolean mask has shape {tuple(idx.shape)}, expected ({self.num_gaussians},)")
            return idx.nonzero().squeeze(1)
        idx = idx.long().reshape(-1)
        if idx.numel() and (idx.min() < -self.num_gaussians or idx.max() >= self.num_gaussians):
            raise IndexError(f"{where}: index out of range for {self.num_gaussians} Gaussians")
        return idx

    # ------------------------------------------------------------------ structural operations
    def prune(self, keep: torch.Tensor, optimizer: Optimizers = None) -> int:
        """Keep only the rows where `keep` is True; returns how many were removed."""
        keep = torch.as_tensor(keep, device=self.means.device)
        if keep.dtype != torch.bool or tuple(keep.shape) != (self.num_gaussians,):
            raise ValueError(f"prune: keep must be a bool tensor of shape ({self.num_gaussians},), got {keep.dtype} {tuple(keep.shape)}")
        idx = keep.nonzero().squeeze(1)
        removed = self.num_gaussians - idx.numel()
        with torch.no_grad():
            for name in PARAM_NAMES:
                p = getattr(self, name)
                _edit_optimizer_rows(optimizer, p, lambda v: v[idx].clone())
                p.data = p.data[idx].clone()
                p.grad = None
            for name in ROW_BUFFERS:
                setattr(self, name, getattr(self, name)[idx].clone())
            if torch.is_tensor(self._trainable):
                self._trainable = self._trainable.to(idx.device)[idx]
        return removed

    def append(
        self,
        params: Union[Mapping[str, torch.Tensor], "GaussianModel"],
        mask: Union[None, bool, torch.Tensor] = None,
        generation: Union[None, int, torch.Tensor] = None,
        optimizer: Optimizers = None,
        trainable: Union[None, bool, torch.Tensor] = None,
    ) -> int:
        """Add Gaussians at the end; returns how many were added.

        `params` is a dict of the six parameter tensors (sh_rest optional: zeros) or another
        GaussianModel of the same SH degree (its mask, generation and matching extras are taken
        unless `mask`/`generation` are given). New rows get zero densification statistics, zero
        extras, and zero optimizer state. With an explicit trainable-row tensor set (see
        `set_trainable_mask`) new rows are trainable unless `trainable` says otherwise.
        """
        dev = self.means.device
        if isinstance(params, GaussianModel):
            other = params
            if other.sh_degree != self.sh_degree:
                raise ValueError(f"append: SH degree {other.sh_degree} does not match the model's {self.sh_degree}")
            new = {name: getattr(other, name).detach() for name in PARAM_NAMES}
            mask = other.mask if mask is None else mask
            generation = other.generation if generation is None else generation
            new_extras = torch.zeros(other.num_gaussians, len(self.extra_names), dtype=torch.float64, device=dev)
            for i, name in enumerate(self.extra_names):
                if name in other.extra_names:
                    new_extras[:, i] = other.extras[:, other.extra_names.index(name)].to(dev)
        else:
            new = self._check_new_params(params, self.sh_degree, "append")
            new_extras = None
        m = new["means"].shape[0]
        if new_extras is None:
            new_extras = torch.zeros(m, len(self.extra_names), dtype=torch.float64, device=dev)

        def rows(value, dtype, default):
            if value is None:
                value = default
            t = torch.as_tensor(value, device=dev).to(dtype)
            return t.expand(m).clone() if t.dim() == 0 else t.reshape(m).clone()

        buffers = {
            "mask": rows(mask, torch.bool, False),
            "generation": rows(generation, torch.long, 0),
            "grad_accum": torch.zeros(m, device=dev),
            "grad_count": torch.zeros(m, device=dev),
            "max_radii2d": torch.zeros(m, device=dev),
            "extras": new_extras,
        }
        with torch.no_grad():
            for name in PARAM_NAMES:
                p = getattr(self, name)
                extra = new[name].detach().to(device=dev, dtype=p.dtype)
                _edit_optimizer_rows(
                    optimizer, p, lambda v: torch.cat([v, v.new_zeros((m,) + tuple(v.shape[1:]))], 0)
                )
                p.data = torch.cat([p.data, extra], 0)
                p.grad = None
            for name in ROW_BUFFERS:
                old = getattr(self, name)
                setattr(self, name, torch.cat([old, buffers[name].to(old.dtype)], 0))
            if torch.is_tensor(self._trainable):
                self._trainable = torch.cat([self._trainable.to(dev), rows(trainable, torch.bool, True)])
        return m

    # ------------------------------------------------------------------ densification (3DGS)
    @torch.no_grad()
    def add_densification_stats(
        self, means2d_grad: torch.Tensor, visible: torch.Tensor, radii: Optional[torch.Tensor] = None
    ) -> None:
        """Accumulate the view-space positional gradient norm of visible Gaussians.

        `means2d_grad` (N, 2) or (V, N, 2) is the gradient of the renderer's `means2d` (in the
        renderer's units; the 3DGS threshold 2e-4 assumes NDC-scaled gradients), `visible` (N,)
        or (V, N) bool, `radii` (N,) or (V, N) screen radii for the max-screen-size prune.
        """
        n = self.num_gaussians
        if means2d_grad is None:
            raise ValueError("add_densification_stats: means2d has no gradient (call backward first; "
                             "the renderer must retain_grad() on means2d)")
        g = means2d_grad.detach()
        g = g[None] if g.dim() == 2 else g
        if g.dim() != 3 or g.shape[1] != n or g.shape[2] < 2:
            raise ValueError(f"add_densification_stats: means2d_grad has shape {tuple(means2d_grad.shape)}, expected ({n}, 2) or (V, {n}, 2)")
        vis = torch.as_tensor(visible, device=g.device).bool()
        vis = vis.expand(g.shape[0], n) if vis.dim() == 1 else vis
        if tuple(vis.shape) != (g.shape[0], n):
            raise ValueError(f"add_densification_stats: visible has shape {tuple(visible.shape)}, expected ({n},) or ({g.shape[0]}, {n})")
        norms = g[..., :2].norm(dim=-1) * vis
        self.grad_accum += norms.sum(0).to(self.grad_accum.dtype)
        self.grad_count += vis.sum(0).to(self.grad_count.dtype)
        if radii is not None:
            r = radii.detach().to(self.max_radii2d.dtype)
            r = r[None] if r.dim() == 1 else r
            self.max_radii2d = torch.maximum(self.max_radii2d, (r * vis).max(0).values)

    def reset_densification_stats(self) -> None:
        self.grad_accum.zero_()
        self.grad_count.zero_()
        self.max_radii2d.zero_()

    def densify_and_prune(
        self,
        grad_threshold: float,
        scene_extent: float,
        percent_dense: float = 0.01,
        min_opacity: float = 0.005,
        max_screen_size: Optional[float] = None,
        radii: Optional[torch.Tensor] = None,
        only_mask: bool = False,
        max_gaussians: Optional[int] = None,
        optimizer: Optimizers = None,
        generator: Optional[torch.Generator] = None,
    ) -> Dict[str, int]:
        """One densification step of the original 3DGS; returns dict(cloned, split, pruned).

        Gaussians whose mean view-space gradient >= grad_threshold are cloned when small
        (max scale <= percent_dense * scene_extent) or split into 2 samples with scale / 1.6
        when large. New Gaussians inherit mask and generation. Then Gaussians with opacity
        < min_opacity are pruned and, when max_screen_size is set, those whose screen radius
        (tracked maximum, or `radii`) exceeds it or whose world size exceeds 0.1 * scene_extent.
        `only_mask`: only editable rows (mask | generation > 0) are densified or pruned.
        `max_gaussians`: at most max_gaussians - N new Gaussians, highest gradients first.
        Statistics are reset afterwards, as in the original trainer.
        """
        n0 = self.num_gaussians
        dev = self.means.device
        with torch.no_grad():
            grads = self.grad_accum / self.grad_count
            grads = torch.nan_to_num(grads, nan=0.0, posinf=0.0)
            allowed = self.editable_rows() if only_mask else torch.ones(n0, dtype=torch.bool, device=dev)
            max_scale = self.scales.max(dim=1).values if n0 else self.means.new_zeros(0)
            high = (grads >= grad_threshold) & allowed
            small = max_scale <= percent_dense * scene_extent
            clone_sel, split_sel = high & small, high & ~small
            if max_gaussians is not None:
                budget = max(0, int(max_gaussians) - n0)
                cand = (clone_sel | split_sel).nonzero().squeeze(1)
                if cand.numel() > budget:
                    top = cand[torch.argsort(grads[cand], descending=True, stable=True)[:budget]]
                    chosen = torch.zeros(n0, dtype=torch.bool, device=dev)
                    chosen[top] = True
                    clone_sel &= chosen
                    split_sel &= chosen
            screen = self.max_radii2d.clone()
            if radii is not None and n0:
                screen = torch.maximum(screen, radii.detach().to(screen.dtype).reshape(-1, n0).max(0).values)

            # Clones are exact copies; splits sample 2 positions from the parent Gaussian.
            ci, si = clone_sel.nonzero().squeeze(1), split_sel.nonzero().squeeze(1)
            src = torch.cat([ci, si, si])
            new = {name: getattr(self, name).detach()[src].clone() for name in PARAM_NAMES}
            ns = si.numel()
            if ns:
                std = self.scales[si].repeat(2, 1)
                noise = torch.randn(std.shape, generator=generator, device=generator.device if generator is not None else dev)
                samples = noise.to(dev) * std
                rot = quat_to_rotmat(self.quats[si]).repeat(2, 1, 1)
                new["means"][ci.numel():] = (rot @ samples[..., None])[..., 0] + self.means[si].repeat(2, 1)
                new["log_scales"][ci.numel():] = torch.log(self.scales[si].repeat(2, 1) / (0.8 * 2))
            trainable_new = self._trainable.to(dev)[src] if torch.is_tensor(self._trainable) else None
            self.append(new, mask=self.mask[src], generation=self.generation[src], optimizer=optimizer,
                        trainable=trainable_new)
            n1 = self.num_gaussians
            screen = torch.cat([screen, screen.new_zeros(n1 - n0)])

            split_parent = torch.cat([split_sel, torch.zeros(n1 - n0, dtype=torch.bool, device=dev)])
            crit = self.opacities < min_opacity
            if max_screen_size:
                crit |= screen > max_screen_size
                crit |= self.scales.max(dim=1).values > 0.1 * scene_extent
            if only_mask:
                crit &= self.editable_rows()
            crit &= ~split_parent
            self.prune(~(crit | split_parent), optimizer=optimizer)
            self.reset_densification_stats()
        return {"cloned": int(ci.numel()), "split": int(ns), "pruned": int(crit.sum())}

    @torch.no_grad()
    def reset_opacity(self, value: float = 0.01, optimizer: Optimizers = None, only_mask: bool = False) -> None:
        """Clamp opacities to at most `value` (3DGS opacity reset) and zero their optimizer state.

        `only_mask`: only editable rows (mask | generation > 0) are reset.
        """
        if not 0.0 < value < 1.0:
            raise ValueError(f"reset_opacity: value must be in (0, 1), got {value}")
        rows = self.editable_rows() if only_mask else torch.ones_like(self.mask)
        p = self.opacity_logits
        target = _inverse_sigmoid(torch.minimum(self.opacities, torch.full_like(p, value)))
        _edit_optimizer_rows(optimizer, p, lambda v: v.masked_fill(rows.view(-1, *[1] * (v.dim() - 1)), 0))
        p.data = torch.where(rows, target, p.data)

    # ------------------------------------------------------------------ gradient masking
    def set_trainable_mask(self, rows: Union[None, str, torch.Tensor]) -> None:
        """Zero the gradients of every parameter (quats included) outside the trainable rows.

        rows: None removes the masking; "editable" (EDITABLE) means mask | generation > 0,
        evaluated at each backward so it follows prune/append/densify; a bool tensor (N,) fixes
        the rows explicitly (pruned along, new rows trainable, see `append`). Saved in the
        state dict. Note: Adam still moves rows whose moments are non-zero from earlier steps.
        """
        for h in self._grad_hooks:
            h.remove()
        self._grad_hooks = []
        if rows is None:
            self._trainable = None
            return
        if isinstance(rows, str):
            if rows != EDITABLE:
                raise ValueError(f"set_trainable_mask: unknown rule '{rows}'; use '{EDITABLE}', a bool tensor or None")
            self._trainable = rows
        else:
            rows = torch.as_tensor(rows, device=self.means.device)
            if rows.dtype != torch.bool or tuple(rows.shape) != (self.num_gaussians,):
                raise ValueError(f"set_trainable_mask: rows must be a bool tensor of shape ({self.num_gaussians},), got {rows.dtype} {tuple(rows.shape)}")
            self._trainable = rows.clone()
        self._register_grad_hooks()

    def trainable_rows(self) -> Optional[torch.Tensor]:
        """(N,) bool rows whose gradients pass, or None when no masking is set."""
        if self._trainable is None:
            return None
        if isinstance(self._trainable, str):
            return self.editable_rows()
        return self._trainable

    def _register_grad_hooks(self) -> None:
        def hook(grad: torch.Tensor) -> torch.Tensor:
            rows = self.trainable_rows()
            if rows is None:
                return grad
            if rows.shape[0] != grad.shape[0]:
                raise RuntimeError(
                    f"trainable rows ({rows.shape[0]}) do not match the {grad.shape[0]} Gaussians; "
                    f"call set_trainable_mask again after changing the model outside prune/append"
                )
            keep = rows.to(grad.device).view(-1, *[1] * (grad.dim() - 1))
            return grad.masked_fill(~keep, 0)  # masked_fill: a NaN gradient is zeroed too

        for name in PARAM_NAMES:
            p = getattr(self, name)
            if p.requires_grad:
                self._grad_hooks.append(p.register_hook(hook))

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_grad_hooks"] = []  # hooks live on the tensors; re-registered on unpickle/deepcopy
        return state

    def __setstate__(self, state) -> None:
        super().__setstate__(state)
        if self._trainable is not None:
            self._register_grad_hooks()

    # ------------------------------------------------------------------ checkpoints
    def get_extra_state(self) -> dict:
        trainable = self._trainable.cpu() if torch.is_tensor(self._trainable) else self._trainable
        return {
            "sh_degree": self.sh_degree,
            "extra_names": list(self.extra_names),
            "extra_dtypes": list(self.extra_dtypes),
            "source_path": self.source_path,
            "trainable": trainable,
        }

    def set_extra_state(self, state: dict) -> None:
        self.extra_names = list(state.get("extra_names", []))
        self.extra_dtypes = list(state.get("extra_dtypes", []))
        self.source_path = state.get("source_path")
        trainable = state.get("trainable")
        self.set_trainable_mask(trainable.to(self.means.device) if torch.is_tensor(trainable) else trainable)

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs):
        # The number of Gaussians changes during training: resize every row tensor to the
        # checkpoint's shape first (through .data, so Parameters and optimizers stay valid).
        for name in PARAM_NAMES + ROW_BUFFERS:
            key = prefix + name
            if key not in state_dict:
                continue
            current = getattr(self, name)
            shape = tuple(state_dict[key].shape)
            if tuple(current.shape) == shape:
                continue
            fresh = torch.zeros(shape, dtype=current.dtype, device=current.device)
            if isinstance(current, nn.Parameter):
                current.data = fresh
                current.grad = None
            else:
                setattr(self, name, fresh)
        try:
            self.sh_degree = _degree_from_rest(self.sh_rest.shape[1])
        except ValueError as e:
            error_msgs.append(f"{prefix}sh_rest: {e}")
        if torch.is_tensor(self._trainable) and self._trainable.shape[0] != self.num_gaussians:
            self._trainable = None  # explicit rows of another size; the extra state restores them
            self.set_trainable_mask(None)
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs)

    # ------------------------------------------------------------------ optimisation
    def optimizer_param_groups(self, lr: Optional[Mapping[str, float]] = None, spatial_scale: float = 1.0) -> List[dict]:
        """One param group per parameter, named, with 3DGS learning rates (overridable).

        The `means` rate is multiplied by `spatial_scale` (the scene extent in 3DGS).
        """
        rates = dict(DEFAULT_LR)
        given = dict(lr or {})
        unknown = sorted(set(given) - set(PARAM_NAMES))
        if unknown:
            raise ValueError(f"optimizer_param_groups: unknown learning-rate keys {unknown}; allowed: {list(PARAM_NAMES)}")
        rates.update({k: float(v) for k, v in given.items()})
        rates["means"] *= float(spatial_scale)
        return [{"params": [getattr(self, name)], "lr": rates[name], "name": name} for name in PARAM_NAMES]
