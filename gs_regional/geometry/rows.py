"""Row operations on a GaussianModel: the only code that changes the number or order of Gaussians.

Each operation updates, in one place, every parameter, every per-row buffer of the model's registry
(`ROW_STATE`: edit mask, generation, source index, trainable rows, densification statistics, extra
PLY properties) and the optimizer's per-row state (Adam moments), so no per-row array can fall out
of step with the others. A buffer added to `ROW_STATE` follows every operation here by itself.

  keep(model, rows)            keep only these rows (prune, reorder)
  append(model, params, ...)   add new Gaussians at the end (zero optimizer state)
  duplicate(model, parents)    add copies of existing rows (clone/split children): they inherit the
                               per-row state marked `inherit` in ROW_STATE
  split_samples(model, parents) the means and scales of 3DGS's split children
  reset_opacity(model, ...)    3DGS's opacity reset, with its optimizer state

Pass the optimizer (or several, or Lightning's wrapper) to have its per-row state follow.
"""
from __future__ import annotations

from typing import Dict, List, Mapping, Optional, Sequence, Union

import torch
import torch.nn as nn

from gs_regional.geometry.gaussian_model import PARAM_NAMES, ROW_STATE, GaussianModel, set_parameter_rows
from gs_regional.utils.rotations import quat_to_rotmat

Optimizers = Union[None, torch.optim.Optimizer, List[torch.optim.Optimizer]]


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

    Must run before `param.data` is resized: a state tensor is per-row when it has the parameter's
    current shape (Adam's scalar `step` is left alone).
    """
    n = param.shape[0]
    for opt in _unwrap_optimizers(optimizer):
        state = opt.state.get(param)
        if not state:
            continue
        for key, value in list(state.items()):
            if torch.is_tensor(value) and value.dim() > 0 and value.shape[0] == n and value.shape == param.shape:
                state[key] = fn(value)


@torch.no_grad()
def keep(model: GaussianModel, rows: torch.Tensor, optimizer: Optimizers = None) -> int:
    """Keep only the rows where the bool tensor `rows` (N,) is True; returns how many were removed."""
    rows = torch.as_tensor(rows, device=model.means.device)
    if rows.dtype != torch.bool or tuple(rows.shape) != (model.num_gaussians,):
        raise ValueError(f"keep: rows must be a bool tensor of shape ({model.num_gaussians},), got {rows.dtype} {tuple(rows.shape)}")
    idx = rows.nonzero().squeeze(1)
    removed = model.num_gaussians - idx.numel()
    for name in PARAM_NAMES:
        p = getattr(model, name)
        _edit_optimizer_rows(optimizer, p, lambda v: v[idx].clone())
        set_parameter_rows(p, p.data[idx].clone())
    for name in ROW_STATE:
        setattr(model, name, getattr(model, name)[idx].clone())
    return removed


@torch.no_grad()
def _append_rows(model: GaussianModel, params: Mapping[str, torch.Tensor], state: Mapping[str, torch.Tensor],
                 optimizer: Optimizers) -> int:
    """Concatenate m new rows: `params` and `state` hold every parameter and every ROW_STATE buffer."""
    dev = model.means.device
    m = params["means"].shape[0]
    for name in PARAM_NAMES:
        p = getattr(model, name)
        extra = params[name].detach().to(device=dev, dtype=p.dtype)
        _edit_optimizer_rows(optimizer, p, lambda v: torch.cat([v, v.new_zeros((m,) + tuple(v.shape[1:]))], 0))
        set_parameter_rows(p, torch.cat([p.data, extra], 0))
    for name in ROW_STATE:
        old = getattr(model, name)
        setattr(model, name, torch.cat([old, state[name].to(device=old.device, dtype=old.dtype)], 0))
    return m


def append(
    model: GaussianModel,
    params: Union[Mapping[str, torch.Tensor], GaussianModel],
    optimizer: Optimizers = None,
    **state,
) -> int:
    """Add Gaussians at the end; returns how many were added.

    `params` is a dict of the six parameter tensors (sh_rest optional: zeros) or another
    GaussianModel of the same SH degree (its mask, generation and the extras whose names match are
    taken). `state` sets per-row buffers by name (see ROW_STATE; a scalar or one value per row),
    e.g. mask=True, generation=1; the others get their fill value: source_index -1 (these
    Gaussians are not rows of the source scene), trainable True, zero statistics and extras.
    Their optimizer state starts at zero.
    """
    unknown = sorted(set(state) - set(ROW_STATE))
    if unknown:
        raise ValueError(f"append: unknown per-row state {unknown}; known: {list(ROW_STATE)}")
    dev = model.means.device
    if isinstance(params, GaussianModel):
        other = params
        if other.sh_degree != model.sh_degree:
            raise ValueError(f"append: SH degree {other.sh_degree} does not match the model's {model.sh_degree}")
        new = {name: getattr(other, name).detach() for name in PARAM_NAMES}
        for name in ("mask", "generation"):
            if state.get(name) is None:
                state[name] = getattr(other, name)
        if state.get("extras") is None:
            extras = torch.zeros(other.num_gaussians, len(model.extra_names), dtype=torch.float64, device=dev)
            for i, name in enumerate(model.extra_names):
                if name in other.extra_names:
                    extras[:, i] = other.extras[:, other.extra_names.index(name)].to(dev)
            state["extras"] = extras
    else:
        new = GaussianModel._check_new_params(params, model.sh_degree, "append")
    m = new["means"].shape[0]
    rows = {name: model.new_row_state(name, m, state.get(name)) for name in ROW_STATE}
    return _append_rows(model, new, rows, optimizer)


@torch.no_grad()
def duplicate(model: GaussianModel, parents: torch.Tensor, optimizer: Optimizers = None,
              **params: torch.Tensor) -> int:
    """Append one copy of each row in `parents` (indices, repeats allowed): clone/split children.

    A child copies its parent's parameters except those given in `params` (one value per child),
    inherits the per-row state marked `inherit` in ROW_STATE (mask, generation, source index,
    trainable flag) and gets the fill value of the rest (zero statistics and extras).
    Its optimizer state starts at zero.
    """
    unknown = sorted(set(params) - set(PARAM_NAMES))
    if unknown:
        raise ValueError(f"duplicate: unknown parameter names {unknown}; expected some of {list(PARAM_NAMES)}")
    parents = torch.as_tensor(parents, device=model.means.device).long().reshape(-1)
    m = parents.numel()
    new = {name: params[name] if name in params else getattr(model, name).detach()[parents] for name in PARAM_NAMES}
    for name, value in new.items():
        if value.shape[0] != m:
            raise ValueError(f"duplicate: '{name}' has {value.shape[0]} rows for {m} children")
    state = {
        name: getattr(model, name)[parents] if spec.inherit else model.new_row_state(name, m)
        for name, spec in ROW_STATE.items()
    }
    return _append_rows(model, new, state, optimizer)


@torch.no_grad()
def split_samples(model: GaussianModel, parents: torch.Tensor, generator: Optional[torch.Generator] = None) -> Dict[str, torch.Tensor]:
    """Means and log-scales of 3DGS's split: two children per parent (first all first children,
    then all second ones), positions drawn from the parent Gaussian, scales divided by 1.6."""
    dev = model.means.device
    std = model.scales[parents].repeat(2, 1)
    noise = torch.randn(std.shape, generator=generator, device=generator.device if generator is not None else dev)
    samples = noise.to(dev) * std
    rot = quat_to_rotmat(model.quats[parents]).repeat(2, 1, 1)
    return {
        "means": (rot @ samples[..., None])[..., 0] + model.means[parents].repeat(2, 1),
        "log_scales": torch.log(model.scales[parents].repeat(2, 1) / (0.8 * 2)),
    }


@torch.no_grad()
def reset_opacity(model: GaussianModel, value: float = 0.01, optimizer: Optimizers = None,
                  rows: Optional[torch.Tensor] = None) -> None:
    """Clamp opacities to at most `value` (3DGS opacity reset) and zero their optimizer state;
    `rows` (N,) bool limits it to some Gaussians (default: all)."""
    if not 0.0 < value < 1.0:
        raise ValueError(f"reset_opacity: value must be in (0, 1), got {value}")
    rows = torch.ones_like(model.mask) if rows is None else rows
    p = model.opacity_logits
    clamped = torch.minimum(model.opacities, torch.full_like(p, value))
    target = torch.log(clamped / (1 - clamped))  # inverse sigmoid
    _edit_optimizer_rows(optimizer, p, lambda v: v.masked_fill(rows.view(-1, *[1] * (v.dim() - 1)), 0))
    p.data = torch.where(rows, target, p.data)


@torch.no_grad()
def restore(model: GaussianModel, source: GaussianModel, rows: torch.Tensor, names: Sequence[str],
            optimizer: Optimizers = None) -> int:
    """Set the parameters `names` of `rows` (N,) bool back to those of the `source` rows they
    are or descend from (`source_index`; rows the edit added are left alone) and zero their
    optimizer state, so that Adam's moments do not move them on. Returns how many were restored."""
    rows = rows & (model.source_index >= 0)
    if not bool(rows.any()):
        return 0
    index = model.source_index[rows]
    for name in names:
        p = getattr(model, name)
        _edit_optimizer_rows(optimizer, p, lambda v: v.masked_fill(rows.view(-1, *[1] * (v.dim() - 1)), 0))
        p.data[rows] = getattr(source, name).detach().to(p.device)[index]
    return int(rows.sum())


def source_rows(model: GaussianModel, selected: torch.Tensor, n_source: int) -> torch.Tensor:
    """(n_source,) bool: the rows of the source scene that the `selected` Gaussians (N,) are or
    descend from, looked up through their `source_index` (wherever the rows are now)."""
    selected = torch.as_tensor(selected, device=model.means.device)
    if selected.dtype != torch.bool or tuple(selected.shape) != (model.num_gaussians,):
        raise ValueError(f"source_rows: selected must be a bool tensor of shape ({model.num_gaussians},), got {selected.dtype} {tuple(selected.shape)}")
    index = model.source_index[selected]
    index = index[index >= 0]
    if index.numel() and int(index.max()) >= n_source:
        raise ValueError(f"source_rows: source index {int(index.max())} is out of range for a source of {n_source} Gaussians")
    out = torch.zeros(n_source, dtype=torch.bool, device=model.means.device)
    out[index] = True
    return out


def of_source(model: GaussianModel, source_selected: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the rows of `model` that are or descend from the `source_selected` rows of the
    source scene (the inverse of `source_rows`); rows with no source (added ones) are not."""
    src = model.source_index
    return (src >= 0) & source_selected.to(src.device)[src.clamp_min(0)]


@torch.no_grad()
def spare_last_descendants(model: GaussianModel, prune: torch.Tensor, removed: Optional[torch.Tensor] = None) -> torch.Tensor:
    """`prune` (N,) bool without the rows that would leave a source row with no descendant: for
    each source row all of whose rows are pruned or `removed` (e.g. split parents, which their
    children replace), the most opaque of its pruned rows is kept. So an edit never deletes a
    Gaussian of the user's scene by densifying it and then pruning all of what it became."""
    src = model.source_index
    has = src >= 0
    if not bool((prune & has).any()):
        return prune
    size = int(src[has].max()) + 1
    gone = prune | removed if removed is not None else prune
    total = torch.bincount(src[has], minlength=size)
    dropped = torch.bincount(src[has & gone], minlength=size)
    orphaned = (total > 0) & (dropped == total)
    candidates = prune & has & orphaned[src.clamp_min(0)]
    if not bool(candidates.any()):
        return prune
    opacity = model.opacities.detach()
    best = torch.full((size,), -1.0, device=opacity.device, dtype=opacity.dtype)
    best = best.scatter_reduce(0, src[candidates], opacity[candidates], reduce="amax")
    return prune & ~(candidates & (opacity == best[src.clamp_min(0)]))
