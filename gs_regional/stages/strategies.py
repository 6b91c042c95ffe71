"""§3.3's two kinds of edit as strategies (as `geometry/strategy.py` does for densification): a
`Recolour` changes the colours of the localized Gaussians (and paints an object no view's depth
showed); an `Addition` adds
Gaussians (from depth, by densification) and leaves the source's where they are. The system
(`systems/regional_edit.py`) runs the schedule, localize -> initialize -> refinement cycles ->
finish, and asks the strategy chosen after initialization (`choose_strategy`):

* `start_timestep(cycle)`: where each cycle's partial edits start from;
* `cycle_views(system, cycle, frontal, near)`: the views a cycle edits (a recolour's later cycles
  go where the part is still unedited);
* `first_view_is_target(m)`: whether the first cycle trains on the first view's full edit;
* `target(system, view, edited)`: the view's training target (the composite);
* `set_trainable(geometry, param_groups)`: which rows and parameters train, at what rates;
* `densify`: the densification strategy of refinement (None: no Gaussian added);
* `after_edits(system)`: what follows each cycle's edits (the recolour's gate, its pixel weights for
  training, its colour step where the cycle's steps fall short and its paint of an object no depth
  showed; the addition's fill from the cycle's depth);
* `finish(system)`: the last word after refinement;
* `state_dict()` / `load_state_dict()` / `to(device)`: what it keeps in a checkpoint.
"""
from __future__ import annotations

import logging
from itertools import islice
from dataclasses import dataclass, field
from typing import Any, ClassVar, Dict, List, Optional, Tuple

import torch

from gs_regional.config import ConfigError, need
from gs_regional.stages.change import NOISE_SIGMAS, edit_blend
from gs_regional.stages.composite import (
    ADDITION_MARGIN_PX, FULL_COVERAGE, MIN_OBJECT_BLEND, composite_target, distinct_parts, outlying_pieces, part_colours,
    recoloured, still_distinct,
)
from gs_regional.geometry import neighbors, rows
from gs_regional.geometry.strategy import DensifyStrategy
from gs_regional.metrics.region import SEEN_MIN_WEIGHT, render_selection
from gs_regional.stages.views import nearest_cameras, spread_subset
from gs_regional.utils.sh import SH_C0, sh_to_rgb

log = logging.getLogger(__name__)

SHAPE_FREE_PARAMS = ("sh_dc", "sh_rest")  # what a recolour trains (no change of shape found)
# A recolour trains colours at this multiple of their learning rate: 3DGS's rates are made for 30k
# steps, and a recolour moves colours far in a few hundred (more costs the surroundings the spill
# the gate lets through).
RECOLOUR_LR_SCALE = 9.0
# An addition moves the Gaussians it added at this multiple of the position learning rate: placed
# from one view's depth and edit, a pixel or two off, they must move further than 3DGS's rate
# carries them in a cycle's tens of steps.
ADDED_POSITION_LR_SCALE = 3.0
# The recolour gate's minimum is `min_edit_blend` times the blend this quantile of the seen
# selected Gaussians reaches: a part a few pixels across is all edge, and even its own Gaussians
# take under half of the edit's nearby colour.
GATE_REFERENCE_QUANTILE = 0.99
# A selected Gaussian recoloured by less than this whose source colour lies well outside those of
# the Gaussians recoloured by more is a part of its own (eyes in a recoloured head) and keeps its
# source colours.
DISTINCT_PART_BLEND = 0.85

# A pixel of a recolour's targets counts in training as much as the editor recoloured it there
# (its `edit_blend`), plus this floor: the editor places its colour a pixel or two off in each view,
# so a part a few pixels across is recoloured in some views and shows its source colour in others;
# counted alike, its Gaussians learn the average (a third to two thirds of the way to the new
# colour), weighted they learn the views that recolour them. The gate still decides which Gaussians train.
RECOLOURED_PIXEL_FLOOR = 0.05

# A Gaussian found a part of its own in an earlier cycle stays one while its colour lies this far
# (RGB) from the part's median colour (`still_distinct`): an enclosed part (a head's eyes, 0.7-0.9
# away) stays out of the edit when later cycles widen the part's colours; a part's other shading
# (0.3-0.4 away), found distinct while the first cycles saw one side, is released.
STILL_DISTINCT = 0.5
# A connected piece of a recolour's selection (each Gaussian joined to its GATE_NEIGHBOURS nearest)
# whose share of fully recoloured Gaussians is under OUTLYING_PIECE_SHARE times the whole selection's
# is no part of the part (`outlying_pieces`): the rim of what stands in front of it.
GATE_NEIGHBOURS = 16
OUTLYING_PIECE_SHARE = 0.5
# A Gaussian inside those the recolour gate lets train, recoloured fully (its blend at least
# FULLY_RECOLOURED), that a cycle's views see less than LITTLE_SEEN times the median of those gets
# its colours from the cycle's targets in one step (`Recolour.little_seen_inside`).
LITTLE_SEEN = 1.0
FULLY_RECOLOURED = 0.85

# A later cycle of a recolour starts at the training view in which the selected Gaussians no
# edited view has seen well yet (`Recolour.poorly_seen`) cover the most, when they cover at least
# this fraction of its pixels: a part seen from every side (a donut's dough) was otherwise edited
# from one side only. Below it (a thin part's hidden side, seen edge-on) the edit's jitter there
# spills onto the neighbours more than it adds. When the unseen Gaussians are at least
# UNEDITED_MIN_SHARE of the selected ones a training view sees (a body seen from the front, its
# back and sides left at their source colours: half of the part's error), a view they cover
# UNEDITED_MIN_SHARE_AREA of is enough: the side they make up matters more than another cycle on
# the sides already edited.
UNEDITED_MIN_AREA = 0.04
UNEDITED_MIN_SHARE = 0.3
UNEDITED_MIN_SHARE_AREA = 0.01
UNEDITED_CANDIDATES = 32  # training views looked at (spread over them)
# A selected Gaussian is seen well once the edited views, all together, have seen it this many
# times as much as the one training view that sees it best (`Recolour.poorly_seen`).
WELL_SEEN = 1.0
# The recolour gate's blend counts each earlier cycle's votes at this weight once a cycle adds its
# own (halved again with every later cycle). A later cycle's targets are the editor's more settled
# answer: partial denoising from a lower timestep of renders that already carry the edit, with less
# of the full edit's jitter. The first cycle's edits of a thin part land beside it (713359 c31, a donut
# icing segment: its true Gaussians' blend a median 0.15-0.54 in the first cycle's views, 0.8-0.9 in
# the later ones), and counted as much as the later ones they declined 4 in 10 of the part.
EARLIER_CYCLES_WEIGHT = 0.5

# A recolour whose edited views recolour the median seen selected Gaussian by less than this is an
# object added on the part that no view's depth showed (a small ball at 64²): its later cycles paint
# what their targets show and the scene lacks (`Recolour.paints_object`). Recolours of the part itself
# recolour most of their selection (the gate's median blend 0.50-0.78 over their cycles on fresh
# 912345's recolours), such additions next to none of it (0.00-0.07: the part lies mostly beside the
# object, or its Gaussians are larger than the object).
SMALL_OBJECT_BLEND = 0.25
# A cycle edits views in which the edit's Gaussians (an addition's added rows, a recolour's
# selection) cover at least this many pixels (`views_that_see`): a view that sees none of them
# edits none of them.
SEEN_PX = 1.0

# An edit whose depth shows a change of shape on fewer pixels than this while its first full edit
# recolours the region beside them (`refine.min_recoloured_fraction`) is a recolour: a monocular
# depth estimator answers a recoloured part's edge with a few pixels of changed depth. Trained as
# an addition (colours at the 3DGS rate, ungated), such recolours came out half done
# (docs/method.md, "Recolour or change of shape").
MIN_SHAPE_PIXELS = 5

# Keys that became named constants: {key: (constant, module)}.
_CONSTANTS = {
    "composite_dilate": ("ADDITION_MARGIN_PX", "composite"), "composite_noise_sigmas": ("NOISE_SIGMAS", "change"),
    "composite_min_blend": ("MIN_OBJECT_BLEND", "composite"), "composite_full_coverage": ("FULL_COVERAGE", "composite"),
    "gate_reference_quantile": ("GATE_REFERENCE_QUANTILE", "strategies"),
    "distinct_part_blend": ("DISTINCT_PART_BLEND", "strategies"), "recolour_lr_scale": ("RECOLOUR_LR_SCALE", "strategies"),
    "added_position_lr_scale": ("ADDED_POSITION_LR_SCALE", "strategies"),
}


@dataclass
class RefineConfig:
    """`system.refine` (§3.3; docs/method.md "Refine")."""

    MOVED_KEYS: ClassVar[Dict[str, str]] = {
        "densify": "system.densify.enabled", "densify_every": "system.densify.every",
        "grad_threshold": "system.densify.grad_threshold", "densify_budget": "system.densify.budget",
        "constant_t": "system.ablation.constant_t", "optimize_all": "system.ablation.optimize_all",
        "composite": "system.ablation.composite",
    }
    REMOVED_KEYS: ClassVar[Dict[str, str]] = {
        **{key: "an addition's first cycle trains on the first view's neighbours (on its full edit when m = 0), a "
                "recolour's on the full edit too; remove the key" for key in ("first_cycle_first_view", "reedit_first_view")},
        "next_frontal": "each later cycle's frontal view is the edited view with the most unedited neighbours; remove the key",
        **{key: "a recolour's colours start at the source's and train; remove the key"
           for key in ("recolour_from_edits", "recolour_start_min_blend")},
        **{key: f"it is the constant {name} of gs_regional/stages/{module}.py now; remove the key"
           for key, (name, module) in _CONSTANTS.items()},
    }
    # The values a removed key had to have for an older checkpoint to resume as the method now runs.
    RETIRED_VALUES: ClassVar[Dict[str, object]] = {
        "first_cycle_first_view": "skip", "next_frontal": "frontier", "recolour_from_edits": False,
        "composite_dilate": ADDITION_MARGIN_PX, "composite_noise_sigmas": NOISE_SIGMAS,
        "composite_min_blend": MIN_OBJECT_BLEND, "composite_full_coverage": FULL_COVERAGE,
        "gate_reference_quantile": GATE_REFERENCE_QUANTILE, "distinct_part_blend": DISTINCT_PART_BLEND,
        "recolour_lr_scale": RECOLOUR_LR_SCALE, "added_position_lr_scale": ADDED_POSITION_LR_SCALE,
    }
    cycles: int = 3
    t_schedule: List[int] = field(default_factory=lambda: [750, 500, 250])  # a recolour's start timestep per cycle
    # An edit that may change the shape (an addition) starts from less noise: each partial denoise
    # regenerates what the render shows, and from less noise it keeps the new geometry's sharpness
    # instead of redrawing it in every view. null: `t_schedule`.
    shape_t_schedule: Optional[List[int]] = field(default_factory=lambda: [450, 350, 250])
    iterations_per_cycle: int = 500
    # The cycle length the learning rates are set for: a longer cycle trains at rates scaled by
    # rate_iterations / iterations_per_cycle, so that it moves the scene as far as this many steps
    # would. The views' targets disagree (the editor draws each a little differently), and a cycle
    # at full rates for longer fits that disagreement further: the added Gaussians drift off the
    # object and the selection's rim takes the spill (docs/method.md, "Refine"). A shorter cycle
    # keeps the rates.
    rate_iterations: int = 500
    m: int = 20  # nearest cameras edited around the cycle's frontal view
    # The parameters of the selected source Gaussians that an addition leaves as they were: only the
    # Gaussians the edit added train them (free, the region's Gaussians grow over their neighbours
    # and follow every view's jittered target). [] frees them all (an edit that must move or
    # remove source geometry).
    source_fixed: List[str] = field(default_factory=lambda: ["means", "quats", "log_scales", "opacity_logits"])
    # An addition leaves the selected source Gaussians their colours too when the first edited view
    # recolours less than this fraction of the region beside what was added (metrics.json
    # `init.recoloured_fraction`): free colours would only learn each view's jittered copy of the
    # new object. 0: the source's colours always train.
    min_recoloured_fraction: float = 0.3
    # A recolour's selected Gaussian takes the edit only while the edited views recolour it: its
    # rendering-weighted mean `edit_blend` over the views edited so far must reach this (relative to
    # the best-recoloured ones, GATE_REFERENCE_QUANTILE), or it keeps its source colours: the
    # selection's rim past the part would learn the editor's bleed. 0 lets every selected Gaussian train.
    min_edit_blend: float = 0.5
    # After the last cycle, Gaussians the edit added that contribute nothing are removed: total
    # rendered weight over the training views below `prune_min_weight` (pixels) or opacity below
    # `prune_min_opacity`.
    prune_added: bool = True
    prune_min_weight: float = 1.0
    prune_min_opacity: float = 0.005
    # Views each training step trains on, shared out over the processes of a run on several devices
    # (systems/parallel.py). A number gives the same edit on any number of processes; null: one
    # view per process (N devices train on N views a step in the time of one).
    views_per_step: Optional[int] = 1

    @property
    def rate_factor(self) -> float:
        """What refinement's learning rates are multiplied by (`rate_iterations`)."""
        return min(1.0, self.rate_iterations / self.iterations_per_cycle)

    def check(self, where: str = "system.refine", num_train_timesteps: int = 1000, constant_t: Optional[int] = None) -> None:
        need(self.cycles >= 1, f"{where}.cycles", "an integer >= 1", self.cycles)
        need(self.iterations_per_cycle >= 1, f"{where}.iterations_per_cycle", "an integer >= 1", self.iterations_per_cycle)
        need(self.rate_iterations >= 1, f"{where}.rate_iterations", "an integer >= 1", self.rate_iterations)
        need(self.m >= 0, f"{where}.m", "an integer >= 0 (views edited around each cycle's frontal view)", self.m)
        need(0 <= self.min_recoloured_fraction <= 1, f"{where}.min_recoloured_fraction", "a number in [0, 1]",
             self.min_recoloured_fraction)
        need(0 <= self.min_edit_blend <= 1, f"{where}.min_edit_blend", "a number in [0, 1]", self.min_edit_blend)
        need(self.views_per_step is None or self.views_per_step >= 1, f"{where}.views_per_step",
             "an integer >= 1 or null (one per process)", self.views_per_step)
        if constant_t is not None:  # system.ablation.constant_t replaces both schedules
            return
        for key in ("t_schedule", "shape_t_schedule"):
            if getattr(self, key) is None:  # shape_t_schedule only: t_schedule then serves every edit
                continue
            t = list(getattr(self, key))
            if len(t) < self.cycles:
                raise ConfigError(f"{where}.{key} has {len(t)} timesteps for {self.cycles} cycles; "
                                  f"give one start timestep per cycle")
            n = num_train_timesteps
            need(all(0 <= x < n for x in t), f"{where}.{key}", f"timesteps in [0, {n - 1}]", t)
            need(all(a >= b for a, b in zip(t, t[1:])), f"{where}.{key}",
                 "non-increasing (each cycle starts from less noise than the one before, e.g. [750, 500, 250])", t)


class EditStrategy:
    """What a kind of edit decides during refinement (see the module's docstring)."""

    name = ""
    shape_may_change = True

    def __init__(self, refine: RefineConfig, ablation: Any, densify: Optional[DensifyStrategy] = None) -> None:
        self.cfg, self.ablation = refine, ablation
        # Trains only the localized selection (and what the edit adds), on targets kept where it renders.
        self.regional = ablation.localize and not ablation.optimize_all
        self.densify = densify

    def t_schedule(self) -> List[int]:
        return list(self.cfg.t_schedule)

    def start_timestep(self, cycle: int) -> int:
        if self.ablation.constant_t is not None:
            return int(self.ablation.constant_t)
        return int(self.t_schedule()[cycle])

    def first_view_is_target(self, neighbours: int) -> bool:
        return True

    def cycle_views(self, system, cycle: int, frontal: int, near: List[int]) -> Tuple[int, List[int]]:
        """(frontal view, its neighbours) that refinement cycle `cycle` edits, given the schedule's
        (`stages.views.cycle_views`)."""
        return frontal, near

    def composite(self, system, index: int, edited: torch.Tensor, added: Optional[torch.Tensor]) -> torch.Tensor:
        if not (self.ablation.composite and self.regional):
            return edited
        return composite_target(edited, system.source_renders[index], system.source_region(index), added,
                                opaque=system.source_alpha(index) > 0.5)

    def target(self, system, index: int, edited: torch.Tensor) -> torch.Tensor:
        return self.composite(system, index, edited, None)

    def set_trainable(self, geometry, param_groups: List[dict]) -> None:
        # "editable" = mask | generation > 0, re-evaluated at every backward pass.
        geometry.set_trainable_mask(None if self.ablation.optimize_all else "editable")

    def after_edits(self, system) -> None:
        pass

    def growable(self, geometry) -> Optional[torch.Tensor]:
        """(N,) bool the rows densification may clone or split, None: every row it may change."""
        return None

    def finish(self, system) -> None:
        pass

    def saved_arrays(self, n_source: int) -> Dict[str, Any]:
        """More per-Gaussian arrays for save/edit_mask.npz, over the `n_source` source rows (none here)."""
        return {}

    def state_dict(self) -> Dict[str, Any]:
        return {}

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        pass

    def to(self, device) -> "EditStrategy":
        return self


@torch.no_grad()
def colour_step(geometry, rows_: torch.Tensor, views: List[Any], targets: torch.Tensor, renders: List[torch.Tensor],
                recoloured: Optional[torch.Tensor] = None) -> None:
    """Move the base colour of each of `rows_` by the mean, over its pixels in `views` (their
    `PixelWeights`) weighted by its compositing weight there, of what the `targets` still ask of the
    `renders`, each pixel's ask scaled by how much the editor recoloured it (`recoloured`, (V, H, W)
    in [0, 1]: a recolour's `edit_blend`; None: wholly): one Jacobi step of the colours towards
    the targets. Where trained rows cover a pixel whole the step lands on its target; where they
    share it with rows that do not train, or the editor recoloured it in part, it falls short,
    never past. Why: a cycle's Adam steps move a colour at most the rate a step (0.38 in RGB over
    the truth suite's 60 steps at the colour rate), and a Gaussian that a share p of the cycle's
    steps see about sqrt(p) as fast; too little for a side the cycle edits for the first time or a
    part its views see little (`Recolour.after_edits`)."""
    num = torch.zeros(geometry.num_gaussians, 3, device=geometry.means.device)
    den = torch.zeros(geometry.num_gaussians, device=geometry.means.device)
    for k, (view, target, render) in enumerate(zip(views, targets, renders)):
        ask = target.to(render) - render.detach()
        num += view.gather(ask if recoloured is None else ask * recoloured[k].to(render)[..., None])
        den += view.totals(*render.shape[:-1], render.device)
    step = rows_ & (den >= SEEN_MIN_WEIGHT)
    geometry.sh_dc.data[step] += num[step] / den[step, None] / SH_C0


@torch.no_grad()
def views_that_see(system, cycle: int, frontal: int, near: List[int], region: torch.Tensor,
                   what: str) -> Tuple[int, List[int]]:
    """(frontal, near) with each neighbour in which the `region` rows cover under SEEN_PX pixels
    (their `render_selection` summed) replaced by the nearest training camera to `frontal` that
    sees them, nearest first; when too few do, the rest of `near` stay. A view that sees none of
    the region edits none of it: its edit trains nothing of the edit and spends the editor's
    evaluations. Rendered until enough seeing views are found (one render a view, kept for the
    cycle); metrics.json `count_cycle_views_moved` counts the views replaced."""
    g, scene = system.geometry, system.scene
    cover: Dict[int, float] = {}

    def sees(v: int) -> bool:
        if v not in cover:
            cam = scene.cameras[v].to(system.device)
            cover[v] = float(render_selection(g, system.renderer, cam, region).sum())
        return cover[v] >= SEEN_PX

    if all(sees(v) for v in near):
        return frontal, near
    by_distance = nearest_cameras(scene.cameras, frontal, len(scene.train_indices), scene.train_indices)
    seeing = list(islice((v for v in by_distance if sees(v)), len(near)))  # rendered until enough are found
    kept = [v for v in near if v not in seeing][: len(near) - len(seeing)]  # too few see it: the rest stay
    chosen = [v for v in by_distance if v in seeing or v in kept]  # nearest first, as the schedule orders them
    moved = sum(v not in near for v in chosen)
    system.counts["cycle_views_moved"] = system.counts.get("cycle_views_moved", 0) + moved
    log.info("refine %d: %d of view %d's nearest views see nothing of %s; the cycle edits the nearest that do "
             "instead", cycle + 1, moved, frontal, what)
    return frontal, chosen


class Recolour(EditStrategy):
    """Depth initialization was trusted and found no change of shape: the localized Gaussians keep
    their shape and opacity and train their colours only. The gate (`after_edits`) keeps the
    selected Gaussians the edited views do not recolour at their source colours. None are added,
    unless the edited views recolour next to none of the selection (SMALL_OBJECT_BLEND): then the
    edit adds an object no view's depth showed, and the later cycles paint it (`paints_object`)."""

    name = "recolour"
    shape_may_change = False

    def __init__(self, refine: RefineConfig, ablation: Any, densify: Optional[DensifyStrategy] = None) -> None:
        super().__init__(refine, ablation, None)
        self.blend_votes: Optional[torch.Tensor] = None  # (2, N) the gate's sums over the edited views
        self.recent_votes: Optional[torch.Tensor] = None  # (2, N) the same, earlier cycles weighted down
        self.was_distinct: Optional[torch.Tensor] = None  # (N,) found a part of its own in an earlier cycle
        self.unedited_cycles: List[int] = []  # the later cycles that went where the part was still unedited
        self.best_weights: Optional[torch.Tensor] = None  # (N,) each row's weight in the view that sees it best
        self.neighbourhood: Optional[torch.Tensor] = None  # (N, GATE_NEIGHBOURS) each row's nearest (`neighbours`)
        self.pieces: Optional[torch.Tensor] = None  # (N,) the selection's connected pieces (`selection_pieces`)

    def rows_appended(self, count: int) -> None:
        """Rows were added at the end (painted): the per-row state grows with them (no votes, not
        distinct); the neighbourhoods and pieces are found again."""
        for name in ("blend_votes", "recent_votes", "was_distinct", "best_weights"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, torch.cat([value, value.new_zeros(*value.shape[:-1], count)], -1))
        self.neighbourhood = self.pieces = None

    def paints_object(self, system, blend: torch.Tensor, seen: torch.Tensor) -> bool:
        """Does this cycle paint what its targets show and the scene lacks? From the second cycle
        on (the first trained the recolour), when the edited views recolour the median seen selected
        Gaussian (`blend`, the gate's, over the `seen` selected rows) by less than SMALL_OBJECT_BLEND:
        the edit adds an object on the part that no view's depth showed. Recoloured, the part's
        Gaussians, mostly beside it or larger than it, could only smear its colour (fresh 880011 c04,
        a small ball on the face splat: +3.95 dB, 95 of 116 declined by the gate)."""
        return system.state.targets_cycle >= 1 and bool(seen.any()) and float(blend[seen].median()) < SMALL_OBJECT_BLEND

    @torch.no_grad()
    def poorly_seen(self, system, seen: torch.Tensor) -> torch.Tensor:
        """(N,) bool: the rows that the views which saw them `seen` (rendering weight summed over
        them, in pixels) have seen less, all together, than the one training view that sees them
        best (of UNEDITED_CANDIDATES), or not at all (under SEEN_MIN_WEIGHT). Why: the back of a
        head edited from the front is seen edge-on at its rim by every edited view, recoloured
        faintly there and declined by the gate; counted as seen, no cycle went to it (a whole
        head's recolour kept its back). A recolour keeps its geometry: the best views are found once."""
        g = system.geometry
        if self.best_weights is None or self.best_weights.shape[0] != g.num_gaussians:
            best = torch.zeros(g.num_gaussians, device=system.device)
            for v in spread_subset(system.scene.train_indices, UNEDITED_CANDIDATES):
                cam = system.scene.cameras[v].to(system.device)
                view = system.renderer.pixel_weights(g, cam)
                best = torch.maximum(best, view.totals(cam.height, cam.width, system.device))
            self.best_weights = best
        return seen < (WELL_SEEN * self.best_weights).clamp_min(SEEN_MIN_WEIGHT)

    @torch.no_grad()
    def cycle_views(self, system, cycle: int, frontal: int, near: List[int]) -> Tuple[int, List[int]]:
        """A later cycle goes where the part is still unedited (`unedited_views`), and every
        cycle edits views that see the selection (`views_that_see`). Why the latter: the nearest
        cameras of a view that sees a small part from its side can all look at the figure from
        the other side (192837 c13, a small ball on a body's flank: five of its second cycle's
        seven views covered none of the selection)."""
        if not self.regional:
            return frontal, near
        if cycle:
            frontal, near = self.unedited_views(system, cycle, frontal, near)
        return views_that_see(system, cycle, frontal, near, self.region_rows(system), "the selection")

    def region_rows(self, system) -> torch.Tensor:
        """(N,) bool: the rows the recolour edits: the source's selected rows and what it painted."""
        g = system.geometry
        return rows.of_source(g, system.state.source_selection) | (g.generation > 0)

    @torch.no_grad()
    def unedited_views(self, system, cycle: int, frontal: int, near: List[int]) -> Tuple[int, List[int]]:
        """A later cycle's frontal view is the training view in which the selected Gaussians the
        edited views have not seen well (`poorly_seen`; the gate's votes count what the edited
        views saw) cover the most, at least UNEDITED_MIN_AREA of its pixels
        (UNEDITED_MIN_SHARE_AREA when they are UNEDITED_MIN_SHARE of the selection); half of its
        neighbours are the nearest cameras to it, the rest the schedule's. Otherwise the
        schedule's views."""
        if self.blend_votes is None:
            return frontal, near
        g, scene = system.geometry, system.scene
        selected = rows.of_source(g, system.state.source_selection)
        unseen = selected & self.poorly_seen(system, self.blend_votes[1])
        # What no training view sees (a part's inside) no cycle can edit: it counts neither way.
        seeable = self.best_weights >= SEEN_MIN_WEIGHT
        selected, unseen = selected & seeable, unseen & seeable
        if not bool(unseen.any()):
            return frontal, near
        share = int(unseen.sum()) / int(selected.sum())
        min_area = UNEDITED_MIN_SHARE_AREA if share >= UNEDITED_MIN_SHARE else UNEDITED_MIN_AREA
        best, most = None, 0.0
        for v in spread_subset(scene.train_indices, UNEDITED_CANDIDATES):
            cam = scene.cameras[v].to(system.device)
            area = float(render_selection(g, system.renderer, cam, unseen).sum()) / (cam.width * cam.height)
            if area >= min_area and area > most:
                best, most = v, area
        if best is None:
            return frontal, near
        if cycle not in self.unedited_cycles:
            self.unedited_cycles.append(cycle)
        system.counts["unedited_cycles"] = len(self.unedited_cycles)
        log.info("refine %d: the selected Gaussians no edited view has seen well cover %.0f%% of view %d; the "
                 "cycle starts there", cycle + 1, 100 * most, best)
        # Half of the cycle's views go there; the rest are the schedule's, which would otherwise
        # lose a cycle of refinement on the sides already edited.
        there = nearest_cameras(scene.cameras, best, self.cfg.m // 2, scene.train_indices)
        return best, there + [v for v in [frontal, *near] if v != best and v not in there][: self.cfg.m - len(there)]

    def set_trainable(self, geometry, param_groups: List[dict]) -> None:
        if self.ablation.optimize_all:
            geometry.set_trainable_mask(None)
            return
        geometry.set_trainable_mask("editable")
        # Left free, the region's Gaussians grow and move into the unedited surroundings.
        for group in param_groups:
            group["lr"] *= RECOLOUR_LR_SCALE if group["name"] in SHAPE_FREE_PARAMS else 0.0

    @torch.no_grad()
    def after_edits(self, system) -> None:
        """The gate: the selected Gaussians that the edited views so far do not recolour
        (`refine.min_edit_blend`; the earlier cycles' views count EARLIER_CYCLES_WEIGHT as much as
        the latest's), or that are a part of their own (DISTINCT_PART_BLEND), go back to
        their source colours and stop training; one whose views later recolour it trains again.
        The cycle's targets train with each pixel weighted by the edit's blend there
        (RECOLOURED_PIXEL_FLOOR). Two gathers per view of this cycle. The Gaussians it takes that its
        steps would leave short get their colours from its targets (`colour_step`: a render and two
        gathers more per view): inside what trains, those recoloured fully that its views see little
        (`little_seen_inside`); in a cycle that went where the part was still unedited, those no
        earlier edited view saw well."""
        if not self.regional or self.cfg.min_edit_blend <= 0:
            return
        g, s = system.geometry, system.state
        weights = [system.renderer.pixel_weights(g, system.scene.cameras[j].to(system.device)) for j in s.cycle_views]
        blends, votes = [], torch.zeros(2, g.num_gaussians, device=system.device)
        for k, (j, view) in enumerate(zip(s.cycle_views, weights)):
            blend = edit_blend(s.cycle_targets[k], system.source_renders[j]).clamp(0, 1)
            votes += torch.stack([view.gather(blend), view.totals(*blend.shape, blend.device)])
            blends.append(blend)
        fresh = self.blend_votes is None or self.blend_votes.shape != votes.shape
        seen_before = torch.zeros_like(votes[1]) if fresh else self.blend_votes[1].clone()  # by the earlier cycles' views
        self.add_cycle_votes(votes)
        blends = torch.stack(blends)
        s.cycle_weights = RECOLOURED_PIXEL_FLOOR + blends  # the cycle trains on what its views recolour
        num, den = self.recent_votes
        src = g.source_index
        selected = rows.of_source(g, s.source_selection)
        blend, seen_by_views = self.judged_blend()
        seen = selected & seen_by_views  # one no edited view sees is not judged: it keeps training
        takes = (selected & ~seen) | recoloured(num, den, seen, self.cfg.min_edit_blend, GATE_REFERENCE_QUANTILE)
        colours = sh_to_rgb(system.source_model.sh_dc.detach()[src.clamp_min(0)]).clamp(0, 1)
        if self.was_distinct is None or self.was_distinct.shape != seen.shape:
            self.was_distinct = torch.zeros_like(seen)
        distinct = torch.zeros_like(seen)
        part = part_colours(colours, blend, seen, DISTINCT_PART_BLEND)
        if part is not None:
            distinct = distinct_parts(colours, blend, seen, DISTINCT_PART_BLEND, part=part) | still_distinct(
                self.was_distinct, colours, blend, seen, DISTINCT_PART_BLEND, part, STILL_DISTINCT)
            # the rim of what stands in front of the part, selected with it, is a piece of its own
            distinct |= seen & outlying_pieces(self.selection_pieces(g, selected), seen & (blend >= DISTINCT_PART_BLEND),
                                               seen, OUTLYING_PIECE_SHARE)
        self.was_distinct |= distinct
        takes &= ~distinct
        system.counts["recolour_distinct"] = int(distinct.sum())
        rows.restore(g, system.source_model, g.mask & ~takes, SHAPE_FREE_PARAMS, system.optimizers())
        g.mask.copy_(takes | (g.generation > 0))  # what the cycles painted trains too (the gate judges the source's)
        system.counts["recolour_declined"] = int((selected & ~takes).sum())
        system.counts["recolour_taken"] = int((seen & takes).sum())
        # Colours the cycle's steps would leave short land on its targets at once: the inside of
        # what trains, recoloured fully, that its views see little, and the part this cycle edits
        # for the first time.
        step = self.little_seen_inside(g, takes, blend, votes[1], seen)
        if s.targets_cycle in self.unedited_cycles:
            step |= takes & self.poorly_seen(system, seen_before)
        if bool(step.any()):
            colour_step(g, step, weights, s.cycle_targets, [system.render_view(j)["rgb"] for j in s.cycle_views], blends)
        if self.paints_object(system, blend, seen):
            before = g.num_gaussians
            if system.fill_from_cycle_depth():
                self.rows_appended(g.num_gaussians - before)

    def little_seen_inside(self, geometry, takes: torch.Tensor, blend: torch.Tensor, cycle_seen: torch.Tensor,
                           judged: torch.Tensor) -> torch.Tensor:
        """(N,) bool: the rows the gate lets train (`takes`) whose GATE_NEIGHBOURS nearest it lets
        train too (not the rim of what trains, where the editor's spill lands), that the edited
        views recolour fully (the gate's `blend` >= FULLY_RECOLOURED) and that the cycle's views
        see less (`cycle_seen`: their rendering weight summed, in pixels) than LITTLE_SEEN times the
        median of the `judged` rows that train. Why: the cycle's steps move those colours the least
        (`colour_step`): a backdrop's Gaussians that the training views see little (under 8 px in
        all) kept a median 60 % of their change undone. The well-seen ones train to their targets by
        themselves. Stepped at once, a part that takes the editor's spill (a nose coloured like the
        recoloured head) took it whole, and so did the band of the selection past the part: inside
        the selection rather than inside what trains, a ball's neighbours lost up to 6 dB outside,
        and Gaussians recoloured in part, hidden under a recoloured surface, took its colour."""
        taken = takes & judged
        if not bool(taken.any()):
            return torch.zeros_like(takes)
        inside = takes & takes[self.neighbours(geometry)].all(-1) & (blend >= FULLY_RECOLOURED)
        return inside & (cycle_seen < LITTLE_SEEN * cycle_seen[taken].median())

    def neighbours(self, geometry) -> torch.Tensor:
        """(N, GATE_NEIGHBOURS) each row's nearest rows (`neighbors.knn`): found once, as a recolour
        keeps its geometry."""
        if self.neighbourhood is None or self.neighbourhood.shape[0] != geometry.num_gaussians:
            self.neighbourhood = neighbors.knn(geometry.means.detach(), GATE_NEIGHBOURS)[1]
        return self.neighbourhood

    def selection_pieces(self, geometry, selected: torch.Tensor) -> torch.Tensor:
        """(N,) the connected piece of the selection each selected row lies in, over each Gaussian's
        GATE_NEIGHBOURS nearest (`neighbors.components`; -1 for the others): found once, as a
        recolour keeps its geometry and its selection."""
        if self.pieces is None or self.pieces.shape[0] != geometry.num_gaussians:
            self.pieces = neighbors.components(self.neighbours(geometry), selected)
        return self.pieces

    def add_cycle_votes(self, votes: torch.Tensor) -> None:
        """Add a cycle's gate votes (2, N: Σ_views gather(edit_blend) and the views' rendering weights)
        to `blend_votes` (every cycle alike: what the edited views have seen) and to `recent_votes`
        (the gate's blend: the earlier cycles' at EARLIER_CYCLES_WEIGHT). Votes of another row count
        (a geometry that changed) start over."""
        if self.blend_votes is None or self.blend_votes.shape != votes.shape:
            self.blend_votes, self.recent_votes = torch.zeros_like(votes), torch.zeros_like(votes)
        if self.recent_votes is None or self.recent_votes.shape != votes.shape:  # a checkpoint from before them
            self.recent_votes = self.blend_votes.clone()
        self.blend_votes += votes
        self.recent_votes.mul_(EARLIER_CYCLES_WEIGHT).add_(votes)

    def finish(self, system) -> None:
        # the gate let no Gaussian an edited view sees through, and the cycles painted nothing
        if system.counts.get("recolour_taken") == 0 and not system.counts.get("added_cycles"):
            system.warn(f"refine: the edited views recolour none of the {system.counts.get('selected', 0):,} selected "
                        f"Gaussians by system.refine.min_edit_blend={self.cfg.min_edit_blend} of the edit's colour, "
                        "so each kept its source colours and the scene comes out unchanged; a lower min_edit_blend "
                        "lets the edit through")

    def judged_blend(self) -> Tuple[torch.Tensor, torch.Tensor]:
        """((N,) each row's blend: the edited views' rendering-weighted mean `edit_blend`, earlier
        cycles weighted down, what the gate judges a selected row on; (N,) bool: an edited view saw
        it, SEEN_MIN_WEIGHT pixels of rendering weight over all cycles)."""
        num, den = self.recent_votes
        return num / den.clamp_min(1e-12), self.blend_votes[1] >= SEEN_MIN_WEIGHT

    def saved_arrays(self, n_source: int) -> Dict[str, Any]:
        """`gate_blend` (n_source,) float32: each source Gaussian's `judged_blend` at the last
        cycle, NaN where no edited view saw it (scripts/changed_gaussians.py: can the rows the gate
        took be told from those it declined by it?). The source's rows come first and in order: a
        recolour only appends (the cycles' paint) and prunes what it appended."""
        if self.recent_votes is None or self.blend_votes is None:
            return {}
        blend, seen = (x[:n_source] for x in self.judged_blend())
        return {"gate_blend": torch.where(seen, blend, torch.full_like(blend, float("nan"))).float().cpu().numpy()}

    def state_dict(self) -> Dict[str, Any]:
        return {**{key: None if value is None else value.cpu()
                   for key, value in (("blend_votes", self.blend_votes), ("recent_votes", self.recent_votes),
                                      ("was_distinct", self.was_distinct))},
                "unedited_cycles": list(self.unedited_cycles)}

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        self.blend_votes, self.was_distinct = state.get("blend_votes"), state.get("was_distinct")
        self.recent_votes = state.get("recent_votes")
        self.unedited_cycles = list(state.get("unedited_cycles") or [])

    def to(self, device) -> "Recolour":
        for name in ("best_weights", "pieces", "neighbourhood", "blend_votes", "recent_votes", "was_distinct"):
            if getattr(self, name) is not None:
                setattr(self, name, getattr(self, name).to(device))
        return self


class Addition(EditStrategy):
    """An edit that may change the shape (depth initialization added Gaussians, was rejected or is
    off): the Gaussians it adds draw the new geometry; the source's keep `refine.source_fixed`, and
    their colours too when the first edit recolours next to nothing beside what it added."""

    name = "addition"

    def __init__(self, refine: RefineConfig, ablation: Any, densify: Optional[DensifyStrategy] = None,
                 recoloured_fraction: Optional[float] = None) -> None:
        super().__init__(refine, ablation, densify)
        # The edit adds and recolours nothing: the source keeps its colours.
        self.adds_only = recoloured_fraction is not None and recoloured_fraction < refine.min_recoloured_fraction

    def t_schedule(self) -> List[int]:
        return list(self.cfg.t_schedule if self.cfg.shape_t_schedule is None else self.cfg.shape_t_schedule)

    def after_edits(self, system) -> None:
        """Gaussians for what the cycle's targets show of the new object and the scene lacks (its
        other sides: the first view's depth placed the side it sees)."""
        if self.regional and self.ablation.initialize:
            system.fill_from_cycle_depth()

    @torch.no_grad()
    def cycle_views(self, system, cycle: int, frontal: int, near: List[int]) -> Tuple[int, List[int]]:
        """The cycle's views that see what the edit added (`views_that_see`). Why: the nearest
        cameras of a view that sees an object at the back of a head can all look at the head from
        the other side (424242 c03, a small ball: the first view's six neighbours saw 0-6 of its
        pixels, other views up to 31); their edits draw nothing, and the cycles place nothing of it.
        Before anything is added, the schedule's views."""
        added = system.geometry.generation > 0
        if not self.regional or not bool(added.any()):
            return frontal, near
        return views_that_see(system, cycle, frontal, near, added, "what the edit added")

    def growable(self, geometry) -> Optional[torch.Tensor]:
        """Once the edit has added Gaussians, only they densify: a selected source Gaussian keeps
        its position (`refine.source_fixed`), and its clone or split children would be rows of the
        edit, free, carved out of the fixed surface beside the object, which take the object's
        colour there and spread it (402113 c11 at twice the steps: 7 of 11 splits were of source
        Gaussians 2.6-3.9 object radii away, and their children ended opaque off the object).
        Before any is added (depth placed none), the selection's Gaussians densify to grow it."""
        if "means" not in self.cfg.source_fixed or self.ablation.optimize_all:
            return None
        added = geometry.generation > 0
        return added if bool(added.any()) else None

    def first_view_is_target(self, neighbours: int) -> bool:
        # A full edit from pure noise places the object the farthest from where the other views put
        # it; as a target it pulls the object towards its own offset. Its neighbours' partial edits
        # are the first cycle's targets (the view counts as edited), unless it has none (m = 0).
        return neighbours == 0

    def target(self, system, index: int, edited: torch.Tensor) -> torch.Tensor:
        added = None
        if self.ablation.composite and self.regional:
            cam = system.scene.cameras[index].to(system.device)
            added = render_selection(system.geometry, system.renderer, cam, system.geometry.generation > 0)
        return self.composite(system, index, edited, added)

    def set_trainable(self, geometry, param_groups: List[dict]) -> None:
        if self.ablation.optimize_all:
            geometry.set_trainable_mask(None)
            return
        geometry.set_trainable_mask("editable")
        fixed = [*self.cfg.source_fixed, *(SHAPE_FREE_PARAMS if self.adds_only else ())]
        if fixed:
            geometry.set_added_only(fixed)
        if "means" in fixed:  # only the added rows move, so only they get the faster rate
            for group in param_groups:
                if group["name"] == "means":
                    group["lr"] *= ADDED_POSITION_LR_SCALE


def is_recolour_edge(report: dict, refine: RefineConfig) -> bool:
    """Is initialization's change of shape (`report`) only a recolour's edge (MIN_SHAPE_PIXELS)?"""
    fraction = report.get("recoloured_fraction")
    return (0 < report.get("placed_pixels", 0) < MIN_SHAPE_PIXELS and fraction is not None
            and fraction >= refine.min_recoloured_fraction)


def choose_strategy(init_report: Optional[dict], initialized: bool, refine: RefineConfig, ablation: Any,
                    densify: DensifyStrategy) -> EditStrategy:
    """A `Recolour` when depth initialization ran (`initialized`), was trusted and found no change
    of shape; an `Addition` otherwise (`init_report`: initialization's report, None when it did not
    run)."""
    report = init_report
    if initialized and report is not None and "rejected" not in report and report["added"] == 0:
        return Recolour(refine, ablation)
    return Addition(refine, ablation, densify, (report or {}).get("recoloured_fraction"))
