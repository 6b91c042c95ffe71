"""The `gaussian-model` geometry: a set of 3D Gaussians as an nn.Module (parameters and per-row state).

Parameter layout (N Gaussians, SH degree D, K = (D+1)^2 coefficients):
  means          (N, 3)
  quats          (N, 4)  (w, x, y, z), not necessarily normalised
  log_scales     (N, 3)
  opacity_logits (N,)    opacity = sigmoid(logit)
  sh_dc          (N, 3)     SH coefficient 0 per colour channel
  sh_rest        (N, K-1, 3) SH coefficients 1..K-1 per channel (empty when D = 0)
Per-row state: the buffers listed in `ROW_STATE` (edit mask, generation, source index, trainable
rows, densification statistics, extra PLY properties), one row per Gaussian.

Changing the number or order of rows is the job of `gs_regional.geometry.rows` (keep, append,
duplicate), which updates every parameter, every buffer of `ROW_STATE` and the optimizer's per-row
state together; `gs_regional.geometry.strategy.DensifyStrategy` decides what to clone, split and
prune. Parameters are resized through `param.data` (`set_parameter_rows`), so the nn.Parameter
objects never change and an optimizer built on them stays valid.
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import torch.nn as nn

from gs_regional.geometry.neighbors import knn
from gs_regional.geometry.ply import PlyGaussians, read_ply, write_ply
from gs_regional.registry import register
from gs_regional.utils.base import BaseModule
from gs_regional.utils.io import check_not_overwriting
from gs_regional.utils.sh import rgb_to_sh

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
EDITABLE = "editable"  # trainable-row rule: mask | generation > 0, evaluated at backward time
_ROWS = "rows"  # trainable-row rule: the `trainable` buffer


def set_parameter_rows(param: nn.Parameter, data: torch.Tensor) -> None:
    """Give `param` new data with another number of rows, keeping the Parameter object.

    Assigning `.data` keeps the parameter's gradient accumulator (the autograd node that sums its
    gradient), which recorded the old shape; while any graph that reaches it is still alive (a
    render someone kept), the next backward then fails with "invalid gradient ... expected shape
    compatible with [N_old, ...]". PyTorch drops that node only when the dtype or device changes,
    so an empty tensor of another dtype goes in first; hooks registered on the tensor stay.
    """
    other = torch.float64 if data.dtype != torch.float64 else torch.float32
    param.data = torch.empty(0, dtype=other, device=data.device)
    param.data = data
    param.grad = None


@dataclass(frozen=True)
class RowState:
    """How one per-row buffer behaves when rows are added (see gs_regional.geometry.rows)."""

    dtype: torch.dtype
    fill: Union[bool, int, float]  # value of new Gaussians that are given none (appended rows)
    inherit: bool  # clone/split children copy their parent's value (else they get `fill`)
    columns: Optional[str] = None  # (N, len(model.<columns>)) instead of (N,)


# Every per-row buffer of a GaussianModel. The row operations go through this registry, so a buffer
# added here follows every prune, append and densification (and checkpoint resizing) by itself.
ROW_STATE: Dict[str, RowState] = {
    "mask": RowState(torch.bool, False, inherit=True),  # selected for editing
    "generation": RowState(torch.long, 0, inherit=True),  # 0 = source scene, > 0 = added by an edit
    # The row of the source scene this Gaussian is, or descends from by cloning/splitting; -1 for
    # Gaussians added later (from depth, or appended from elsewhere) and their children. A model
    # built from a file, tensors or points is its own source: source_index = 0..N-1.
    "source_index": RowState(torch.long, -1, inherit=True),
    "trainable": RowState(torch.bool, True, inherit=True),  # explicit trainable rows (set_trainable_mask)
    # densification statistics: summed view-space gradient norms, the number of views they were
    # summed over, the largest screen radius seen; new Gaussians start from zero
    "grad_accum": RowState(torch.float32, 0.0, inherit=False),
    "grad_count": RowState(torch.float32, 0.0, inherit=False),
    "max_radii2d": RowState(torch.float32, 0.0, inherit=False),
    # extra PLY vertex properties (names in `extra_names`; non-zero normals are kept here as nx, ny,
    # nz); they describe the trained Gaussians, so new ones (children included) get 0
    "extras": RowState(torch.float64, 0.0, inherit=False, columns="extra_names"),
}


@dataclass
class LearningRates:
    """Adam learning rates per parameter, those of the original 3DGS trainer."""

    means: float = 1.6e-4  # times the scene extent
    quats: float = 1e-3
    log_scales: float = 5e-3
    opacity_logits: float = 0.05
    sh_dc: float = 2.5e-3
    sh_rest: float = 1.25e-4  # sh_dc / 20


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
        self.extra_names: List[str] = []
        self.extra_dtypes: List[str] = []  # numpy dtype strings, to write extras back unchanged
        for name in ROW_STATE:
            self.register_buffer(name, self.new_row_state(name, n))
        self.source_index = torch.arange(n)  # a new model is its own source
        self.source_path: Optional[str] = None  # the PLY this model was loaded from
        self._trainable_rule: Optional[str] = None  # None, EDITABLE or _ROWS (see set_trainable_mask)
        self._added_only: Tuple[str, ...] = ()  # parameters only added rows train (set_added_only)
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

    def mark_as_source(self) -> None:
        """Make this model the source scene that later rows are tracked against: row i gets
        source_index i (a model built from a file, tensors or points already starts so; a copy
        made with `select` keeps the source rows of the model it was taken from)."""
        self.source_index = torch.arange(self.num_gaussians, device=self.means.device)

    def extra_repr(self) -> str:
        return f"num_gaussians={self.num_gaussians}, sh_degree={self.sh_degree}, masked={int(self.mask.sum())}"

    # ------------------------------------------------------------------ construction
    def _empty_like(self) -> "GaussianModel":
        """A new empty model of the same class and degree that does not load any PLY."""
        cfg = dataclasses.replace(self.cfg, ply=None) if dataclasses.is_dataclass(self.cfg) else None
        other = type(self)(cfg, n=0, sh_degree=self.sh_degree)
        other.extra_names, other.extra_dtypes = list(self.extra_names), list(self.extra_dtypes)
        return other

    def row_state_shape(self, name: str, n: int) -> tuple:
        columns = ROW_STATE[name].columns
        return (n,) if columns is None else (n, len(getattr(self, columns)))

    def new_row_state(self, name: str, n: int, value=None, device=None) -> torch.Tensor:
        """The per-row buffer `name` for n rows: `value` (a scalar or n rows) or the registry's fill."""
        spec = ROW_STATE[name]
        shape = self.row_state_shape(name, n)
        device = self.means.device if device is None else device
        if value is None:
            return torch.full(shape, spec.fill, dtype=spec.dtype, device=device)
        t = torch.as_tensor(value, device=device).to(spec.dtype)
        if t.dim() == 0:
            return t.expand(shape).clone()
        if t.numel() != math.prod(shape):
            raise ValueError(f"GaussianModel: '{name}' for {n} Gaussians must have shape {shape}, got {tuple(t.shape)}")
        return t.reshape(shape).clone()

    def _set_rows(self, params: Mapping[str, torch.Tensor], **state: Optional[torch.Tensor]) -> None:
        """Replace every row (any N, any SH degree) keeping the Parameter objects.

        `state` gives per-row buffers by name (see ROW_STATE); the others get their fill value, and
        `source_index` 0..N-1 (a model built from scratch is its own source).
        """
        unknown = sorted(set(state) - set(ROW_STATE))
        if unknown:
            raise ValueError(f"GaussianModel: unknown per-row state {unknown}; known: {list(ROW_STATE)}")
        means = params["means"]
        n, dev = means.shape[0], means.device
        for name in PARAM_NAMES:
            p = getattr(self, name)
            set_parameter_rows(p, params[name].detach().to(device=dev, dtype=p.dtype).clone())
        self.sh_degree = _degree_from_rest(self.sh_rest.shape[1])
        if state.get("source_index") is None:
            state["source_index"] = torch.arange(n, device=dev)
        for name in ROW_STATE:
            setattr(self, name, self.new_row_state(name, n, state.get(name), device=dev))
        self._check_rows()

    def _check_rows(self) -> None:
        n = self.num_gaussians
        k1 = (self.sh_degree + 1) ** 2 - 1
        expected = {
            "means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,),
            "sh_dc": (n, 3), "sh_rest": (n, k1, 3),
            **{name: self.row_state_shape(name, n) for name in ROW_STATE},
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

    @classmethod
    def from_gaussians(cls, g: PlyGaussians) -> "GaussianModel":
        """A model holding the Gaussians of `g` (e.g. a scene read back by geometry.formats)."""
        model = cls({"sh_degree": 0}, n=0)
        model.load_gaussians(g)
        return model

    def load_ply(self, path, drop_nonfinite: bool = False) -> None:
        """Replace this model's Gaussians by those of a PLY (the file's SH degree wins)."""
        self.load_gaussians(read_ply(path, drop_nonfinite=drop_nonfinite))
        self.source_path = os.path.abspath(os.fspath(path))

    def load_gaussians(self, g: PlyGaussians) -> None:
        """Replace this model's Gaussians by those of `g` (its SH degree wins)."""
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
        # Centred: distances to the 3 nearest points are then exact to float32 far from the origin too.
        d2 = knn(xyz - xyz.mean(0), k=3)[0]
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
        """A detached copy holding the selected rows (bool mask or indices) and all their per-row
        state, e.g. for mask.ply."""
        idx = self._as_index(index_or_bool, "select")
        other = self._empty_like()
        other._set_rows(
            {name: getattr(self, name).detach()[idx] for name in PARAM_NAMES},
            **{name: getattr(self, name)[idx] for name in ROW_STATE},
        )
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

    # ------------------------------------------------------------------ gradient masking
    def set_trainable_mask(self, rows: Union[None, str, torch.Tensor]) -> None:
        """Zero the gradients of every parameter (quats included) outside the trainable rows.

        rows: None removes the masking; "editable" (EDITABLE) means mask | generation > 0,
        evaluated at each backward so it follows prune/append/densify; a bool tensor (N,) fixes
        the rows explicitly (kept in the `trainable` buffer, which follows every row operation:
        appended rows are trainable unless told otherwise, children inherit their parent's flag).
        Saved in checkpoints. Note: Adam still moves rows whose moments are non-zero from earlier steps.
        """
        if isinstance(rows, str):
            if rows != EDITABLE:
                raise ValueError(f"set_trainable_mask: unknown rule '{rows}'; use '{EDITABLE}', a bool tensor or None")
            self._use_trainable_rule(EDITABLE)
        elif rows is None:
            self._use_trainable_rule(None)
        else:
            rows = torch.as_tensor(rows, device=self.means.device)
            if rows.dtype != torch.bool or tuple(rows.shape) != (self.num_gaussians,):
                raise ValueError(f"set_trainable_mask: rows must be a bool tensor of shape ({self.num_gaussians},), got {rows.dtype} {tuple(rows.shape)}")
            self.trainable = rows.clone()
            self._use_trainable_rule(_ROWS)

    def set_added_only(self, names: Sequence[str]) -> None:
        """Of the parameters `names`, only rows the edit added (generation > 0) train: the
        source's rows keep them (on top of the trainable-row rule, which must be set)."""
        unknown = sorted(set(names) - set(PARAM_NAMES))
        if unknown:
            raise ValueError(f"set_added_only: unknown parameters {unknown}; known: {', '.join(PARAM_NAMES)}")
        self._added_only = tuple(names)
        self._use_trainable_rule(self._trainable_rule)

    def _use_trainable_rule(self, rule: Optional[str]) -> None:
        for h in self._grad_hooks:
            h.remove()
        self._grad_hooks = []
        self._trainable_rule = rule
        if rule is not None:
            self._register_grad_hooks()

    def trainable_rows(self) -> Optional[torch.Tensor]:
        """(N,) bool rows whose gradients pass, or None when no masking is set."""
        if self._trainable_rule is None:
            return None
        if self._trainable_rule == EDITABLE:
            return self.editable_rows()
        return self.trainable

    def _register_grad_hooks(self) -> None:
        def make_hook(added_only: bool):
            def hook(grad: torch.Tensor) -> torch.Tensor:
                rows = self.trainable_rows()
                if rows is None:
                    return grad
                if rows.shape[0] != grad.shape[0]:
                    raise RuntimeError(
                        f"trainable rows ({rows.shape[0]}) do not match the {grad.shape[0]} Gaussians; "
                        f"call set_trainable_mask again after changing the model outside gs_regional.geometry.rows"
                    )
                if added_only:
                    rows = rows & (self.generation > 0)
                keep = rows.to(grad.device).view(-1, *[1] * (grad.dim() - 1))
                return grad.masked_fill(~keep, 0)  # masked_fill: a NaN gradient is zeroed too
            return hook

        for name in PARAM_NAMES:
            p = getattr(self, name)
            if p.requires_grad:
                self._grad_hooks.append(p.register_hook(make_hook(name in self._added_only)))

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_grad_hooks"] = []  # hooks live on the tensors; re-registered on unpickle/deepcopy
        return state

    def __setstate__(self, state) -> None:
        super().__setstate__(state)
        if self._trainable_rule is not None:
            self._register_grad_hooks()

    # ------------------------------------------------------------------ checkpoints
    def get_extra_state(self) -> dict:
        return {
            "sh_degree": self.sh_degree,
            "extra_names": list(self.extra_names),
            "extra_dtypes": list(self.extra_dtypes),
            "source_path": self.source_path,
            "trainable_rule": self._trainable_rule,
            "added_only": list(self._added_only),
        }

    def set_extra_state(self, state: dict) -> None:
        # Runs after the buffers are loaded, so the `trainable` rows are already in place.
        self.extra_names = list(state.get("extra_names", []))
        self.extra_dtypes = list(state.get("extra_dtypes", []))
        self.source_path = state.get("source_path")
        rule = state.get("trainable_rule")
        if rule not in (None, EDITABLE, _ROWS):
            raise ValueError(f"GaussianModel checkpoint: unknown trainable-row rule {rule!r}")
        self._added_only = tuple(state.get("added_only", ()))
        self._use_trainable_rule(rule)

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs):
        # The number of Gaussians changes during training: resize every row tensor to the
        # checkpoint's shape first (through .data, so Parameters and optimizers stay valid).
        for name in PARAM_NAMES + tuple(ROW_STATE):
            key = prefix + name
            if key not in state_dict:
                continue
            current = getattr(self, name)
            shape = tuple(state_dict[key].shape)
            if tuple(current.shape) == shape:
                continue
            fresh = torch.zeros(shape, dtype=current.dtype, device=current.device)
            if isinstance(current, nn.Parameter):
                set_parameter_rows(current, fresh)
            else:
                setattr(self, name, fresh)
        try:
            self.sh_degree = _degree_from_rest(self.sh_rest.shape[1])
        except ValueError as e:
            error_msgs.append(f"{prefix}sh_rest: {e}")
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs)

    # ------------------------------------------------------------------ optimisation
    def optimizer_param_groups(
        self, lr: Union[None, LearningRates, Mapping[str, float]] = None, spatial_scale: float = 1.0
    ) -> List[dict]:
        """One param group per parameter, named, with 3DGS learning rates (`LearningRates`, or a
        mapping that overrides some of them). The `means` rate is multiplied by `spatial_scale`
        (the scene extent in 3DGS)."""
        rates = dataclasses.asdict(LearningRates())
        given = dataclasses.asdict(lr) if isinstance(lr, LearningRates) else dict(lr or {})
        unknown = sorted(set(given) - set(PARAM_NAMES))
        if unknown:
            raise ValueError(f"optimizer_param_groups: unknown learning-rate keys {unknown}; allowed: {list(PARAM_NAMES)}")
        rates.update({k: float(v) for k, v in given.items()})
        rates["means"] *= float(spatial_scale)
        return [{"params": [getattr(self, name)], "lr": rates[name], "name": name} for name in PARAM_NAMES]
