"""`regional-edit`: the schedule localize → initialize → refinement cycles → finish (DESIGN.md §3).
What differs between a recolour and an addition is the strategy chosen after initialization
(gs_regional/stages/strategies.py); the stages' own logic lives beside each stage in gs_regional/stages/."""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Dict, List, Optional

import torch

from gs_regional.config import ConfigError, check_saved_config, need
from gs_regional.stages.ablation import AblationConfig
from gs_regional.stages.change import recoloured_fraction
from gs_regional.stages.first_view import FirstView, check_edit, choose_first_view, mask_areas, stop_message
from gs_regional.stages.initialize import (
    HOLE_MAX_DISTANCE, InitConfig, calibration_pixels, depth_calibration_pixels, initialize_from_views,
    new_gaussians_in_holes,
)
from gs_regional.stages.localize import (
    LOCALIZATION_FILE, LocalizeConfig, covered, localize_selection, render_selection, splat_selection, views_disagree,
)
from gs_regional.stages.prune import prune_useless_added
from gs_regional.stages.state import EditState
from gs_regional.stages.strategies import EditStrategy, RefineConfig, choose_strategy, is_recolour_edge
from gs_regional.stages.views import cycle_views, spread_subset
from gs_regional.geometry import rows
from gs_regional.geometry.strategy import DensifyStrategy
from gs_regional.utils.image import dilate
from gs_regional.utils.visualize import overlay_mask
from gs_regional.registry import find, register
from gs_regional.systems import parallel
from gs_regional.systems.edit_base import EditSystemBase

log = logging.getLogger(__name__)

STOP_AFTER = (None, "localize")  # system.stop_after


@register("regional-edit")
class RegionalEdit(EditSystemBase):
    @dataclass
    class Config(EditSystemBase.Config):
        MOVED_KEYS: ClassVar[Dict[str, str]] = {
            "localize": "system.ablation.localize", "initialize": "system.ablation.initialize",
            "localize_with_truth": "system.ablation.localize_with_truth",
        }
        depth_type: str = "depth-anything"
        depth: dict = field(default_factory=dict)
        # "localize": localization runs, metrics.json gets its figures (mask_iou ... with a known
        # edit, view_agreement) and the run ends with the source written unchanged; null: the edit.
        stop_after: Optional[str] = None
        # A selection made by the caller (gs_regional.edit(selection=...)): a .npy/.npz of one bool
        # per source Gaussian, used in place of localization's lift; null: localization selects.
        selection_file: Optional[str] = None
        localization: LocalizeConfig = field(default_factory=LocalizeConfig)
        init: InitConfig = field(default_factory=InitConfig)
        refine: RefineConfig = field(default_factory=RefineConfig)
        # Densification during refinement, once a cycle at its middle, of the editable Gaussians only,
        # at most `budget` more than when refinement began; the threshold (2.5x 3DGS's) sits at the
        # knee of the compactness sweep: fewer Gaussians cost quality, more add none (docs/method.md).
        densify: DensifyStrategy = field(
            default_factory=lambda: DensifyStrategy(
                start=0, stop=None, every=None, rounds=1, opacity_reset_every=0, max_gaussians=None, budget=20000,
                child_generation=1, grad_threshold=5e-4, prune_only_added=True,
            )
        )
        ablation: AblationConfig = field(default_factory=AblationConfig)

    # Settings a resume must keep (launch.py refuses a change): the step -> cycle mapping, and the
    # stages that a checkpoint has usually passed already (a change would be silently ignored).
    RESUME_FIXED_KEYS: ClassVar[tuple] = (
        "refine.iterations_per_cycle", "ablation.localize", "ablation.plain_vote", "localization", "ablation.initialize",
        "init", "refine.source_fixed", "refine.min_recoloured_fraction")

    def __init__(self, cfg=None, resumed: bool = False) -> None:
        super().__init__(cfg, resumed=resumed)
        self.check_settings()  # before configure() loads the priors
        self.configure()
        self.depth_estimator = None
        if self.cfg.ablation.initialize:  # loads after the guidance, on the same thread
            self.priors.start("depth_estimator", find(self.cfg.depth_type, kind="depth", key="system.depth_type"),
                              self.cfg.depth)
        self.state = EditState()
        self.given_selection: Optional[torch.Tensor] = None  # system.selection_file, read by check_scene
        self.strategy: Optional[EditStrategy] = None  # chosen after initialization

    def check_settings(self) -> None:
        """Settings that cannot work fail at start-up, naming the key and the allowed range."""
        cfg = self.cfg
        n_t = int(getattr(find(cfg.guidance_type, kind="guidance", key="system.guidance_type"), "num_train_timesteps", 1000))
        need(cfg.stop_after in STOP_AFTER, "system.stop_after", "null or 'localize'", cfg.stop_after)
        cfg.ablation.check("system.ablation", n_t)
        cfg.localization.check("system.localization", n_t)
        cfg.init.check("system.init")
        cfg.refine.check("system.refine", n_t, cfg.ablation.constant_t)
        cfg.densify.check("system.densify")

    def check_scene(self) -> None:
        if self.cfg.ablation.localize_with_truth and self.scene.ground_truth is None:
            raise ConfigError("system.ablation.localize_with_truth=true needs a scene with a known edit (a ground truth: "
                              "data_type synthetic-scene or splat-truth)")
        if self.cfg.selection_file:
            self.given_selection = read_selection(self.cfg.selection_file, self.geometry.num_gaussians)
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
        if self.cfg.ablation.localize and lc.gamma > 0:
            stages.append((len(spread_subset(train, lc.max_views)),
                           f"localization views (system.localization.max_views={lc.max_views})"))
        views, what = min(stages)
        if n > views:
            raise ConfigError(f"trainer.devices / --gpu ask for {n} processes, but the edit has only {views} {what} "
                              f"to share out among them: give at most {views} devices")

    @property
    def total_steps(self) -> int:
        return self.cfg.refine.cycles * self.cfg.refine.iterations_per_cycle

    # ----- stage 1 -------------------------------------------------------------------------------
    @torch.no_grad()
    def run_localize(self) -> None:
        self.set_stage("localize")
        t0 = time.perf_counter()
        cfg, lc, scene, s, g = self.cfg, self.cfg.localization, self.scene, self.state, self.geometry
        views = spread_subset(scene.train_indices, lc.max_views)
        s.localize_views, s.localize_metrics = views, {}
        loc, masks = None, None
        if self.given_selection is not None:  # the caller's selection: no relevance maps, no lift
            selected = self.given_selection.to(self.device)
        elif not cfg.ablation.localize or lc.gamma <= 0:
            selected = torch.ones(g.num_gaussians, dtype=torch.bool, device=self.device)
        else:
            images = torch.stack([self.source_renders[i] for i in views])
            cams = [scene.cameras[i] for i in views]
            # The views shared out over the processes of a run on several devices (map_views).
            masks = self.map_views(len(views), lambda ks: self.guidance.mask(
                images[ks], cfg.prompt, threshold=lc.gamma, blur_sigma=lc.blur_sigma, timestep=lc.timestep,
                samples=lc.samples, seed=cfg.seed, cameras=[cams[k] for k in ks],
            ), images.shape[1:3])
            loc = localize_selection(g, self.renderer, [c.to(self.device) for c in cams], masks, images, lc, scene.extent,
                                     cfg.ablation.plain_vote, agree=lambda sel: parallel.from_rank_zero(self, sel))
            selected, s.localize_metrics = loc.selected, dict(loc.metrics)  # every process edits one selection
            for k, i in enumerate(views):
                self.save_image(f"localize/mask2d_{i:03d}.png", overlay_mask(self.source_renders[i], masks[k]))
        if cfg.ablation.localize_with_truth:  # check_scene made sure there is a truth
            selected = self.scene.ground_truth.region.to(self.device)
        g.mask.copy_(selected)
        self.save_localization(loc, selected, masks, views)
        # The localized region as rows of the source scene: what the composite and the evaluation
        # render from the source, however densification and pruning move the rows later.
        s.source_selection = rows.source_rows(g, selected, self.n_source)
        self.counts["selected"] = int(selected.sum())
        s.masks2d = masks
        self.add_time("localize", time.perf_counter() - t0)
        if self.truth is not None:
            s.localize_metrics.update(self.truth.localization(g, s.source_selection, self.n_source, *(() if loc is None else (
                loc.lifted["seen"], loc.lifted["views"], lambda exact: loc.relift(g, self.renderer, exact)))))
        # The selection rendered back into each view, from the lift's kept pixel weights when there
        # was a lift (no new renders); initialization reuses these masks.
        for k, i in enumerate(views):
            if loc is not None:
                m3 = splat_selection(loc.lifted["views"][k], selected)
            else:
                m3 = render_selection(g, self.renderer, scene.cameras[i].to(self.device), selected)
            s.localized_masks[i] = m3 > 0.5
            self.save_image(f"localize/mask3d_{i:03d}.png", overlay_mask(self.source_renders[i], m3 > 0.5))
        if selected.any() and self.writes_outputs:
            g.select(selected).save_ply(str(self.save_dir / "mask.ply"))
        s.localize_metrics = parallel.from_rank_zero(self, s.localize_metrics)  # one decision to go on
        s.phase = "initialize"

    def save_localization(self, loc, selected: torch.Tensor, masks, views: List[int]) -> None:
        """save/localization.npz, the evidence a selection is re-made from without the editor
        (gs_regional.localize, the studio): `selected` (N,) bool; with a lift also its `scores`
        (N,) float32, `threshold` (the lift's mask_threshold), `expand_radius` (world units) and
        `neighbourhood` (N, k) int32 rows; `views` and their 2D `masks` (V, H, W) bool."""
        if not self.writes_outputs:
            return
        import numpy as np

        out = {"selected": selected.cpu().numpy(), "views": np.asarray(views, dtype=np.int32)}
        if masks is not None:
            out["masks"] = (masks > 0.5).cpu().numpy()
        if loc is not None:
            out.update(scores=loc.lifted["scores"].float().cpu().numpy(), threshold=np.float64(loc.lift["threshold"]),
                       expand_radius=np.float64(self.cfg.localization.expand_radius * self.scene.extent))
            if loc.lifted["neighbourhood"] is not None:
                out["neighbourhood"] = loc.lifted["neighbourhood"].to(torch.int32).cpu().numpy()
        np.savez(self.save_path(LOCALIZATION_FILE), **out)

    # ----- stage 2 -------------------------------------------------------------------------------
    def rendered_mask(self, index: int, faint: bool = False) -> torch.Tensor:
        """(H, W) bool: the pixels of view `index` the selection covers by more than half (`covered`;
        with `faint`, by half of its most in a view where it covers none by half)."""
        cam = self.scene.cameras[index].to(self.device)
        return covered(render_selection(self.geometry, self.renderer, cam, self.geometry.mask), faint)

    def checked_region(self, index: int, localized: torch.Tensor) -> torch.Tensor:
        """What a full edit of view `index` is checked against: the `localized` pixels (covered by
        half), or, where the selection covers none by half, those it covers by half of its most
        (`covered(..., faint=True)`, rendered only then)."""
        return localized if bool(localized.any()) else self.rendered_mask(index, faint=True)

    @torch.no_grad()
    def run_initialize(self) -> Optional[FirstView]:
        """The first view (§3.2 step 1), then new Gaussians from its depth; the returned first view
        says whether its edit lies outside the localized region (`stop`: nothing added)."""
        self.set_stage("initialize")
        t0 = time.perf_counter()
        cfg, s, g = self.cfg, self.state, self.geometry
        views = s.localize_views
        # The localized masks of the views (kept by run_localize; rendered again after a resume).
        regions = [s.localized_masks.pop(i, None) for i in views]
        regions = [self.rendered_mask(i) if r is None else r for i, r in zip(views, regions)]
        localized = dict(zip(views, regions))
        if s.masks2d is not None:
            regions = [r | m.bool().to(self.device) for r, m in zip(regions, s.masks2d)]
        calibratable = None if not cfg.ablation.initialize or bool(g.mask.all()) else [
            int(calibration_pixels(self.source_alpha(i), r, cfg.init).sum()) >= cfg.init.min_calibration_pixels
            for i, r in zip(views, regions)]
        areas = mask_areas(regions, s.masks2d, calibratable)
        masks2d = [localized[u] if s.masks2d is None else s.masks2d[k].bool().to(self.device) for k, u in enumerate(views)]
        whole = bool(g.mask.all())
        first = choose_first_view(
            views, areas, localized, masks2d, views[int(torch.argmax(areas))], self.full_edit,
            lambda u, out: check_edit(u, out, self.source_renders[u], self.checked_region(u, localized[u]),
                                      self.source_alpha(u), self.source_render(u)["depth"], global_edit=whole),
            cfg.localization.min_edit_coverage)
        s.v_first, s.first_edit = first.view, first.edited
        self.save_image("initialize/first_view_source.png", self.source_renders[first.view])
        self.save_image("initialize/first_view_edited.png", first.edited)
        s.localize_metrics["edit_coverage"] = first.decided.coverage
        s.localize_metrics["edit_coverage_views"] = [c.as_dict() for c in first.checks]
        if first.stop:
            self.__dict__.pop("_full_edits", None)
            self.add_time("initialize", time.perf_counter() - t0)
            return first
        self.counts["added_init"] = 0
        if cfg.ablation.initialize and whole:
            log.warning("initialize: every Gaussian is selected (a global edit); no geometry is added from depth")
        elif cfg.ablation.initialize:
            self.initialize_from_depth(views, regions, areas, first.own.changed_px)
        s.edited_views = [s.v_first]
        s.refine_start_count = g.num_gaussians
        self.counts.setdefault("densified", 0)
        self.strategy = self.choose_strategy()
        if not self.strategy.shape_may_change:
            log.info("initialize: the depth of view %d shows no change of shape: refinement recolours the region's "
                     "Gaussians and adds none, unless its edits recolour next to none of them", s.v_first)
        groups = self.optimizers().optimizer.param_groups
        self.strategy.set_trainable(g, groups)
        for group in groups:  # a longer cycle moves the scene no further (refine.rate_iterations)
            group["lr"] *= cfg.refine.rate_factor
        self.__dict__.pop("_full_edits", None)  # (each view's full edit is needed by this stage only)
        self.add_time("initialize", time.perf_counter() - t0)
        s.phase = "refine"
        return first

    def initialize_from_depth(self, views: List[int], regions: List[torch.Tensor], areas: torch.Tensor,
                              changed_px: float) -> None:
        """§3.2 steps 2-5 (stages/initialize.py), from the view among the first and the next
        largest regions' (`init.views`) whose depth shows the most change of shape (`changed_px`:
        the pixels the first view's edit changes); adds the new Gaussians."""
        cfg, s, g, scene = self.cfg, self.state, self.geometry, self.scene
        v = s.v_first
        ranked = [views[i] for i in torch.argsort(areas, descending=True, stable=True).tolist() if views[i] != v]
        order = ([v] + ranked)[: max(cfg.init.views, 1)]
        found = initialize_from_views(
            order, lambda u: s.first_edit if u == v else self.full_edit(u), lambda u: self.source_renders[u],
            lambda u: scene.cameras[u], self.render_view, lambda images, cams: self.depth_estimator.disparity(images, cameras=cams),
            lambda u: regions[views.index(u)], cfg.init, g.sh_degree, region_means=g.means.detach()[g.mask],
            changed_px=changed_px)
        v, edited, params, report, d_new, disp = (found.view, found.edited, found.params, found.report, found.d_new,
                                                  found.disparities)
        if v != s.v_first:  # the view whose depth shows the most change of shape is the first edited view
            s.v_first, s.first_edit = v, edited
            self.save_image("initialize/first_view_source.png", self.source_renders[v])
            self.save_image("initialize/first_view_edited.png", edited)
        s.init_report = report
        if "rejected" in report:
            self.warn(f"initialize: depth calibration rejected in view {v}: {report['rejected']}; no Gaussians are "
                      "added from depth, refinement densifies the region instead")
        elif d_new is None:  # no pixels to calibrate on, and the two disparities show no change of shape
            log.info("initialize: view %d leaves no pixels to calibrate its depth on; its monocular depth, edited "
                     "against unedited, shows no change of shape (%s)", v, report["uncalibrated"])
        else:
            n = params["means"].shape[0]
            if n:
                rows.append(g, params, optimizer=self.optimizers().optimizer, mask=True, generation=1)
                # Does the edit recolour the region besides adding to it? (the Addition's adds_only)
                region_v = regions[views.index(v)]
                report["recoloured_fraction"] = recoloured_fraction(
                    edited, self.source_renders[v], region_v,
                    render_selection(g, self.renderer, scene.cameras[v].to(self.device), g.generation > 0) > 0.05,
                    depth_calibration_pixels(self.source_alpha(v), region_v, disp[0], disp[1], cfg.init))
                if report["recoloured_fraction"] is not None:
                    log.info("initialize: the first edit recolours %.2f of the region beside the added Gaussians "
                             "(the source keeps its colours below system.refine.min_recoloured_fraction=%s)",
                             report["recoloured_fraction"], cfg.refine.min_recoloured_fraction)
                if is_recolour_edge(report, cfg.refine):
                    rows.keep(g, g.generation == 0, optimizer=self.optimizers().optimizer)
                    log.info("initialize: %d Gaussians of changed depth beside a recoloured region are the recolour's "
                             "edge, not a new shape: removed; the edit is a recolour", n)
                    report["recolour_edge"], report["added"], n = n, 0, 0
            self.counts["added_init"] = n
            self.save_image("initialize/depth_new.png", _normalize(1.0 / d_new.clamp_min(1e-6)))
            self.save_image("initialize/initialized_render.png", self.render_view(v)["rgb"].clamp(0, 1))
            log.info(
                "initialize: added %d Gaussians from the depth of view %d (%d region pixels without a depth change "
                "beyond %.3f, %d merged into a Gaussian of their cell, %d too far from the region, %d over the cap of "
                "%d)", n, v, report["skipped_unchanged"], report["depth_threshold"], report["merged_pixels"],
                report.get("skipped_far_from_region", 0), report["skipped_by_cap"], cfg.init.max_new,
            )
        self.save_image("initialize/depth_unedited.png", _normalize(disp[0]))
        self.save_image("initialize/depth_edited.png", _normalize(disp[1]))

    @torch.no_grad()
    def fill_from_cycle_depth(self) -> int:
        """An addition's Gaussians for what this cycle's targets show of the new object and the
        scene still lacks (`new_gaussians_in_holes`: from depth, or painted on the surface where the
        depth shows no change), view by view, each view seeing what the ones before it placed: the
        first view's depth places only the side of the object it sees.
        Returns how many were added (metrics.json `count_added_cycles`)."""
        cfg, s, g, scene = self.cfg, self.state, self.geometry, self.scene
        views = list(s.cycle_views)
        cams = [scene.cameras[j].to(self.device) for j in views]
        renders = [self.render_view(j) for j in views]
        # Where each target shows the edit. Not widened by the pixel a drawing may be off by: a view
        # would then no longer contradict what another placed beside the object (docs/decisions.md).
        shows = [(s.cycle_targets[k] - self.source_renders[j]).abs().amax(-1) > 2.0 / 255 for k, j in enumerate(views)]
        surfaces = [torch.where(r["alpha"] > 0.5, r["depth"], torch.full_like(r["depth"], math.inf)) for r in renders]
        total = 0
        for k, j in enumerate(views):
            # near what the edit added so far; when depth placed nothing yet, near the selection
            added_rows = g.generation > 0
            anchor, reach = (added_rows, HOLE_MAX_DISTANCE) if bool(added_rows.any()) else (g.mask, cfg.init.max_distance)
            out = dict(self.render_view(j) if total else renders[k])
            out["rgb"] = self.as_image(out["rgb"], "the current renders")
            added = render_selection(g, self.renderer, cams[k], added_rows)
            others = [i for i in range(len(views)) if i != k]
            params = new_gaussians_in_holes(
                cams[k], out, s.cycle_targets[k], shows[k], added, (self.source_region(j) > 0.5) | (added > 0.05),
                self.depth_estimator.disparity(torch.stack([out["rgb"], s.cycle_targets[k]]), cameras=[cams[k]] * 2),
                ([cams[i] for i in others], [shows[i] for i in others], [surfaces[i] for i in others]),
                cfg.init, g.sh_degree, g.means.detach()[anchor], reach)
            params = parallel.from_rank_zero(self, params)  # one geometry on every process
            if params:
                rows.append(g, {name: value.to(self.device) for name, value in params.items()},
                            optimizer=self.optimizers().optimizer, mask=True, generation=1)
                total += params["means"].shape[0]
        self.counts["added_cycles"] = self.counts.get("added_cycles", 0) + total
        if total:
            log.info("refine: added %d Gaussians where this cycle's edits show the new object and the scene lacks it",
                     total)
        return total

    def choose_strategy(self) -> EditStrategy:
        cfg = self.cfg
        return choose_strategy(self.state.init_report, cfg.ablation.initialize, cfg.refine, cfg.ablation, cfg.densify)

    # ----- stage 3 -------------------------------------------------------------------------------
    @torch.no_grad()
    def edit_cycle_views(self, cycle: int) -> None:
        r, cfg, scene, s = self.cfg.refine, self.cfg, self.scene, self.state
        self.set_stage(f"refine {cycle + 1}/{r.cycles}: editing views")
        t0 = time.perf_counter()
        frontal, near = cycle_views(scene.cameras, cycle, s.v_first, s.edited_views, r.m, scene.train_indices, cfg.seed)
        frontal, near = self.strategy.cycle_views(self, cycle, frontal, near)
        views = [frontal] + near  # in order of distance
        full_edit_is_target = cycle == 0 and self.strategy.first_view_is_target(len(near))
        if cycle == 0 and not full_edit_is_target:
            views = near  # the first view stays among the edited views (set at initialization)

        def targets(ks: List[int]) -> torch.Tensor:
            # Every view is edited from a render of the same scene state, so all go to the editor in
            # one call (batched by guidance.batch_size), each with its own seed as if edited alone;
            # with several processes, each edits its share of the views (map_views).
            mine = [views[k] for k in ks]
            to_edit = [j for j in mine if not (full_edit_is_target and j == s.v_first)]
            edited = {}
            if to_edit:
                current = torch.stack([self.as_image(self.render_view(j)["rgb"], "the current renders") for j in to_edit])
                out = self.guidance.edit(
                    current, torch.stack([self.source_renders[j] for j in to_edit]), cfg.prompt,
                    t_start=self.strategy.start_timestep(cycle), seed=[self.view_seed(cycle, j) for j in to_edit],
                    cameras=[scene.cameras[j] for j in to_edit],
                )
                edited = dict(zip(to_edit, out.to(self.device)))
            if full_edit_is_target and s.v_first in mine:
                edited[s.v_first] = s.first_edit  # the first, full edit is this cycle's frontal target
            return torch.stack([self.target(j, edited[j]) for j in mine])

        s.cycle_targets = self.map_views(len(views), targets, self.source_renders[frontal].shape)
        s.cycle_views, s.targets_cycle, s.cycle_weights = views, cycle, None  # the strategy's after_edits may weight them
        s.edited_views = sorted(set(s.edited_views) | set(views))
        shown = [[self.source_renders[j], s.cycle_targets[k]] for k, j in enumerate(views[:6])]
        self.save_image_grid(f"refine/cycle{cycle}_edited_views.png", shown)
        self.strategy.after_edits(self)
        self.add_time("refine_edit", time.perf_counter() - t0)

    def view_seed(self, cycle: int, index: int) -> int:
        """The editor's seed for view `index` in refinement cycle `cycle`."""
        return self.cfg.seed + 1000 * (cycle + 1) + index

    def source_region(self, index: int) -> torch.Tensor:
        """(H, W) render of the localized Gaussians of the source scene at view `index`: rendered
        once per view, since neither the source scene nor its selection changes after localization."""
        selection = self.state.source_selection
        if getattr(self, "_source_regions", (None,))[0] is not selection:
            self._source_regions = (selection, {})
        renders = self._source_regions[1]
        if index not in renders:
            cam = self.scene.cameras[index].to(self.device)
            renders[index] = render_selection(self.source_model, self.renderer, cam, selection.to(self.device))
        return renders[index]

    def target(self, index: int, edited: torch.Tensor) -> torch.Tensor:
        """The training target of view `index` from its edit `edited` (the strategy's composite)."""
        return self.strategy.target(self, index, edited)

    def training_step(self, batch, batch_idx):
        s = self.state
        if s.phase == "localize":
            self.run_localize()
            agreement, lc = s.localize_metrics.get("view_agreement"), self.cfg.localization
            if not bool(self.geometry.mask.any()):
                return self.stop_unchanged(
                    "empty selection", "localize: no Gaussian was selected for the prompt; nothing to edit. Try a lower "
                    "system.localization.gamma or system.localization.mask_threshold.")
            if self.cfg.stop_after == "localize":
                return self.stop_unchanged("stop_after=localize", None)
            if agreement is not None and agreement < lc.min_view_agreement:
                return self.stop_unchanged("views disagree", views_disagree(agreement, lc.min_view_agreement))
            self.save_stage_checkpoint()  # a kill later in this step resumes after localization
        if s.phase == "initialize":
            first = self.run_initialize()
            if parallel.from_rank_zero(self, first.stop):  # one decision to go on
                return self.stop_unchanged("edit outside the region", stop_message(first, self.cfg.localization.min_edit_coverage))
            parallel.check_agree(self, "initialization", [self.geometry.num_gaussians, s.v_first])
            self.save_stage_checkpoint()
        if s.phase != "refine":
            return None
        r = self.cfg.refine
        step = self.global_step
        cycle, it = divmod(step, r.iterations_per_cycle)
        if cycle >= r.cycles:
            return None
        if s.targets_cycle != cycle:
            self.edit_cycle_views(cycle)
        self.set_stage(f"refine {cycle + 1}/{r.cycles}")
        t0 = time.perf_counter()
        # Stateless per-step choice of view, so a resumed run makes the same choices.
        gen = torch.Generator().manual_seed(self.cfg.seed * 104729 + step)
        n_views = min(r.views_per_step or parallel.world_size(self), len(s.cycle_views))
        if n_views == 1:
            ks = [int(torch.randint(len(s.cycle_views), (1,), generator=gen))]
        else:
            ks = torch.randperm(len(s.cycle_views), generator=gen)[:n_views].tolist()
        densify = self.strategy.densify
        weights = None if s.cycle_weights is None else s.cycle_weights[ks]
        if n_views == 1 and parallel.world_size(self) == 1:
            self.optimize_on(s.cycle_views[ks[0]], s.cycle_targets[ks[0]], densify=densify, step=it,
                             weight=None if weights is None else weights[0])
        else:  # the step's views shared out over the processes of a run on several devices
            self.optimize_on_views([s.cycle_views[k] for k in ks], s.cycle_targets[ks], densify=densify, step=it,
                                   weights=weights)
        due = densify is not None and densify.densifies_at(it, r.iterations_per_cycle - 1)
        if due:
            parallel.agree_on_rng(self)  # split samples: rank 0's draws on every process
        rep = None if densify is None else densify.refine(
            self.geometry, it, self.scene.extent, self.optimizers().optimizer,
            last_step=r.iterations_per_cycle - 1, base_count=s.refine_start_count,
            grow=self.strategy.growable(self.geometry) if due else None,  # once a cycle, not every step
        )
        if rep is not None:
            parallel.check_agree(self, f"the densification of step {step}", [self.geometry.num_gaussians])
            self.counts["densified"] = self.counts.get("densified", 0) + rep["cloned"] + rep["split"]
            self.counts["pruned"] = self.counts.get("pruned", 0) + rep["pruned"]
        self.add_time("refine_train", time.perf_counter() - t0)
        if step == self.total_steps - 1:
            self.finish_refinement()
        return None

    def stop_unchanged(self, reason: str, message: Optional[str]) -> None:
        """End the run with the source scene written out unchanged (metrics.json `stopped`): the
        safe path when localization cannot be trusted (warned: `message`), or system.stop_after."""
        if message is not None:
            self.warn(message + " The source scene is written out unchanged.")
        self.state.phase = "done"
        self.trainer.should_stop = True
        self.write_outputs({"stopped": reason, **self.state.localize_metrics})
        return None

    def finish_refinement(self) -> None:
        """The end of refinement, inside its last step: prune the useless added Gaussians. Part of
        the step, not of on_train_end: a run stopped earlier (trainer.max_steps) then checkpoints
        the state refinement goes on from, so resuming it with more steps gives the whole run's
        scene."""
        t0 = time.perf_counter()
        r = self.cfg.refine
        n = 0 if not r.prune_added else prune_useless_added(
            self.geometry, self.renderer, [self.scene.cameras[i].to(self.device) for i in self.scene.train_indices],
            r.prune_min_weight, r.prune_min_opacity, self.optimizers().optimizer,
            agree=lambda rows_: parallel.from_rank_zero(self, rows_))  # every process prunes the same rows
        self.add_time("prune", time.perf_counter() - t0)
        self.counts["pruned_added"] = n
        self.counts["pruned"] = self.counts.get("pruned", 0) + n
        self.strategy.finish(self)

    def edit_mask_arrays(self) -> Dict[str, Any]:
        """save/edit_mask.npz also holds the selection over the source Gaussians (gs_regional.edit)
        and the strategy's arrays (a recolour's `gate_blend`)."""
        sel = self.state.source_selection
        out = {} if sel is None else {"source_selection": sel.cpu().numpy()}
        return out if self.strategy is None else {**out, **self.strategy.saved_arrays(self.n_source)}

    def on_train_end(self) -> None:
        s = self.state
        if s.phase == "done":
            return
        extra = dict(s.localize_metrics)
        extra["v_first"] = s.v_first
        extra["edited_views"] = len(s.edited_views)
        if self.strategy is not None:  # how this edit was refined, and its schedule
            extra["refined_as"] = self.strategy.name
            extra["t_starts"] = [self.strategy.start_timestep(c) for c in range(self.cfg.refine.cycles)]
        if s.init_report:
            extra["init"] = s.init_report
        if self.truth is not None:
            # a recolour: which stage lost what it did not reach (localization, the gate, training);
            # an addition: how much of the new object its Gaussians draw. Each is {} for the other.
            g, views = self.geometry, self.evaluation_views()
            if s.source_selection is not None:
                extra.update(self.truth.recolour_rows(g, s.source_selection, g.mask, views))
            extra.update(self.truth.addition_cover(g, g.generation > 0, views))
        self.write_outputs(extra)

    def evaluation_region(self, index: int):
        region = super().evaluation_region(index)
        selection = self.state.source_selection
        if region is None and selection is not None and bool(selection.any()):
            # No ground truth: what lies outside this run's own (dilated) 3D mask should not change.
            region = ~dilate(self.source_region(index) > 0.01, 2)
        return region

    # ----- checkpoint ----------------------------------------------------------------------------
    def extra_state(self) -> dict:
        return {**super().extra_state(), **self.state.state_dict(),
                "strategy": None if self.strategy is None else self.strategy.state_dict()}

    def load_extra_state(self, state: dict) -> None:
        super().load_extra_state(state)
        if not state:
            return
        self.state.load_state_dict(state)
        if self.state.phase in ("refine", "done"):
            self.strategy = self.choose_strategy()
            self.strategy.load_state_dict(state.get("strategy") or state)  # (older checkpoints: at the top level)

    def on_load_checkpoint(self, checkpoint: Dict[str, Any]) -> None:
        # A checkpoint written with a setting that was removed or moved, at another value than now: one line.
        check_saved_config(((checkpoint.get("gs_regional_config") or {}).get("system")), self.Config, self.cfg, "system")
        super().on_load_checkpoint(checkpoint)

    def on_train_start(self) -> None:
        self.state.to(self.device)
        if self.strategy is not None:
            self.strategy.to(self.device)


def read_selection(path: str, n: int) -> torch.Tensor:
    """system.selection_file: one bool per source Gaussian from a .npy, or from a .npz's
    `selection` array (its only array otherwise); anything else is a one-line ConfigError."""
    import numpy as np

    try:
        with open(path, "rb") as f:
            data = np.load(f, allow_pickle=False)
            if isinstance(data, np.lib.npyio.NpzFile):
                names = list(data.files)
                if "selection" not in names and len(names) != 1:
                    raise ConfigError(f"system.selection_file {path}: a .npz needs a 'selection' array, it has {names}")
                data = data["selection" if "selection" in names else names[0]]
    except ConfigError:
        raise
    except Exception as e:
        raise ConfigError(f"system.selection_file {path}: cannot be read ({type(e).__name__}: {e})") from None
    data = np.asarray(data).reshape(-1) if np.ndim(data) == 2 and 1 in np.shape(data) else np.asarray(data)
    if data.ndim != 1 or len(data) != n:
        raise ConfigError(f"system.selection_file {path}: {data.size:,} entries (shape {tuple(data.shape)}), "
                          f"but the scene has {n:,} Gaussians")
    if data.dtype != bool and not np.isin(data, (0, 1)).all():
        raise ConfigError(f"system.selection_file {path}: the selection must be bool (or 0/1), got {data.dtype}")
    return torch.as_tensor(data.astype(bool))


def _normalize(x: torch.Tensor) -> torch.Tensor:
    x = x.float()
    lo, hi = x.min(), x.max()
    return ((x - lo) / (hi - lo).clamp_min(1e-8))[..., None].expand(*x.shape, 3)
