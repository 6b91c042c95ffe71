"""`DensifyStrategy`: 3DGS's adaptive density control as a config dataclass (after gsplat's
strategy/default.py). It decides from the densification statistics when and which Gaussians to
clone, split and prune, and when to reset opacities; the row operations that carry its decisions
out (parameters, per-row state and optimizer state together) are in gs_regional.geometry.rows.

Both the `reconstruct` system and the regional edit use it, each with its own settings
(`system.densify`). In a training step:

    out = renderer.render(model, camera)          # out["means2d"] retains its gradient
    loss.backward()
    strategy.collect_stats(model, out, camera, step)
    optimizer.step()
    strategy.refine(model, step, scene_extent, optimizer)   # densify / prune / reset when due

`step` counts what the system schedules by: training steps for `reconstruct`, steps within a
refinement cycle for the regional edit.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional

import torch

from gs_regional.config import ConfigError
from gs_regional.geometry import rows
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.geometry.rows import Optimizers


@dataclass
class DensifyStrategy:
    enabled: bool = True  # false: no statistics, densification, pruning or opacity reset
    start: int = 100  # first step that densifies (statistics are gathered from step 0)
    stop: Optional[int] = 1500  # no densification, statistics or opacity reset from this step on; null: none
    every: Optional[int] = 100  # densify every n steps; null: `rounds` times over the schedule
    # With `every` null: densify this many times, evenly spaced over the schedule that the caller's
    # `last_step` ends (the regional edit: each refinement cycle). Lengthening the schedule then
    # trains longer between the same rounds instead of adding rounds: an edit's targets disagree
    # from view to view, so the gradient that densification reads never settles, and every extra
    # round clones the Gaussians where the views disagree (docs/method.md).
    rounds: int = 1
    # Mean view-space gradient norm above which a Gaussian is cloned or split. In NDC units
    # (pixel gradient x half the image size), as 3DGS's 2e-4: independent of the resolution.
    grad_threshold: float = 0.0002
    percent_dense: float = 0.01  # clone (small) vs split (large) at this fraction of the scene extent
    min_opacity: float = 0.005  # prune below this opacity
    opacity_reset_every: int = 1000  # clamp opacities to 0.01 every n steps; 0: never
    # After the first opacity reset, prune Gaussians wider than this on screen (pixels at the
    # working resolution) or than 0.1 x the scene extent in the world; 0: off.
    max_screen_size: float = 0.0
    max_gaussians: Optional[int] = 200000  # densify no further at this many Gaussians; null: no cap
    budget: Optional[int] = None  # at most this many more Gaussians than when refinement began; null: no cap
    # Densify, prune and reset only Gaussians whose gradients pass (GaussianModel.trainable_rows():
    # the edit's mask and added Gaussians while the rest is frozen); false: every Gaussian.
    only_trainable: bool = True
    # Clone and split children get at least this generation (an edit's 1: they count as Gaussians
    # the edit added, like those from depth, and may be pruned as such); 0: they inherit their parent's.
    child_generation: int = 0
    # Prune only rows of generation > 0 (the ones an edit added): an edit keeps every Gaussian of
    # the user's scene, however transparent (a trained splat holds many near-transparent ones,
    # which the opacity prune of 3DGS's training would delete). False: prune any allowed row.
    prune_only_added: bool = False

    def check(self, where: str = "densify") -> None:
        """Raise a ConfigError naming the key (`where`.<key>) for impossible settings."""
        if self.every is not None and self.every < 1:
            raise ConfigError(f"{where}.every must be >= 1 or null (`rounds` evenly spaced rounds), got {self.every}")
        if self.every is None and self.rounds < 1:
            raise ConfigError(f"{where}.rounds must be >= 1 (densifications over the schedule), got {self.rounds}")
        if self.child_generation < 0:
            raise ConfigError(f"{where}.child_generation must be >= 0, got {self.child_generation}")
        if self.opacity_reset_every < 0:
            raise ConfigError(f"{where}.opacity_reset_every must be >= 0 (0: never), got {self.opacity_reset_every}")
        for key in ("max_gaussians", "budget"):
            value = getattr(self, key)
            if value is not None and value < 0:
                raise ConfigError(f"{where}.{key} must be >= 0 or null, got {value}")

    # ----- schedule ------------------------------------------------------------------------------
    def _before_stop(self, step: int) -> bool:
        return self.stop is None or step < self.stop

    def collects_stats(self, step: int) -> bool:
        return self.enabled and self._before_stop(step)

    def densifies_at(self, step: int, last_step: Optional[int] = None) -> bool:
        """Every `every` steps (or `rounds` times, evenly spaced up to `last_step`) in [start,
        stop), never at step 0 nor at `last_step` (the last step of the system's schedule, whose
        new Gaussians would never be trained)."""
        if self.every is None:
            if last_step is None:
                raise ValueError("DensifyStrategy.every is null: pass last_step, the end of the schedule that `rounds` spans")
            due = step in {(k * (last_step + 1)) // (self.rounds + 1) for k in range(1, self.rounds + 1)}
        else:
            due = step % self.every == 0
        return (
            self.enabled and step > 0 and step >= self.start and self._before_stop(step)
            and due and (last_step is None or step < last_step)
        )

    def resets_opacity_at(self, step: int) -> bool:
        every = self.opacity_reset_every
        return self.enabled and every > 0 and step > 0 and self._before_stop(step) and step % every == 0

    def prunes_large_at(self, step: int) -> bool:
        """Large Gaussians are pruned only after the first opacity reset, as in 3DGS."""
        return self.max_screen_size > 0 and self.opacity_reset_every > 0 and step > self.opacity_reset_every

    def max_count(self, base_count: Optional[int] = None) -> Optional[int]:
        """The cap on the number of Gaussians: `max_gaussians`, and `base_count + budget`."""
        caps = [] if self.max_gaussians is None else [int(self.max_gaussians)]
        if self.budget is not None:
            if base_count is None:
                raise ValueError("DensifyStrategy.budget is set: pass base_count, the number of Gaussians when refinement began")
            caps.append(int(base_count) + int(self.budget))
        return min(caps) if caps else None

    def allowed_rows(self, model: GaussianModel) -> Optional[torch.Tensor]:
        """(N,) bool Gaussians this strategy may change, or None for all."""
        return model.trainable_rows() if self.only_trainable else None

    # ----- the two calls of a training step -------------------------------------------------------
    @torch.no_grad()
    def collect_stats(self, model: GaussianModel, render_out: Dict[str, torch.Tensor], camera, step: int) -> None:
        """After backward: add the view-space gradients of the render `render_out` at `camera`
        (NDC-scaled, like 3DGS's threshold), when the schedule gathers statistics at `step`."""
        grad = render_out["means2d"].grad
        if not self.collects_stats(step) or grad is None:
            return
        ndc = torch.tensor([camera.width / 2.0, camera.height / 2.0], device=grad.device)
        add_gradient_stats(model, grad * ndc, render_out["visible"], render_out.get("radii"))

    @torch.no_grad()
    def refine(
        self,
        model: GaussianModel,
        step: int,
        scene_extent: float,
        optimizer: Optimizers = None,
        last_step: Optional[int] = None,
        base_count: Optional[int] = None,
        generator: Optional[torch.Generator] = None,
        grow: Optional[torch.Tensor] = None,
    ) -> Optional[Dict[str, int]]:
        """After the optimizer step: densify and prune, then reset opacities, when due at `step`.

        Returns the densification report (cloned, split, pruned), or None when none was due.
        `base_count`: the number of Gaussians `budget` counts from. `generator`: for the split samples.
        `grow`: (N,) bool the rows that may be cloned or split (None: every allowed row).
        """
        report = None
        if self.densifies_at(step, last_step):
            report = self.densify_and_prune(
                model, scene_extent, optimizer, max_gaussians=self.max_count(base_count),
                prune_large=self.prunes_large_at(step), generator=generator, grow=grow,
            )
        if self.resets_opacity_at(step):
            rows.reset_opacity(model, optimizer=optimizer, rows=self.allowed_rows(model))
        return report

    # ----- what to clone, split and prune -----------------------------------------------------------
    @torch.no_grad()
    def densify_and_prune(
        self,
        model: GaussianModel,
        scene_extent: float,
        optimizer: Optimizers = None,
        max_gaussians: Optional[int] = None,
        prune_large: bool = False,
        generator: Optional[torch.Generator] = None,
        grow: Optional[torch.Tensor] = None,
    ) -> Dict[str, int]:
        """One densification step of the original 3DGS; returns dict(cloned, split, pruned).

        Gaussians whose mean view-space gradient >= grad_threshold are cloned when small
        (max scale <= percent_dense * scene_extent) or split into 2 samples with scale / 1.6 when
        large; children inherit their parent's mask, generation, source index and trainable flag.
        Then Gaussians with opacity < min_opacity are pruned and, with `prune_large`, those whose
        largest screen radius exceeds max_screen_size or whose world size exceeds 0.1 *
        scene_extent. Only `allowed_rows` are densified or pruned. `max_gaussians`: at most
        max_gaussians - N new Gaussians, highest gradients first. `grow`: (N,) bool, of the allowed
        rows those that may be cloned or split (None: all; pruning is not limited by it).
        Statistics are reset afterwards, as in the original trainer.
        """
        n0 = model.num_gaussians
        dev = model.means.device
        grads = torch.nan_to_num(model.grad_accum / model.grad_count, nan=0.0, posinf=0.0)
        allowed = self.allowed_rows(model)
        if allowed is None:
            allowed = torch.ones(n0, dtype=torch.bool, device=dev)
        max_scale = model.scales.max(dim=1).values if n0 else model.means.new_zeros(0)
        high = (grads >= self.grad_threshold) & allowed & (True if grow is None else grow.to(dev))
        small = max_scale <= self.percent_dense * scene_extent
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
        screen = model.max_radii2d.clone()

        # Clones are exact copies; splits sample 2 positions from the parent Gaussian.
        ci, si = clone_sel.nonzero().squeeze(1), split_sel.nonzero().squeeze(1)
        children = {}
        if si.numel():
            samples = rows.split_samples(model, si, generator)
            children = {name: torch.cat([getattr(model, name).detach()[ci], samples[name]]) for name in samples}
        rows.duplicate(model, torch.cat([ci, si, si]), optimizer, **children)
        n1 = model.num_gaussians
        if self.child_generation > 0:
            model.generation[n0:] = model.generation[n0:].clamp_min(self.child_generation)
        screen = torch.cat([screen, screen.new_zeros(n1 - n0)])

        split_parent = torch.cat([split_sel, torch.zeros(n1 - n0, dtype=torch.bool, device=dev)])
        crit = model.opacities < self.min_opacity
        if prune_large:
            crit |= screen > self.max_screen_size
            crit |= model.scales.max(dim=1).values > 0.1 * scene_extent
        allowed = self.allowed_rows(model)  # children included
        if allowed is not None:
            crit &= allowed
        crit &= ~split_parent
        if self.prune_only_added:
            crit &= model.generation > 0
            crit = rows.spare_last_descendants(model, crit, removed=split_parent)
        rows.keep(model, ~(crit | split_parent), optimizer)
        reset_stats(model)
        return {"cloned": int(ci.numel()), "split": int(si.numel()), "pruned": int(crit.sum())}


@torch.no_grad()
def add_gradient_stats(
    model: GaussianModel, means2d_grad: torch.Tensor, visible: torch.Tensor, radii: Optional[torch.Tensor] = None
) -> None:
    """Accumulate the view-space positional gradient norm of visible Gaussians.

    `means2d_grad` (N, 2) or (V, N, 2) is the gradient of the renderer's `means2d` (in the
    renderer's units; the 3DGS threshold 2e-4 assumes NDC-scaled gradients), `visible` (N,)
    or (V, N) bool, `radii` (N,) or (V, N) screen radii for the max-screen-size prune.
    """
    n = model.num_gaussians
    if means2d_grad is None:
        raise ValueError("add_gradient_stats: means2d has no gradient (call backward first; "
                         "the renderer must retain_grad() on means2d)")
    g = means2d_grad.detach()
    g = g[None] if g.dim() == 2 else g
    if g.dim() != 3 or g.shape[1] != n or g.shape[2] < 2:
        raise ValueError(f"add_gradient_stats: means2d_grad has shape {tuple(means2d_grad.shape)}, expected ({n}, 2) or (V, {n}, 2)")
    vis = torch.as_tensor(visible, device=g.device).bool()
    vis = vis.expand(g.shape[0], n) if vis.dim() == 1 else vis
    if tuple(vis.shape) != (g.shape[0], n):
        raise ValueError(f"add_gradient_stats: visible has shape {tuple(visible.shape)}, expected ({n},) or ({g.shape[0]}, {n})")
    norms = g[..., :2].norm(dim=-1) * vis
    model.grad_accum += norms.sum(0).to(model.grad_accum.dtype)
    model.grad_count += vis.sum(0).to(model.grad_count.dtype)
    if radii is not None:
        r = radii.detach().to(model.max_radii2d.dtype)
        r = r[None] if r.dim() == 1 else r
        model.max_radii2d = torch.maximum(model.max_radii2d, (r * vis).max(0).values)


def reset_stats(model: GaussianModel) -> None:
    model.grad_accum.zero_()
    model.grad_count.zero_()
    model.max_radii2d.zero_()
