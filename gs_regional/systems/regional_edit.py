"""`regional-edit`: localize → initialize → conditional sequential refinement (DESIGN.md §3)."""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import ClassVar, Dict, List, Optional

import torch

from gs_regional.config import ConfigError
from gs_regional.edit.change import edit_blend, edit_change, recoloured_fraction
from gs_regional.edit.composite import MIN_OBJECT_BLEND, composite_target, distinct_parts, recoloured
from gs_regional.edit.initialize import InitConfig, calibration_pixels, depth_calibration_pixels, new_gaussians_from_depth
from gs_regional.edit.localize import (
    expand_selection, localize_gaussians, mask_agreement, render_selection, splat_selection,
)
from gs_regional.edit.prune import useless_added
from gs_regional.edit.views import frontier_view, nearest_cameras, spread_subset
from gs_regional.geometry import rows
from gs_regional.geometry.strategy import DensifyStrategy
from gs_regional.metrics.region import mask_metrics
from gs_regional.renderers.base import PixelWeights
from gs_regional.utils.image import dilate
from gs_regional.utils.sh import SH_C0, sh_to_rgb
from gs_regional.utils.visualize import overlay_mask
from gs_regional.registry import find, register
from gs_regional.systems import parallel
from gs_regional.systems.edit_base import EditSystemBase

log = logging.getLogger(__name__)

FIRST_VIEW_TARGETS = ("skip", "reedit", "full")  # refine.first_cycle_first_view
SHAPE_FREE_PARAMS = ("sh_dc", "sh_rest")  # what a recolour trains (no change of shape found)
# A first edit whose change (beyond the editor's noise) is under this fraction of another view's
# shows nothing of the edit: the region is hidden there (run_initialize).
SHOWS_NOTHING = 0.15
# A full edit whose change (beyond the editor's noise) covers fewer than this fraction of the view's
# pixels is too small to say where the edit is (at 64², 8 pixels: a small object a few pixels
# across, or a jittered placement showing a pixel of it): it cannot stop the run.
MIN_JUDGED_CHANGE = 0.002
# A first view whose selection overlaps its 2D mask by less than this share of the best view's
# overlap hides the region (769177 c24: 0 px against 66); one that shows it as well (the
# stability sweep's regeneration drift 0.4: 176 against 179) keeps the edit even when a tone
# drift drowns the edit's change there.
HIDES_REGION = 0.5
# A full edit puts its change in the selection when at least `min_edit_coverage` of it lies there,
# or half of that while it changes at least this fraction of the selection's pixels: a big object
# added on a small part sticks out of it over what lies behind (half or more of its change beside
# the selection) but covers the part; an edit placed on something else changes next to none of
# the selection (0-0.03 in the stability sweep's stops, 0.09-0.27 on the big balls put on a head).
MIN_FILLED = 0.1
SEEN_MIN_WEIGHT = 0.01  # pixels of rendering weight over the localization views: a Gaussian they see


@dataclass
class LocalizeConfig:
    max_views: int = 24  # views rendered for the 2D relevance maps, spread over the cameras
    timestep: int = 600  # τ of the noise difference
    gamma: float = 0.6  # threshold of the normalised relevance; 0 selects everything
    samples: int = 1  # noise draws averaged per view
    blur_sigma: float = 2.0  # Gaussian filter that removes isolated specks (pixels)
    mask_threshold: float = 0.5  # a Gaussian is selected if its weighted mask vote exceeds this
    # In the lift, a Gaussian's votes from a mask's one-pixel edge are dropped in a view where its
    # own colour is closer to the outside's local mean colour than to the interior's by this factor
    # (gs_regional.edit.localize.outside_like_edge_votes): blobby relevance maps reach a pixel past
    # the region, and a surface seen edge-on beside it (a neck under a head) is selected whole.
    # 0 switches it off (docs/method.md).
    edge_colour_ratio: float = 0.5
    # Robust lifting (gs_regional.edit.localize.localize_gaussians); 0 / 1 give the plain vote.
    reweight_iters: int = 2  # re-lift with views weighted by their agreement with the 3D mask
    agreement_power: float = 2.0  # view weight = IoU(2D mask, rendered 3D mask) ** power
    knn: int = 16  # pool votes over the k nearest Gaussians (point expansion)
    expand_radius: float = 0.0  # also select everything within this radius, as a fraction of the scene extent
    # The views disagree about the region when, even in the better half of them (side views may
    # miss it), the 2D masks overlap the rendered 3D mask by less than this (mean IoU): the
    # instruction names nothing the editor finds consistently, and the run stops with the source
    # written unchanged. 0 never stops.
    min_view_agreement: float = 0.3
    # ... where a mask pixel within this many pixels of the other mask counts as shared
    # (gs_regional.edit.localize.mask_agreement): a part a few pixels across, its masks a pixel
    # off, is the same place (the face patches of 14-53 Gaussians that stopped; docs/method.md).
    agreement_tolerance_px: int = 1
    # The first full edit (initialization) checked against the selection, without ground truth:
    # the fraction of the editor's change beyond its noise in that view (tone drift fitted away,
    # as for the composite; gs_regional.edit.composite.edit_change) within 2 px of the localized
    # region (metrics.json `edit_coverage`). Below this, most of what the editor changes is not
    # what localization selected, and the run stops with the source written unchanged (the
    # values seen on runs that should and should not stop: docs/method.md). 0 never stops.
    min_edit_coverage: float = 0.5


@dataclass
class RefineConfig:
    MOVED_KEYS: ClassVar[Dict[str, str]] = {
        "densify": "system.densify.enabled", "densify_every": "system.densify.every",
        "grad_threshold": "system.densify.grad_threshold", "densify_budget": "system.densify.budget",
        "reedit_first_view": "system.refine.first_cycle_first_view (skip | reedit | full)",
    }
    cycles: int = 3
    t_schedule: List[int] = field(default_factory=lambda: [750, 500, 250])  # start timestep per cycle
    # The start timesteps of an edit that may change the shape (depth initialization added
    # Gaussians, was rejected or is off); None uses `t_schedule`. A recolour needs the noise to
    # move colours far; an addition needs the opposite: each partial denoise regenerates what the
    # render already shows, and from less noise it keeps more of the new geometry's sharpness
    # instead of redrawing it anew in every view (the views disagree and training averages them
    # into a smear). Recolours lose with less noise, so they keep `t_schedule` (docs/method.md).
    shape_t_schedule: Optional[List[int]] = field(default_factory=lambda: [450, 350, 250])
    constant_t: Optional[int] = None  # ablation: one start timestep for every cycle
    # The first cycle's target for its frontal view (the first edited view) in an edit that may
    # change the shape (a recolour always takes the first full edit):
    #   "skip"   none: the view gives initialization its depth, its m neighbours' partial edits
    #            are the cycle's targets (it counts as edited for later cycles; with m = 0 it
    #            takes the full edit);
    #   "reedit" a partial edit of the render after initialization at the cycle's start timestep,
    #            like its neighbours (one partial edit more: 27 UNet evaluations at t=450);
    #   "full"   the first full edit itself.
    # A full edit from pure noise places the edit the farthest from where the other views put it
    # (the editor's per-view shift is largest there), and as a target it pulled the new object
    # towards its own offset, which training averaged into a soft, wide silhouette: "reedit" gained
    # up to 3 dB outside the true footprint on big balls. "skip" removes that pull at no cost and
    # matched "reedit" on 925517 (tuned on) and fresh 219221, 3 / 2 run seeds a case (paired median gain +0.10 / -0.15
    # dB, outside -0.28 / +0.11 dB), with 27 UNet evaluations fewer an addition (docs/results.md).
    # Dropping the farthest neighbour instead lost up to 5.7 dB of gain; a recolour re-edited lost
    # 5.6 dB on a patch a few pixels across (549446 c09).
    first_cycle_first_view: str = "skip"
    iterations_per_cycle: int = 500
    m: int = 20  # nearest cameras edited around the cycle's frontal view
    # The frontal view of cycles after the first: "random" (the paper: any edited view) or
    # "frontier" (the edited view with the most unedited views among its m nearest: the edit
    # spreads outwards instead of re-editing the same views; views never edited keep the source's
    # look on the edited part, seen as smears in side views).
    next_frontal: str = "frontier"
    optimize_all: bool = False  # let gradients reach every Gaussian (the paper's setting)
    # The parameters of the selected source Gaussians that an edit which may change the shape
    # leaves as they were: only the Gaussians the edit added (from depth, by densification) train
    # them, the source's keep their place, size and opacity and change colour only. Free, the
    # region's Gaussians grow over their neighbours and follow every view's jittered target
    # (docs/method.md). [] frees them all (an edit that must move or remove source geometry).
    source_fixed: List[str] = field(default_factory=lambda: ["means", "quats", "log_scales", "opacity_logits"])
    # An edit that adds Gaussians from depth leaves the selected source Gaussians their colours too
    # when the first edited view recolours less than this fraction of the region beside what was
    # added (metrics.json `init.recoloured_fraction`): the edit adds and recolours nothing, and
    # free colours would only learn each view's jittered copy of the new object and the editor's
    # bleed (they drift further the longer refinement runs). The added Gaussians, and those
    # densified from them, draw the object. 0: the source's colours always train.
    min_recoloured_fraction: float = 0.3
    # Keep each edited view only where the localized Gaussians render (weighted by how much of the
    # pixel they cover) and the source render elsewhere: the 2D editor's changes outside the region
    # (bleed, the blur and tone drift of regenerating the image) never become targets.
    composite: bool = True
    # An edit that may change the shape (depth initialization added Gaussians, was rejected or is
    # off) also keeps, within this many pixels of the region and the added Gaussians, the pixels
    # the editor changed by more than `composite_noise_sigmas` x its noise (measured beyond that
    # margin): room for geometry the edit adds. A recolour gets no margin.
    composite_dilate: int = 6
    composite_noise_sigmas: float = 4.0
    # An edit that may change the shape: a target pixel keeps the edit only where it takes at least
    # this much of the edit's nearby colour (gs_regional.edit.composite.edit_blend); the colour the
    # editor spills round a new object stays a source pixel (why just over half: MIN_OBJECT_BLEND).
    composite_min_blend: float = MIN_OBJECT_BLEND
    # A pixel the region covers by at least this fraction keeps the edit fully, below it in
    # proportion (gs_regional.edit.composite.composite_target).
    composite_full_coverage: float = 0.5
    # A recolour's selected Gaussian takes the edit only while the edited views recolour it: its
    # rendering-weighted mean `edit_blend` over every view edited so far (how much of the nearby
    # edit's colour its pixels take; 1 inside the edit, at most about half on the editor's bleed
    # past the edit's edge, 0 where the edit leaves it alone) must reach this, or it keeps its
    # source colours. The selection reaches a pixel or two past the part (blobby 2D masks), and
    # that rim learned the bleed, which costs the unedited surroundings ~15 dB (docs/method.md).
    # 0 lets every selected Gaussian train.
    min_edit_blend: float = 0.5
    # The gate's minimum is `min_edit_blend` times the blend that this quantile of the seen
    # selected Gaussians reaches, kept within [0.3, 1] (gs_regional.edit.composite.recoloured): a
    # part a few pixels across is all edge, its pixels half covered, and even its own Gaussians
    # take under half of the edit's nearby colour (0.2-0.45 on the face patches that came out
    # unchanged), while in a larger part this quantile is 1. 0 compares with `min_edit_blend` as
    # it is (docs/method.md).
    gate_reference_quantile: float = 0.99
    # ... and one recoloured by less than this whose source colour lies well outside the colours
    # of the selected Gaussians recoloured by more (gs_regional.edit.composite.distinct_parts) is
    # a part of its own and keeps its source colours too: the editor spills about half of its
    # colour onto a small part enclosed by the edited one (the figure's eyes in its head), as
    # much as the edited part's own edge takes, but the edge shares the part's colours
    # (metrics.json `count_recolour_distinct`; docs/method.md). 0 switches it off.
    distinct_part_blend: float = 0.85
    # A recolour (depth initialization trusted, no change of shape) trains only colours, at this
    # multiple of their learning rate: 3DGS's rates are made for 30k steps, and a recolour moves
    # colours far in a few hundred. At 6x the colours of the truth suite's recolours (3 x 60
    # steps) arrived short and dull: the recolours' median gain fell under +10 dB on two fresh
    # draws. 9x lifts both over it, no recolour losing gain; 12x gains more but costs the
    # surroundings up to 7.7 dB (the rim the gate lets through takes more of the editor's
    # spill; docs/results.md). Not used when the shape may change (docs/method.md).
    recolour_lr_scale: float = 9.0
    # An edit that may change the shape moves the Gaussians it added (while the source's keep their
    # place: "means" in `source_fixed`) at this multiple of the position learning rate.
    # The new object is placed from one view's depth and that view's edit, which the editor puts a
    # pixel or two off; 3DGS's rate, made for 30k steps, moves it less than that in a cycle's tens
    # of steps, so it kept the first view's offset (docs/method.md). 1 keeps 3DGS's rate.
    added_position_lr_scale: float = 3.0
    # A recolour's selected Gaussians start from the colours of the first cycle's edited views:
    # each one the gate lets take the edit (see the next key) moves its base colour by the
    # rendering-weighted mean, over its pixels in those views, of the edited view minus the source
    # render. 3DGS's colour rate, even at `recolour_lr_scale`, carries a colour that far only in
    # about as many steps as a short refinement has, so the colours arrived late and dull
    # (docs/method.md). Training then refines them. Off by default: it gains 1-2 dB of median
    # gain on the truth suite's recolours, but on the demo's head the eyes it encloses then take
    # the edit (the later views' targets, made from redder renders, recolour them past the
    # distinct-part rule) and a longer refinement loses more outside the true footprint.
    recolour_from_edits: bool = False
    # ... only those the edited views recolour fully: the gate's rendering-weighted mean
    # `edit_blend` reaches this. The rim the gate lets through (0.5 up) takes the editor's spill at
    # once when started too, and cost up to 7.8 dB outside the true footprint; left to train from
    # its source colours it lags as before (docs/method.md). 0 starts every one the gate lets take it.
    recolour_start_min_blend: float = 0.85
    # After the last cycle, Gaussians the edit added (from depth or by densification) that
    # contribute nothing are removed: total rendered weight over the training views below
    # `prune_min_weight` (in pixels) or opacity below `prune_min_opacity`.
    prune_added: bool = True
    prune_min_weight: float = 1.0
    prune_min_opacity: float = 0.005
    # Views each training step trains on (the gradient of their mean loss), shared out over the
    # processes of a run on several devices (systems/parallel.py). A number gives the same edit on
    # any number of processes (beyond the order of float sums); null: one view per process, so N
    # devices train on N views a step in the time of one (another edit than one device's).
    views_per_step: Optional[int] = 1


@register("regional-edit")
class RegionalEdit(EditSystemBase):
    @dataclass
    class Config(EditSystemBase.Config):
        depth_type: str = "depth-anything"
        depth: dict = field(default_factory=dict)
        localize: bool = True  # ablation: false selects every Gaussian
        # Ablation for scenes with a known edit: the true region is the selection (localization
        # still runs; mask_iou is then 1), to measure what the rest of the method loses to it.
        localize_with_truth: bool = False
        initialize: bool = True  # ablation: false adds no Gaussians from depth
        localization: LocalizeConfig = field(default_factory=LocalizeConfig)
        init: InitConfig = field(default_factory=InitConfig)
        refine: RefineConfig = field(default_factory=RefineConfig)
        # Densification during refinement: `rounds` times in each cycle, evenly spaced (once, at
        # its middle), whatever the cycle's length (`every: N` instead: every N steps within each
        # cycle, never at its last step); only the editable Gaussians are densified and pruned
        # unless refine.optimize_all; `budget` caps the Gaussians above the count when refinement began.
        # The threshold (5e-4, 2.5x 3DGS's) sits at the knee of scripts/compactness.py on the
        # synthetic add: fewer Gaussians would cost quality, more add none (docs/results.md).
        densify: DensifyStrategy = field(
            default_factory=lambda: DensifyStrategy(
                start=0, stop=None, every=None, rounds=1, opacity_reset_every=0, max_gaussians=None, budget=20000,
                child_generation=1, grad_threshold=5e-4, prune_only_added=True,
            )
        )

    # Settings a resume must keep (launch.py refuses a change): the step -> cycle mapping, and the
    # stages that a checkpoint has usually passed already (a change would be silently ignored).
    RESUME_FIXED_KEYS: ClassVar[tuple] = ("refine.iterations_per_cycle", "localize", "localization", "initialize", "init",
                                          "refine.source_fixed", "refine.min_recoloured_fraction")

    def __init__(self, cfg=None, resumed: bool = False) -> None:
        super().__init__(cfg, resumed=resumed)
        self.check_settings()  # before configure() loads the priors
        self.configure()
        self.cfg.densify.check("system.densify")
        self.depth_estimator = None
        if self.cfg.initialize:
            self.depth_estimator = find(self.cfg.depth_type, kind="depth", key="system.depth_type")(self.cfg.depth)
        # Edit state (all of it goes into checkpoints).
        self.phase = "localize"  # localize -> initialize -> refine -> done
        self.v_first: Optional[int] = None
        self.cycle_targets: Optional[torch.Tensor] = None  # (k, H, W, 3) edited views of a cycle
        self.cycle_views: List[int] = []
        self.targets_cycle = -1
        self.edited_views: List[int] = []
        self.masks2d: Optional[torch.Tensor] = None
        self.source_selection: Optional[torch.Tensor] = None  # (n_source,) bool, set by localization
        self.first_edit: Optional[torch.Tensor] = None
        self.refine_start_count = 0
        self.localized_masks: Dict[int, torch.Tensor] = {}  # view -> (H, W) bool, localize -> initialize
        self.blend_votes: Optional[torch.Tensor] = None  # (2, N) gate_recolour's sums over the edited views

    def check_settings(self) -> None:
        """Settings that cannot work fail at start-up, naming the key and the allowed range."""
        r, lc = self.cfg.refine, self.cfg.localization
        n_t = int(getattr(find(self.cfg.guidance_type, kind="guidance", key="system.guidance_type"),
                          "num_train_timesteps", 1000))

        def need(ok: bool, key: str, allowed: str, value) -> None:
            if not ok:
                raise ConfigError(f"system.{key} must be {allowed}, got {value!r}")

        need(r.cycles >= 1, "refine.cycles", "an integer >= 1", r.cycles)
        need(r.iterations_per_cycle >= 1, "refine.iterations_per_cycle", "an integer >= 1", r.iterations_per_cycle)
        need(r.first_cycle_first_view in FIRST_VIEW_TARGETS, "refine.first_cycle_first_view",
             " or ".join(FIRST_VIEW_TARGETS), r.first_cycle_first_view)
        need(r.m >= 0, "refine.m", "an integer >= 0 (views edited around each cycle's frontal view)", r.m)
        need(0 <= r.composite_full_coverage <= 1, "refine.composite_full_coverage", "a fraction in [0, 1]",
             r.composite_full_coverage)
        need(r.recolour_lr_scale >= 0, "refine.recolour_lr_scale", "a number >= 0", r.recolour_lr_scale)
        need(0 <= r.recolour_start_min_blend <= 1, "refine.recolour_start_min_blend", "a number in [0, 1]",
             r.recolour_start_min_blend)
        need(r.added_position_lr_scale >= 0, "refine.added_position_lr_scale", "a number >= 0", r.added_position_lr_scale)
        need(0 <= r.min_recoloured_fraction <= 1, "refine.min_recoloured_fraction", "a number in [0, 1]",
             r.min_recoloured_fraction)
        need(0 <= r.min_edit_blend <= 1, "refine.min_edit_blend", "a number in [0, 1]", r.min_edit_blend)
        need(0 <= r.gate_reference_quantile <= 1, "refine.gate_reference_quantile", "a number in [0, 1]",
             r.gate_reference_quantile)
        need(0 <= r.distinct_part_blend <= 1, "refine.distinct_part_blend", "a number in [0, 1]", r.distinct_part_blend)
        need(0 <= r.composite_min_blend <= 1, "refine.composite_min_blend", "a number in [0, 1]", r.composite_min_blend)
        need(r.next_frontal in ("frontier", "random"), "refine.next_frontal", "'frontier' or 'random'", r.next_frontal)
        need(lc.max_views >= 1, "localization.max_views", "an integer >= 1", lc.max_views)
        need(lc.agreement_tolerance_px >= 0, "localization.agreement_tolerance_px", "an integer >= 0 (pixels)",
             lc.agreement_tolerance_px)
        need(r.views_per_step is None or r.views_per_step >= 1, "refine.views_per_step",
             "an integer >= 1 or null (one per process)", r.views_per_step)
        need(0 <= lc.timestep < n_t, "localization.timestep", f"a timestep in [0, {n_t - 1}]", lc.timestep)
        if r.constant_t is not None:
            need(0 <= r.constant_t < n_t, "refine.constant_t", f"a timestep in [0, {n_t - 1}]", r.constant_t)
            return
        for key in ("t_schedule", "shape_t_schedule"):
            if getattr(r, key) is None:  # shape_t_schedule only: t_schedule then serves every edit
                continue
            t = list(getattr(r, key))
            if len(t) < r.cycles:
                raise ConfigError(
                    f"system.refine.{key} has {len(t)} timesteps for {r.cycles} cycles; "
                    "give one start timestep per cycle (or system.refine.constant_t)"
                )
            need(all(0 <= x < n_t for x in t), f"refine.{key}", f"timesteps in [0, {n_t - 1}]", t)
            need(all(a >= b for a, b in zip(t, t[1:])), f"refine.{key}",
                 "non-increasing (each cycle starts from less noise than the one before, e.g. [750, 500, 250])", t)

    def check_scene(self) -> None:
        if self.cfg.localize_with_truth and self.scene.ground_truth is None:
            raise ConfigError("system.localize_with_truth=true needs a scene with a known edit (a ground truth: "
                              "data_type synthetic-scene or splat-truth)")
        n = len(self.scene.train_indices)
        if self.cfg.refine.m >= n - 1:
            log.warning("system.refine.m=%d: the scene has %d training views, so every cycle edits all of them",
                        self.cfg.refine.m, n)
        super().check_scene()

    def check_processes(self, n: int, scene) -> None:
        """Before a run on `n` processes (launch.py; systems/parallel.py): each stage that shares
        its views out must have one for every process."""
        if scene is None:
            return
        train, lc, r = list(scene.train_indices), self.cfg.localization, self.cfg.refine
        stages = [(min(r.m, max(len(train) - 1, 0)) + 1,
                   f"views in each refinement cycle (system.refine.m={r.m} and the frontal view)")]
        if self.cfg.localize and lc.gamma > 0:
            stages.append((len(spread_subset(train, lc.max_views)),
                           f"localization views (system.localization.max_views={lc.max_views})"))
        views, what = min(stages)
        if n > views:
            raise ConfigError(f"trainer.devices / --gpu ask for {n} processes, but the edit has only {views} {what} "
                              f"to share out among them: give at most {views} devices")

    @property
    def total_steps(self) -> int:
        return self.cfg.refine.cycles * self.cfg.refine.iterations_per_cycle

    def start_timestep(self, cycle: int) -> int:
        r = self.cfg.refine
        if r.constant_t is not None:
            return int(r.constant_t)
        shape = self.shape_may_change and r.shape_t_schedule is not None
        return int((r.shape_t_schedule if shape else r.t_schedule)[cycle])

    # ----- stage 1 -------------------------------------------------------------------------------
    @torch.no_grad()
    def run_localize(self) -> None:
        self.set_stage("localize")
        t0 = time.perf_counter()
        cfg, lc, scene = self.cfg, self.cfg.localization, self.scene
        g = self.geometry
        views = spread_subset(scene.train_indices, lc.max_views)
        self.localize_views = views
        self.localize_metrics = {}
        if not cfg.localize or lc.gamma <= 0:
            selected = torch.ones(g.num_gaussians, dtype=torch.bool, device=self.device)
            masks = None
        else:
            images = torch.stack([self.source_renders[i] for i in views])
            cams = [scene.cameras[i] for i in views]
            # The views shared out over the processes of a run on several devices (map_views).
            masks = self.map_views(len(views), lambda ks: self.guidance.mask(
                images[ks], cfg.prompt, threshold=lc.gamma, blur_sigma=lc.blur_sigma, timestep=lc.timestep,
                samples=lc.samples, seed=cfg.seed, cameras=[cams[k] for k in ks],
            ), images.shape[1:3])
            cams = [c.to(self.device) for c in cams]
            lift = dict(threshold=lc.mask_threshold, reweight_iters=lc.reweight_iters, agreement_power=lc.agreement_power,
                        knn=lc.knn, images=images, edge_ratio=lc.edge_colour_ratio)
            lifted = localize_gaussians(g, self.renderer, cams, masks, **lift)
            selected = lifted["selected"]
            self.localize_metrics["view_weights"] = [round(float(w), 3) for w in lifted["view_weights"]]
            selected = expand_selection(g.means.detach(), selected, lc.expand_radius * scene.extent)
            selected = parallel.from_rank_zero(self, selected)  # every process edits one selection
            iou = mask_agreement(lifted["views"], masks, selected, faint=True, tolerance_px=lc.agreement_tolerance_px)
            self.localize_metrics["view_agreement"] = float(iou.sort(descending=True).values[: (len(iou) + 1) // 2].mean())
            for k, i in enumerate(views):
                self.save_image(f"localize/mask2d_{i:03d}.png", overlay_mask(self.source_renders[i], masks[k]))
        if cfg.localize_with_truth:  # check_scene made sure there is a truth
            selected = self.scene.ground_truth.region.to(self.device)
        g.mask.copy_(selected)
        # The localized region as rows of the source scene: what the composite and the evaluation
        # render from the source, however densification and pruning move the rows later.
        self.source_selection = rows.source_rows(g, selected, self.n_source)
        self.counts["selected"] = int(selected.sum())
        self.masks2d = masks
        self.add_time("localize", time.perf_counter() - t0)
        if self.scene.ground_truth is not None:
            truth = self.scene.ground_truth.region.cpu()
            self.localize_metrics.update(mask_metrics(self.source_selection.cpu(), truth))
            if masks is not None:
                # The same over the Gaussians the localization views see (0.01 px of weight or
                # more): no localizer can find the others, and they would skew the figure.
                seen = lifted["seen"].cpu() >= SEEN_MIN_WEIGHT
                self.localize_metrics["mask_iou_seen"] = mask_metrics(self.source_selection.cpu()[seen], truth[seen])["mask_iou"]
                self.localize_metrics["region_unseen"] = int((truth & ~seen).sum())
                # What the same lift makes of exact 2D masks (the true region's own render, > 0.5):
                # the IoU the views' resolution allows, apart from the relevance maps' errors (a
                # region a few pixels across loses its half-covered pixels and scores lower).
                exact = [splat_selection(v, truth.to(self.device)) > 0.5 for v in lifted["views"]]
                ceiling = localize_gaussians(g, self.renderer, cams, exact, reuse=lifted, **lift)["selected"]
                self.localize_metrics["mask_iou_exact_masks"] = mask_metrics(
                    rows.source_rows(g, ceiling, self.n_source).cpu(), truth)["mask_iou"]
        # The selection rendered back into each view, from the lift's kept pixel weights when there
        # was a lift (no new renders); initialization reuses these masks.
        weights = lifted["views"] if masks is not None else None
        for k, i in enumerate(views):
            if weights is not None:
                m3 = splat_selection(weights[k], selected)
            else:
                m3 = render_selection(g, self.renderer, scene.cameras[i].to(self.device), selected)
            self.localized_masks[i] = m3 > 0.5
            self.save_image(f"localize/mask3d_{i:03d}.png", overlay_mask(self.source_renders[i], m3 > 0.5))
        if selected.any() and self.writes_outputs:
            g.select(selected).save_ply(str(self.save_dir / "mask.ply"))
        self.localize_metrics = parallel.from_rank_zero(self, self.localize_metrics)  # one decision to go on
        self.phase = "initialize"

    # ----- stage 2 -------------------------------------------------------------------------------
    def rendered_mask(self, index: int) -> torch.Tensor:
        return render_selection(self.geometry, self.renderer, self.scene.cameras[index].to(self.device), self.geometry.mask) > 0.5

    def source_render(self, index: int) -> Dict[str, torch.Tensor]:
        """The source scene's (H, W) "alpha" and "depth" at view `index`, rendered once per view
        (initialization and every cycle's composite ask again; the source never changes)."""
        cache = self.__dict__.setdefault("_source_render", {})
        if index not in cache:
            out = self.render_view(index, self.source_model)
            cache[index] = {"alpha": out["alpha"], "depth": out["depth"]}
        return cache[index]

    def source_alpha(self, index: int) -> torch.Tensor:
        """(H, W) rendered opacity of the source scene at view `index`."""
        return self.source_render(index)["alpha"]

    def behind_region(self, index: int, region: torch.Tensor) -> torch.Tensor:
        """(H, W) bool: where the source at view `index` shows something farther than the region
        by more than the region's own depth range (what an object added on it may cover). The
        range is the 5th to 95th percentile of the region's depths: a few stray Gaussians the
        lift selected on the backdrop would otherwise set it (draw 260372 c11: 3.68 for a head
        at 2.1-2.5, which left only the farthest wall behind)."""
        src = self.source_render(index)
        opaque = src["alpha"] > 0.5
        depth = src["depth"][region & opaque]
        if depth.numel() == 0:
            return torch.zeros_like(opaque)
        ordered = depth.sort().values  # (torch.quantile refuses more than 16M values)
        near, far = float(ordered[int(0.05 * (len(ordered) - 1))]), float(ordered[int(0.95 * (len(ordered) - 1))])
        return opaque & (src["depth"] > far + (far - near))

    @torch.no_grad()
    def run_initialize(self) -> bool:
        """False (and nothing added) when the first edit lies outside the localized region."""
        self.set_stage("initialize")
        t0 = time.perf_counter()
        cfg, scene, g = self.cfg, self.scene, self.geometry
        views = self.localize_views
        # v_first = argmax_v Σ M_v over the editor's own 2D masks (§3.2): the view where the 2D
        # editor is most confident about the region, usually a frontal one.
        # The localized masks of the views (kept by run_localize; rendered again after a resume).
        regions = [self.localized_masks.pop(i, None) for i in views]
        regions = [self.rendered_mask(i) if r is None else r for i, r in zip(views, regions)]
        localized = dict(zip(views, regions))
        if self.masks2d is not None:
            regions = [r | m.bool().to(self.device) for r, m in zip(regions, self.masks2d)]
            areas = self.masks2d.flatten(1).sum(1).float()
        else:
            areas = torch.stack([r.sum() for r in regions]).float()
        if cfg.initialize and not bool(g.mask.all()):
            # Among the views that leave enough pixels outside the region to calibrate the
            # monocular depth on (a region that fills the view leaves none), when there are any.
            calibratable = torch.tensor([
                int(calibration_pixels(self.source_alpha(i), r, cfg.init).sum()) >= cfg.init.min_calibration_pixels
                for i, r in zip(views, regions)
            ], device=areas.device)
            if bool(calibratable.any()):
                areas = torch.where(calibratable, areas, torch.full_like(areas, -1.0))
        self.v_first = views[int(torch.argmax(areas))]

        full_edits: Dict[int, torch.Tensor] = {}  # view -> the editor's full edit of it (one seed: edited once)

        def full_edit(u: int) -> torch.Tensor:
            if u not in full_edits:
                full_edits[u] = self.guidance.edit(self.source_renders[u][None], self.source_renders[u][None], cfg.prompt,
                                                   t_start=None, seed=cfg.seed, cameras=[scene.cameras[u]])[0].to(self.device)
            return full_edits[u]

        def first_edit(u: int):
            """The editor's full edit of view `u`, and what of its change lies in the localized
            region (`coverage` None: cannot be told; a global edit leaves nothing to compare)."""
            out = full_edit(u)
            counts = None if bool(g.mask.all()) else edit_change(
                out, self.source_renders[u], localized[u], opaque=self.source_alpha(u) > 0.5,
                noise_sigmas=cfg.refine.composite_noise_sigmas, behind=self.behind_region(u, localized[u]))
            near, total, filled = counts if counts is not None else (0.0, 0.0, 0.0)
            return out, {"view": u, "coverage": near / total if total > 0 else None, "changed_px": round(total, 1),
                         "region_px": int(localized[u].sum()), "region_changed": round(filled, 3)}

        low = cfg.localization.min_edit_coverage

        def agrees(c: dict) -> bool:
            """The edit of view c["view"] lies in the selection (MIN_FILLED); False when that cannot be told."""
            cov = c["coverage"]
            return cov is not None and (cov >= low or (cov >= low / 2 and c["region_changed"] >= MIN_FILLED))

        def elsewhere(c: dict) -> bool:
            """The edit of view c["view"] lies outside the selection (a global edit cannot be told)."""
            return c["coverage"] is not None and not agrees(c)

        # Does the editor edit what localization selected? (No ground truth needed.)
        edited, check = first_edit(self.v_first)
        checked = [check]
        masks2d = [localized[u] if self.masks2d is None else self.masks2d[k].bool().to(self.device)
                   for k, u in enumerate(views)]
        overlap = torch.stack([(localized[u] & m).sum() for u, m in zip(views, masks2d)]).float().to(areas.device)
        best = views[int(torch.argmax(torch.where(areas >= 0, overlap, torch.full_like(overlap, -1.0))))]
        hides = float(overlap[views.index(self.v_first)]) < HIDES_REGION * float(overlap[views.index(best)])
        if check["changed_px"] < self.min_judged_change(self.v_first) and best != self.v_first and hides:
            # The first edit shows next to nothing (it can neither confirm nor stop the run) and
            # the view hides the region: there the relevance map, normalised to its peak, is noise
            # whose blobs can make the largest 2D mask (a patch on the donut seen from below: 3
            # pixels of it, and the edit gained 1.5 dB instead of 9.3). The view where the
            # editor's 2D mask and the selection overlap most is edited, checked and initialized
            # from instead. (A view that shows the region keeps it: a tone drift the fit cannot
            # take out can drown an edit's change in the noise, and moving cost 1.2 dB there.)
            self.v_first, (edited, check) = best, first_edit(best)
            checked.append(check)
        if elsewhere(check):
            # One edit of one view is thin evidence for throwing the run away. The view where the
            # editor's 2D masks and the selection overlap most is edited too, and decides when
            # the first edit showed almost nothing (under SHOWS_NOTHING of its change: the 2D mask
            # can be largest in a view that hides the region; initialization moves there) or only
            # just missed (coverage at least half the minimum: a placement jittered off the
            # region's edge; initialization stays with the first view).
            # The other views that can be calibrated (areas < 0: not), by overlap.
            others = [views[i] for i in torch.argsort(overlap, descending=True, stable=True).tolist()
                      if views[i] != self.v_first and areas[i] >= 0]
            if others:
                u = others[0]
                edited_u, check_u = first_edit(u)
                checked.append(check_u)
                log.info("initialize: the first edit (view %d) lies outside the selection: %s; view %d: %s",
                         self.v_first, check, u, check_u)
                if check["changed_px"] < max(SHOWS_NOTHING * check_u["changed_px"], self.min_judged_change(self.v_first)):
                    self.v_first, edited, check = u, edited_u, check_u
                elif check["coverage"] >= low / 2:
                    check = check_u
                elif agrees(check_u) and len(others) > 1:
                    # The two views disagree: the first edit lies clearly elsewhere (a full edit
                    # may place a new object pixels off; an object sticking out of its part lies
                    # mostly beside it), the second in the selection. A third view, the next by
                    # overlap, decides between them: when it agrees with the second, the run goes
                    # on, initialized from the second view. (Only a view that agrees: at leakage
                    # 1.5 the body is selected in the head's place and a third view "only just
                    # missing" it, 0.48, would let the wrong selection through.)
                    _, check_w = first_edit(others[1])
                    checked.append(check_w)
                    log.info("initialize: views %d and %d disagree; view %d: %s", self.v_first, u, others[1], check_w)
                    if agrees(check_w):
                        self.v_first, edited, check = u, edited_u, check_u
        coverage = check["coverage"]
        check["decides"] = True
        v = self.v_first
        unedited = self.source_renders[v]
        self.first_edit = edited
        self.save_image("initialize/first_view_source.png", unedited)
        self.save_image("initialize/first_view_edited.png", edited)
        self.localize_metrics["edit_coverage"] = coverage
        self.localize_metrics["edit_coverage_views"] = checked
        if elsewhere(check):
            if check["changed_px"] >= self.min_judged_change(check["view"]):
                self.add_time("initialize", time.perf_counter() - t0)
                return False
            check["too_small_to_judge"] = True
            log.info("initialize: the edit of view %d changes %.1f pixels beyond the editor's noise, too few to tell "
                     "whether it lies in the selection; the edit goes on", check["view"], check["changed_px"])
        if cfg.initialize and bool(g.mask.all()):
            log.warning("initialize: every Gaussian is selected (a global edit); no geometry is added from depth")
            self.counts["added_init"] = 0
        elif cfg.initialize:
            # The recolour path (no Gaussian added, shapes frozen) is decided on the depth of up to
            # `init.views` full edits, largest regions first: one edit can draw a thin new object a
            # few pixels off, and its depth then shows no change of shape.
            ranked = [views[i] for i in torch.argsort(areas, descending=True, stable=True).tolist() if views[i] != v]
            order = ([v] + ranked)[: max(cfg.init.views, 1)]
            found = None  # (view, edit, params, report, d_new, disparities) of the view depth initialization uses
            for k, u in enumerate(order):
                cam_u, unedited_u = scene.cameras[u], self.source_renders[u]
                if k:
                    log.info("initialize: the depth of view %d shows no change of shape; checking the edit of view %d",
                             order[k - 1], u)
                    edited = full_edit(u)  # the coverage check may have edited it already
                out = self.render_view(u)
                disp = self.depth_estimator.disparity(torch.stack([unedited_u, edited]), cameras=[cam_u, cam_u])
                params, report, d_new = new_gaussians_from_depth(
                    cam_u, unedited_u, edited, regions[views.index(u)], out["depth"], out["alpha"],
                    disp[0], disp[1], cfg.init, g.sh_degree, region_means=g.means.detach()[g.mask],
                )
                # A later view's calibration rejected for a poor fit is no evidence either way; a
                # change of shape seen without calibration (the region fills the view) is.
                shows_change = ("rejected" not in report and report["added"] > 0) or \
                    bool((report.get("uncalibrated") or {}).get("shape_changed"))
                if k == 0 or shows_change:
                    found = (u, edited, params, report, d_new, disp)
                if (k == 0 and "rejected" in report) or shows_change:
                    break
            v, edited, params, report, d_new, disp = found
            report["views_checked"] = order[: k + 1]
            if v != self.v_first:  # the view whose depth shows the change of shape is the first edited view
                self.v_first, self.first_edit = v, edited
                self.save_image("initialize/first_view_source.png", self.source_renders[v])
                self.save_image("initialize/first_view_edited.png", edited)
            self.init_report = report
            if "rejected" in report:
                self.warn(f"initialize: depth calibration rejected in view {v}: {report['rejected']}; no Gaussians are "
                          "added from depth, refinement densifies the region instead")
                self.counts["added_init"] = 0
            elif d_new is None:  # no pixels to calibrate on, and the two disparities show no change of shape
                self.counts["added_init"] = 0
                log.info("initialize: view %d leaves no pixels to calibrate its depth on; its monocular depth, edited "
                         "against unedited, shows no change of shape (%s)", v, report["uncalibrated"])
            else:
                n = params["means"].shape[0]
                if n:
                    rows.append(g, params, optimizer=self.optimizers().optimizer, mask=True, generation=1)
                    # Does the edit recolour the region besides adding to it? (set_trainable)
                    cam = scene.cameras[v].to(self.device)
                    region_v = regions[views.index(v)]
                    report["recoloured_fraction"] = recoloured_fraction(
                        edited, self.source_renders[v], region_v,
                        render_selection(g, self.renderer, cam, g.generation > 0) > 0.05,
                        depth_calibration_pixels(self.source_alpha(v), region_v, disp[0], disp[1], cfg.init),
                        cfg.refine.composite_noise_sigmas)
                    if report["recoloured_fraction"] is not None:
                        log.info("initialize: the first edit recolours %.2f of the region beside the added Gaussians "
                                 "(the source keeps its colours below system.refine.min_recoloured_fraction=%s)",
                                 report["recoloured_fraction"], cfg.refine.min_recoloured_fraction)
                self.counts["added_init"] = n
                self.save_image("initialize/depth_new.png", _normalize(1.0 / d_new.clamp_min(1e-6)))
                self.save_image("initialize/initialized_render.png", self.render_view(v)["rgb"].clamp(0, 1))
                log.info(
                    "initialize: added %d Gaussians from the depth of view %d (%d region pixels without a depth change "
                    "beyond %.3f, %d skipped by stride, %d too far from the region, %d over the cap of %d)", n, v,
                    report["skipped_unchanged"], report["depth_threshold"], report["skipped_by_stride"],
                    report.get("skipped_far_from_region", 0), report["skipped_by_cap"], cfg.init.max_new,
                )
            self.save_image("initialize/depth_unedited.png", _normalize(disp[0]))
            self.save_image("initialize/depth_edited.png", _normalize(disp[1]))
        else:
            self.counts["added_init"] = 0
        self.edited_views = [v]
        self.refine_start_count = g.num_gaussians
        self.counts.setdefault("densified", 0)
        if not self.shape_may_change:
            log.info("initialize: the depth of view %d shows no change of shape: refinement recolours the region's "
                     "Gaussians and adds none", v)
        self.set_trainable()
        self.add_time("initialize", time.perf_counter() - t0)
        self.phase = "refine"
        return True

    def min_judged_change(self, index: int) -> float:
        """Pixels of change a full edit of view `index` needs for its coverage to stop the run."""
        cam = self.scene.cameras[index]
        return MIN_JUDGED_CHANGE * cam.width * cam.height

    def set_trainable(self) -> None:
        g, r = self.geometry, self.cfg.refine
        # "editable" = mask | generation > 0, re-evaluated at every backward pass.
        g.set_trainable_mask(None if r.optimize_all else "editable")
        if r.optimize_all:
            return
        groups = self.optimizers().optimizer.param_groups
        if self.shape_may_change:
            fixed = [*r.source_fixed, *(SHAPE_FREE_PARAMS if self.adds_only else ())]
            if fixed:
                g.set_added_only(fixed)
            if "means" in fixed:
                # Only the added rows move (the source's are fixed), so only they get the faster rate.
                for group in groups:
                    if group["name"] == "means":
                        group["lr"] *= r.added_position_lr_scale
        else:
            # A recolour: the region's Gaussians keep their shape and opacity, only their colours
            # train (left free, they grow and move into the unedited surroundings).
            for group in groups:
                group["lr"] *= r.recolour_lr_scale if group["name"] in SHAPE_FREE_PARAMS else 0.0

    # ----- stage 3 -------------------------------------------------------------------------------
    @torch.no_grad()
    def edit_cycle_views(self, cycle: int) -> None:
        r, cfg, scene = self.cfg.refine, self.cfg, self.scene
        self.set_stage(f"refine {cycle + 1}/{r.cycles}: editing views")
        t0 = time.perf_counter()
        if cycle == 0:
            frontal = self.v_first
        else:
            gen = torch.Generator().manual_seed(cfg.seed * 7919 + cycle)
            if r.next_frontal == "frontier":
                frontal = frontier_view(scene.cameras, self.edited_views, r.m, scene.train_indices, gen)
            else:  # the paper's choice
                frontal = self.edited_views[int(torch.randint(len(self.edited_views), (1,), generator=gen))]
        near = nearest_cameras(scene.cameras, frontal, r.m, scene.train_indices)
        views = [frontal] + near  # in order of distance
        first_view = r.first_cycle_first_view if self.shape_may_change else "full"
        if first_view == "skip" and not near:
            first_view = "full"  # m = 0: the first view is all the first cycle has
        full_edit_is_target = cycle == 0 and first_view == "full"
        if cycle == 0 and first_view == "skip":
            views = near  # the first view stays among the edited views (set at initialization)

        def targets(ks: List[int]) -> torch.Tensor:
            # Every view is edited from a render of the same scene state, so all go to the editor in
            # one call (batched by guidance.batch_size), each with its own seed as if edited alone;
            # with several processes, each edits its share of the views (map_views).
            mine = [views[k] for k in ks]
            to_edit = [j for j in mine if not (full_edit_is_target and j == self.v_first)]
            edited = {}
            if to_edit:
                current = torch.stack([self.as_image(self.render_view(j)["rgb"], "the current renders") for j in to_edit])
                out = self.guidance.edit(
                    current, torch.stack([self.source_renders[j] for j in to_edit]), cfg.prompt,
                    t_start=self.start_timestep(cycle), seed=[self.view_seed(cycle, j) for j in to_edit],
                    cameras=[scene.cameras[j] for j in to_edit],
                )
                edited = dict(zip(to_edit, out.to(self.device)))
            if full_edit_is_target and self.v_first in mine:
                edited[self.v_first] = self.first_edit  # the first, full edit is this cycle's frontal target
            return torch.stack([self.composite(j, edited[j]) for j in mine])

        self.cycle_targets = self.map_views(len(views), targets, self.source_renders[frontal].shape)
        self.cycle_views = views
        self.targets_cycle = cycle
        self.edited_views = sorted(set(self.edited_views) | set(views))
        shown = [[self.source_renders[j], self.cycle_targets[k]] for k, j in enumerate(views[:6])]
        self.save_image_grid(f"refine/cycle{cycle}_edited_views.png", shown)
        start = cycle == 0 and r.recolour_from_edits
        if self.gated_recolour and (r.min_edit_blend > 0 or start):
            # The views' pixel weights, one render each, for the gate and the colour start (the
            # geometry does not change in between: a recolour trains colours only).
            weights = [self.renderer.pixel_weights(self.geometry, scene.cameras[j].to(self.device)) for j in views]
            self.gate_recolour(weights)
            if start:
                self.recolour_from_edits(weights)
        self.add_time("refine_edit", time.perf_counter() - t0)

    @property
    def gated_recolour(self) -> bool:
        """A recolour of the localized selection only: its Gaussians are judged by the gate
        (`gate_recolour`) and may start from the edited colours (`recolour_from_edits`)."""
        return not (self.shape_may_change or self.cfg.refine.optimize_all or not self.cfg.localize)

    @torch.no_grad()
    def gate_recolour(self, weights: List[PixelWeights]) -> None:
        """A recolour: the selected Gaussians that the edited views so far do not recolour
        (`refine.min_edit_blend`), or that are a part of their own (`refine.distinct_part_blend`),
        go back to their source colours and stop training; one whose views later recolour it trains
        again. `weights`: the pixel weights of this cycle's views. Two gathers per view."""
        r, g = self.cfg.refine, self.geometry
        if r.min_edit_blend <= 0:
            return
        if self.blend_votes is None or self.blend_votes.shape[1] != g.num_gaussians:
            self.blend_votes = torch.zeros(2, g.num_gaussians, device=self.device)
        for k, (j, view) in enumerate(zip(self.cycle_views, weights)):
            blend = edit_blend(self.cycle_targets[k], self.source_renders[j]).clamp(0, 1)
            self.blend_votes[0] += view.gather(blend)
            self.blend_votes[1] += view.gather(torch.ones_like(blend))
        num, den = self.blend_votes
        src = g.source_index
        selected = (src >= 0) & self.source_selection.to(self.device)[src.clamp_min(0)]
        seen = selected & (den >= SEEN_MIN_WEIGHT)  # one no edited view sees is not judged: it keeps training
        takes = (selected & ~seen) | recoloured(num, den, seen, r.min_edit_blend, r.gate_reference_quantile)
        if r.distinct_part_blend > 0:
            colours = sh_to_rgb(self.source_model.sh_dc.detach()[src.clamp_min(0)]).clamp(0, 1)
            distinct = distinct_parts(colours, num / den.clamp_min(1e-12), seen, r.distinct_part_blend)
            takes &= ~distinct
            self.counts["recolour_distinct"] = int(distinct.sum())
        rows.restore(g, self.source_model, g.mask & ~takes, SHAPE_FREE_PARAMS, self.optimizers())
        g.mask.copy_(takes)
        self.counts["recolour_declined"] = int((selected & ~takes).sum())
        self.counts["recolour_taken"] = int((seen & takes).sum())

    @torch.no_grad()
    def recolour_from_edits(self, weights: List[PixelWeights]) -> None:
        """A recolour (`refine.recolour_from_edits`): move the base colour (SH degree 0) of each
        editable Gaussian that this cycle's views recolour fully (`recolour_start_min_blend`) by
        the rendering-weighted mean of (target - source render) over its pixels in those views
        (`weights`: their pixel weights), which edit the source scene (the first cycle). Where a
        pixel's Gaussians all move so, the pixel's colour moves by the same amount times its
        opacity. One gather per view."""
        r, g = self.cfg.refine, self.geometry
        sums = torch.zeros(g.num_gaussians, 4, device=self.device)
        for k, (j, view) in enumerate(zip(self.cycle_views, weights)):
            change = self.cycle_targets[k].to(self.device) - self.source_renders[j].to(self.device)
            sums += view.gather(torch.cat([change, torch.ones_like(change[..., :1])], -1))
        moves = g.mask & (g.source_index >= 0) & (sums[:, 3] >= SEEN_MIN_WEIGHT)
        if self.blend_votes is not None:  # the gate ran: the rim it let through trains from the source
            num, den = self.blend_votes
            moves &= num >= r.recolour_start_min_blend * den
        g.sh_dc.data[moves] += sums[moves, :3] / sums[moves, 3:] / SH_C0
        self.counts["recolour_started"] = int(moves.sum())

    def view_seed(self, cycle: int, index: int) -> int:
        """The editor's seed for view `index` in refinement cycle `cycle`."""
        return self.cfg.seed + 1000 * (cycle + 1) + index

    def source_region(self, index: int) -> torch.Tensor:
        """(H, W) render of the localized Gaussians of the source scene at view `index`."""
        cam = self.scene.cameras[index].to(self.device)
        return render_selection(self.source_model, self.renderer, cam, self.source_selection.to(self.device))

    @property
    def shape_may_change(self) -> bool:
        """False when depth initialization ran, was trusted and found no change of shape."""
        report = getattr(self, "init_report", None)
        return not (self.cfg.initialize and report is not None and "rejected" not in report and report["added"] == 0)

    @property
    def adds_only(self) -> bool:
        """True when depth initialization added Gaussians and the first edit recolours under
        `refine.min_recoloured_fraction` of the region beside them: the source keeps its colours."""
        report = getattr(self, "init_report", None) or {}
        fraction = report.get("recoloured_fraction")
        return fraction is not None and fraction < self.cfg.refine.min_recoloured_fraction

    def composite(self, index: int, edited: torch.Tensor) -> torch.Tensor:
        """The target of view `index`: `edited` where the edit is (composite_target), the source
        render elsewhere."""
        r = self.cfg.refine
        if not r.composite or r.optimize_all or not self.cfg.localize:
            return edited
        added = None
        if self.shape_may_change:
            cam = self.scene.cameras[index].to(self.device)
            added = render_selection(self.geometry, self.renderer, cam, self.geometry.generation > 0)
        return composite_target(edited, self.source_renders[index], self.source_region(index), added,
                                r.composite_dilate, r.composite_noise_sigmas, r.composite_full_coverage,
                                opaque=self.source_alpha(index) > 0.5, min_blend=r.composite_min_blend)

    def training_step(self, batch, batch_idx):
        if self.phase == "localize":
            self.run_localize()
            agreement = self.localize_metrics.get("view_agreement")
            if not bool(self.geometry.mask.any()):
                return self.stop_unchanged(
                    "empty selection", "localize: no Gaussian was selected for the prompt; nothing to edit. Try a lower "
                    "system.localization.gamma or system.localization.mask_threshold.")
            if agreement is not None and agreement < self.cfg.localization.min_view_agreement:
                return self.stop_unchanged(
                    "views disagree", f"localize: the views disagree about the region (its 2D masks overlap the "
                    f"lifted 3D mask by IoU {agreement:.2f} in the better half of the views, below "
                    f"system.localization.min_view_agreement={self.cfg.localization.min_view_agreement}); the "
                    "instruction names nothing the editor finds consistently.")
            self.save_stage_checkpoint()  # a kill later in this step resumes after localization
        if self.phase == "initialize":
            initialized = parallel.from_rank_zero(self, self.run_initialize())  # one decision to go on
            if not initialized:
                checked, lc = self.localize_metrics["edit_coverage_views"], self.cfg.localization
                decided = next(c for c in checked if c.get("decides"))
                other = next((c for c in checked if c is not decided), None)
                note = "" if other is None else (
                    f" (view {other['view']}, edited first, showed almost nothing of the edit)" if other is checked[0] else
                    f" (view {other['view']}, where the editor's 2D masks and the selection overlap most, puts "
                    f"{other['coverage'] or 0:.2f} in it: the editor edits different things in different views)")
                return self.stop_unchanged(
                    "edit outside the region", f"initialize: the first edited view ({decided['view']}) changes the "
                    f"image outside the localized region: a fraction {decided['coverage']:.2f} of its change beyond "
                    f"the editor's noise lies in the region, below system.localization.min_edit_coverage="
                    f"{lc.min_edit_coverage}, and it changes {decided['region_changed']:.2f} of the region's pixels{note}; "
                    "localization selected something other than what the editor edits.")
            parallel.check_agree(self, "initialization", [self.geometry.num_gaussians, self.v_first])
            self.save_stage_checkpoint()
        if self.phase != "refine":
            return None
        r = self.cfg.refine
        step = self.global_step
        cycle, it = divmod(step, r.iterations_per_cycle)
        if cycle >= r.cycles:
            return None
        if self.targets_cycle != cycle:
            self.edit_cycle_views(cycle)
        self.set_stage(f"refine {cycle + 1}/{r.cycles}")
        t0 = time.perf_counter()
        # Stateless per-step choice of view, so a resumed run makes the same choices.
        gen = torch.Generator().manual_seed(self.cfg.seed * 104729 + step)
        n_views = min(r.views_per_step or parallel.world_size(self), len(self.cycle_views))
        if n_views == 1:
            ks = [int(torch.randint(len(self.cycle_views), (1,), generator=gen))]
        else:
            ks = torch.randperm(len(self.cycle_views), generator=gen)[:n_views].tolist()
        # A trusted depth initialization that found no change of shape (a recolour): the existing
        # Gaussians are recoloured, none are added.
        densify = self.cfg.densify if self.shape_may_change else None
        if n_views == 1 and parallel.world_size(self) == 1:
            self.optimize_on(self.cycle_views[ks[0]], self.cycle_targets[ks[0]], densify=densify, step=it)
        else:  # the step's views shared out over the processes of a run on several devices
            self.optimize_on_views([self.cycle_views[k] for k in ks], self.cycle_targets[ks], densify=densify, step=it)
        if densify is not None and densify.densifies_at(it, r.iterations_per_cycle - 1):
            parallel.agree_on_rng(self)  # split samples: rank 0's draws on every process
        rep = None if densify is None else densify.refine(
            self.geometry, it, self.scene.extent, self.optimizers().optimizer,
            last_step=r.iterations_per_cycle - 1, base_count=self.refine_start_count,
        )
        if rep is not None:
            parallel.check_agree(self, f"the densification of step {step}", [self.geometry.num_gaussians])
            self.counts["densified"] = self.counts.get("densified", 0) + rep["cloned"] + rep["split"]
            self.counts["pruned"] = self.counts.get("pruned", 0) + rep["pruned"]
        self.add_time("refine_train", time.perf_counter() - t0)
        if step == self.total_steps - 1:
            self.finish_refinement()
        return None

    def stop_unchanged(self, reason: str, message: str) -> None:
        """The safe path when localization cannot be trusted: warn, write the source scene out
        unchanged (with metrics.json `stopped`) and end the run."""
        self.warn(message + " The source scene is written out unchanged.")
        self.phase = "done"
        self.trainer.should_stop = True
        self.write_outputs({"stopped": reason, **self.localize_metrics})
        return None

    @torch.no_grad()
    def prune_useless_added(self) -> int:
        """Remove the Gaussians this edit added that contribute nothing to the training views
        (RefineConfig.prune_*); returns how many."""
        r, g = self.cfg.refine, self.geometry
        if not r.prune_added:
            return 0
        cams = [self.scene.cameras[i].to(self.device) for i in self.scene.train_indices]
        useless = rows.spare_last_descendants(g, useless_added(g, self.renderer, cams, r.prune_min_weight, r.prune_min_opacity))
        useless = parallel.from_rank_zero(self, useless)  # every process prunes the same rows
        n = int(useless.sum())
        if n:
            rows.keep(g, ~useless, self.optimizers().optimizer)
        log.info("refine: pruned %d of the %d added Gaussians that contribute nothing", n, int((g.generation > 0).sum()) + n)
        return n

    def finish_refinement(self) -> None:
        """The end of refinement, inside its last step: prune the useless added Gaussians. Part of
        the step, not of on_train_end: a run stopped earlier (trainer.max_steps) then checkpoints
        the state refinement goes on from, so resuming it with more steps gives the whole run's
        scene (pruned at the end, on_train_end, its checkpoint held the pruned scene and the
        resumed run densified from that and skipped the final prune)."""
        t0 = time.perf_counter()
        n = self.prune_useless_added()
        self.add_time("prune", time.perf_counter() - t0)
        self.counts["pruned_added"] = n
        self.counts["pruned"] = self.counts.get("pruned", 0) + n
        if self.counts.get("recolour_taken") == 0:  # the gate ran and let no Gaussian an edited view sees through
            self.warn(f"refine: the edited views recolour none of the {self.counts.get('selected', 0):,} selected "
                      f"Gaussians by system.refine.min_edit_blend={self.cfg.refine.min_edit_blend} of the edit's colour, "
                      "so each kept its source colours and the scene comes out unchanged; a lower min_edit_blend lets "
                      "the edit through")

    def on_train_end(self) -> None:
        if self.phase == "done":
            return
        extra = dict(self.localize_metrics) if hasattr(self, "localize_metrics") else {}
        extra["v_first"] = self.v_first
        extra["edited_views"] = len(self.edited_views)
        extra["t_starts"] = [self.start_timestep(c) for c in range(self.cfg.refine.cycles)]  # the schedule this edit got
        if getattr(self, "init_report", None):
            extra["init"] = self.init_report
        self.write_outputs(extra)

    def evaluation_region(self, index: int):
        region = super().evaluation_region(index)
        if region is None and self.source_selection is not None and bool(self.source_selection.any()):
            # No ground truth: what lies outside this run's own (dilated) 3D mask should not change.
            region = ~dilate(self.source_region(index) > 0.01, 2)
        return region

    # ----- checkpoint ----------------------------------------------------------------------------
    def extra_state(self) -> dict:
        return {
            **super().extra_state(),
            "phase": self.phase,
            "v_first": self.v_first,
            "cycle_targets": None if self.cycle_targets is None else self.cycle_targets.cpu(),
            "cycle_views": list(self.cycle_views),
            "targets_cycle": self.targets_cycle,
            "edited_views": list(self.edited_views),
            "first_edit": None if self.first_edit is None else self.first_edit.cpu(),
            "refine_start_count": self.refine_start_count,
            "source_selection": None if self.source_selection is None else self.source_selection.cpu(),
            "localize_views": list(getattr(self, "localize_views", [])),
            "localize_metrics": dict(getattr(self, "localize_metrics", {})),
            "init_report": getattr(self, "init_report", None),
            "blend_votes": None if self.blend_votes is None else self.blend_votes.cpu(),
            # The 2D masks choose the first view: needed by a resume between localize and initialize.
            "masks2d": self.masks2d.cpu() if self.phase == "initialize" and self.masks2d is not None else None,
        }

    def load_extra_state(self, state: dict) -> None:
        super().load_extra_state(state)
        if not state:
            return
        self.phase = state["phase"]
        self.v_first = state["v_first"]
        self.cycle_targets = state["cycle_targets"]
        self.cycle_views = state["cycle_views"]
        self.targets_cycle = state["targets_cycle"]
        self.edited_views = state["edited_views"]
        self.first_edit = state["first_edit"]
        self.refine_start_count = state["refine_start_count"]
        self.source_selection = state.get("source_selection")
        self.localize_views = state["localize_views"]
        self.localize_metrics = state["localize_metrics"]
        self.init_report = state["init_report"]
        self.masks2d = state.get("masks2d")
        self.blend_votes = state.get("blend_votes")

    def on_train_start(self) -> None:
        if self.masks2d is not None:
            self.masks2d = self.masks2d.to(self.device)
        if self.cycle_targets is not None:
            self.cycle_targets = self.cycle_targets.to(self.device)
        if self.first_edit is not None:
            self.first_edit = self.first_edit.to(self.device)
        if self.blend_votes is not None:
            self.blend_votes = self.blend_votes.to(self.device)


def _normalize(x: torch.Tensor) -> torch.Tensor:
    x = x.float()
    lo, hi = x.min(), x.max()
    return ((x - lo) / (hi - lo).clamp_min(1e-8))[..., None].expand(*x.shape, 3)
