"""What `regional-edit` and the `in2n` baseline share: the scene being edited, the 2D editor,
finetuning steps, evaluation and the output files (DESIGN.md §1, §3.4)."""
from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence

import numpy as np
import torch

from gs_regional.config import ConfigError
from gs_regional.stages.views import camera_path, order_by_azimuth
from gs_regional.geometry.formats import ExportConfig, export_scene
from gs_regional.geometry.gaussian_model import PARAM_NAMES
from gs_regional.geometry.ply import PlyError, check_ply_header, ply_bytes_with_rows
from gs_regional.geometry.strategy import DensifyStrategy
from gs_regional.metrics.image import psnr, ssim
from gs_regional.metrics.region import error_map, unedited_scores
from gs_regional.metrics.truth import TruthScoring
from gs_regional.registry import find
from gs_regional.renderers.select import check_renderer_config, make_renderer
from gs_regional.sim.truth import GroundTruth, GroundTruthConsumer
from gs_regional.systems import parallel
from gs_regional.systems.base import GaussianSystem
from gs_regional.utils.pretrained import PriorLoader

log = logging.getLogger(__name__)

MIN_FRACTION_SEEN = 0.1  # below this fraction of Gaussians in any camera's view, the run warns


@dataclass
class EvalConfig:
    max_test_views: int = 8  # views in the before/after grid and the metrics
    turntable_frames: int = 48
    fps: int = 24
    clip_model: Optional[str] = None  # e.g. openai/clip-vit-large-patch14 or a local folder
    source_caption: str = "a photo"  # for the CLIP direction similarity
    edit_caption: str = ""  # defaults to the prompt
    # Region-aware metrics (gs_regional.metrics.region): the true edit's footprint is where the
    # rendered weight of its region (and of the Gaussians it adds) exceeds this; the object's
    # silhouette is where the source renders more opaque than `opaque_alpha`.
    footprint_threshold: float = 0.1
    opaque_alpha: float = 0.5


class EditSystemBase(GaussianSystem):
    @dataclass
    class Config(GaussianSystem.Config):
        geometry_type: str = "gaussian-model"
        geometry: dict = field(default_factory=dict)
        renderer_type: str = "auto"  # gsplat-rasterizer on a CUDA device when gsplat imports, else torch-rasterizer
        renderer: dict = field(default_factory=dict)
        guidance_type: str = "instructpix2pix"
        guidance: dict = field(default_factory=dict)
        prompt: str = ""
        seed: int = 0
        lambda_l1: float = 1.0
        lambda_lpips: float = 0.0  # needs the `lpips` extra
        eval: EvalConfig = field(default_factory=EvalConfig)
        export: ExportConfig = field(default_factory=ExportConfig)  # viewer formats beside the PLY

    @classmethod
    def check_inputs(cls, section) -> None:
        """launch.py calls this before the system (and its priors) is built: the scene's PLY must
        exist and have a usable header, or the run stops with one line naming the file."""
        ply = (section.get("geometry") or {}).get("ply") if hasattr(section, "get") else None
        if ply:
            try:
                check_ply_header(str(ply))
            except PlyError as e:
                raise PlyError(f"system.geometry.ply: {e}") from None

    def check_scene(self) -> None:
        """Before anything is edited: the cameras must see the scene (a PLY and cameras of two
        different scenes, or of one scene in two coordinate frames, see nothing of each other)."""
        means = self.geometry.means.detach()
        seen = torch.zeros(len(means), dtype=torch.bool, device=means.device)
        for cam in self.scene.cameras:
            seen |= cam.to(means.device).in_view(means)
        fraction = float(seen.float().mean()) if len(means) else 0.0
        where = f"system.geometry.ply={self.cfg.geometry.get('ply')}" if self.cfg.geometry.get("ply") else "the scene"
        if fraction == 0.0:
            raise ConfigError(
                f"the cameras do not see the scene: none of the {len(means):,} Gaussians of {where} lies in the view of "
                f"any of the {len(self.scene.cameras)} cameras; check that the cameras (data.source) belong to this PLY "
                "(same scene, coordinate frame and scale)"
            )
        if fraction < MIN_FRACTION_SEEN:
            self.warn(f"only {fraction:.1%} of the Gaussians lie in the view of any camera: check that the cameras "
                      f"(data.source) belong to {where}")

    def configure(self) -> None:
        """Build the non-scene components (called from the constructor of subclasses)."""
        cfg = self.cfg
        if not cfg.prompt or not cfg.prompt.strip():
            raise ConfigError("system.prompt is empty: say what to change, e.g. system.prompt=\"give him a mustache\"")
        # Built in setup(), for the device the trainer places the module on; checked now.
        check_renderer_config(cfg.renderer_type, cfg.renderer)
        cfg.export.check()
        self._source_renders: Optional[List[torch.Tensor]] = None
        # The 2D editor is not an nn.Module of the system: its weights never enter checkpoints.
        # With CUDA the priors load on a background thread while the scene is read and the source
        # views render (`PriorLoader`): a missing folder fails here, a load error where the system
        # waits for them (on_fit_start) or first uses one.
        self.priors = PriorLoader()
        self.priors.start("guidance", find(cfg.guidance_type, kind="guidance", key="system.guidance_type"), cfg.guidance)
        self.lpips = None
        if cfg.lambda_lpips > 0:
            try:
                import lpips  # noqa: F401
            except Exception as e:  # lpips needs torchvision, which is not always installable
                raise ConfigError(
                    f"system.lambda_lpips={cfg.lambda_lpips} needs the 'lpips' extra "
                    f"(pip install 'gs_regional[lpips]'), which failed to import: {e}. "
                    "Set system.lambda_lpips=0 to train with L1 only."
                ) from None
        self.timings: Dict[str, float] = {}
        self.counts: Dict[str, int] = {}
        self.warnings: List[str] = []  # what the run noticed going wrong; metrics.json lists them

    @property
    def guidance(self):
        """The 2D editor (waits for it while it loads)."""
        priors = self.__dict__.get("priors")
        if priors is None:
            raise AttributeError("guidance: the system has not built its priors yet (configure())")
        return priors.get("guidance")

    @guidance.setter
    def guidance(self, value) -> None:
        self.__dict__.setdefault("priors", PriorLoader()).set("guidance", value)

    @property
    def depth_estimator(self):
        """The depth estimator, None when the system has none (waits for it while it loads)."""
        priors = self.__dict__.get("priors")
        return None if priors is None else priors.get("depth_estimator")

    @depth_estimator.setter
    def depth_estimator(self, value) -> None:
        self.__dict__.setdefault("priors", PriorLoader()).set("depth_estimator", value)

    # ----- scene ---------------------------------------------------------------------------------
    def setup(self, stage: Optional[str] = None) -> None:
        if getattr(self, "geometry", None) is not None:
            return
        dm = self.trainer.datamodule
        dm.setup(stage)
        self.scene = dm.scene
        gt = self.scene.ground_truth
        geometry_cls = find(self.cfg.geometry_type, kind="geometry", key="system.geometry_type")
        if self.cfg.geometry.get("ply"):
            self.geometry = geometry_cls(self.cfg.geometry)
        elif gt is not None:
            self.geometry = geometry_cls(self.cfg.geometry, n=0, sh_degree=gt.source.sh_degree)
            self.geometry.load_state_dict(gt.source.state_dict(), strict=False)
        else:
            raise ConfigError(
                "system.geometry.ply is not set: give the trained scene to edit "
                "(system.geometry.ply=path/to/point_cloud.ply)"
            )
        if gt is not None:
            self.attach_ground_truth(gt)
        # The scene as loaded is the source: its rows are numbered 0..n_source-1 and every row
        # added, split or moved later keeps the number of the source row it descends from.
        self.geometry.mark_as_source()
        self.n_source = self.geometry.num_gaussians
        # The unedited scene, for source renders and comparisons. Kept out of the module tree
        # (object.__setattr__) so it never enters checkpoints: setup() rebuilds it on resume.
        object.__setattr__(self, "source_model", copy.deepcopy(self.geometry).requires_grad_(False))
        self.renderer = make_renderer(self.cfg.renderer_type, self.cfg.renderer, self.trainer.strategy.root_device)
        # Scoring against the known edit, when the scene has one (metrics only: it steers nothing).
        self.truth = None if gt is None else TruthScoring(gt, self.renderer, self.scene.cameras, lambda: self.device,
                                                          self.cfg.eval.footprint_threshold)

    def attach_ground_truth(self, truth: GroundTruth) -> None:
        """Hand the scene's known edit to every prior that renders one (the simulators; ours share
        their renders of it)."""
        shared = {}
        for prior in (self.guidance, getattr(self, "depth_estimator", None)):
            if isinstance(prior, GroundTruthConsumer):
                prior.attach_ground_truth(truth, shared)
            elif hasattr(prior, "attach_ground_truth"):  # a plugin's own
                prior.attach_ground_truth(truth)

    def on_fit_start(self) -> None:
        # setup() ran before Lightning moved the module to its device: the source scene follows it
        # and is rendered there, once (a resumed run renders it again; renders are deterministic).
        self.source_model.to(self.device)
        self.check_scene()
        t0 = time.perf_counter()
        cams = self.scene.cameras
        sizes = {(c.height, c.width) for c in cams}
        with torch.no_grad():
            if parallel.world_size(self) > 1 and len(sizes) == 1:  # each process renders its share
                self._source_renders = list(self.map_views(len(cams), lambda ks: torch.stack([
                    self.as_image(self.render_view(i, self.source_model)["rgb"], "the source renders") for i in ks
                ]), (*sizes.pop(), 3)))
            else:
                renders = [self.render_view(i, self.source_model)["rgb"] for i in range(len(cams))]
                self._source_renders = [self.as_image(r, "the source renders") for r in renders]
        self.add_time("source_renders", time.perf_counter() - t0)
        # Before the first stage, and before Lightning's loops draw from the global random state
        # that the priors' constructors draw from.
        t0 = time.perf_counter()
        self.priors.wait()
        self.prior_wait_seconds = time.perf_counter() - t0

    def as_image(self, render: torch.Tensor, what: str) -> torch.Tensor:
        """A render as the 2D priors take images: in [0, 1]. A splat fitted to photos renders
        above 1 here and there (view-dependent colour overshoots), which a display clamps too;
        pixels that leave the range by more than a level of 8-bit colour are counted
        (metrics.json `count_render_pixels_clamped`) and said once per kind of render."""
        lo, hi = (float(v) for v in torch.aminmax(render.detach()))
        if lo < -1.0 / 255 or hi > 1 + 1.0 / 255:
            n = int(((render < -1.0 / 255) | (render > 1 + 1.0 / 255)).any(-1).sum())
            self.counts["render_pixels_clamped"] = self.counts.get("render_pixels_clamped", 0) + n
            said = self.__dict__.setdefault("_clamp_said", set())
            if what not in said:
                said.add(what)
                log.info("%s leave [0, 1] (values in [%.3g, %.3g]), as renders of a splat fitted to photos do: "
                         "clamped where they feed the 2D editor and the depth estimator", what, lo, hi)
        return render.clamp(0, 1)

    @property
    def source_renders(self) -> List[torch.Tensor]:
        """(H, W, 3) render of the unedited scene at every camera, on the module's device."""
        if self._source_renders is None:
            raise RuntimeError(
                "source renders are made in on_fit_start, once Lightning has moved the system to its device; "
                "they are not available before fit starts"
            )
        return self._source_renders

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

    def full_edit(self, u: int) -> torch.Tensor:
        """The editor's full edit of view `u` (one seed: each view is edited once)."""
        cache = self.__dict__.setdefault("_full_edits", {})
        if u not in cache:
            cache[u] = self.guidance.edit(self.source_renders[u][None], self.source_renders[u][None], self.cfg.prompt,
                                          t_start=None, seed=self.cfg.seed, cameras=[self.scene.cameras[u]])[0].to(self.device)
        return cache[u]

    def render_view(self, index: int, model=None, **kw) -> Dict[str, torch.Tensor]:
        cam = self.scene.cameras[index].to(self.device)
        return self.renderer.render(model if model is not None else self.geometry, cam, **kw)

    def add_time(self, stage: str, seconds: float) -> None:
        self.timings[stage] = self.timings.get(stage, 0.0) + seconds

    def warn(self, message: str) -> None:
        """Say in the log that something went wrong, and keep it for metrics.json (`warnings`)."""
        log.warning(message)
        self.warnings.append(message)

    # ----- optimisation --------------------------------------------------------------------------
    def photometric_loss(self, rgb: torch.Tensor, target: torch.Tensor, weight: Optional[torch.Tensor] = None) -> torch.Tensor:
        """L1 (and LPIPS with `lambda_lpips`) of `rgb` against `target`; `weight` (H, W): how much each
        pixel counts in the L1 term (None: alike)."""
        diff = (rgb - target).abs()
        loss = self.cfg.lambda_l1 * (diff if weight is None else weight.to(diff)[..., None] * diff).mean()
        if self.cfg.lambda_lpips > 0:
            if self.lpips is None:
                import lpips

                self.lpips = lpips.LPIPS(net="vgg", verbose=False).to(self.device).eval().requires_grad_(False)
            to_net = lambda x: x.permute(2, 0, 1)[None] * 2 - 1  # noqa: E731
            loss = loss + self.cfg.lambda_lpips * self.lpips(to_net(rgb), to_net(target)).mean()
        return loss

    def optimize_on(self, index: int, target: torch.Tensor, densify: Optional[DensifyStrategy] = None,
                    step: int = 0, weight: Optional[torch.Tensor] = None) -> Dict[str, torch.Tensor]:
        """One Adam step of the scene towards `target` at view `index` (its pixels weighted by
        `weight`, `photometric_loss`); with `densify`, its statistics are gathered from this step's
        gradients (at the strategy's `step`)."""
        opt = self.optimizers()
        out = self.render_view(index)
        loss = self.photometric_loss(out["rgb"], target.to(self.device), weight)
        opt.zero_grad(set_to_none=True)
        self.manual_backward(loss)
        if densify is not None:
            densify.collect_stats(self.geometry, out, self.scene.cameras[index], step)
        opt.step()
        self.log("train/loss", loss.detach(), prog_bar=True)
        return out

    def optimize_on_views(self, indices: Sequence[int], targets: torch.Tensor,
                          densify: Optional[DensifyStrategy] = None, step: int = 0,
                          weights: Optional[torch.Tensor] = None) -> None:
        """One Adam step of the scene towards `targets` (k, H, W, 3) at the k views `indices` (their
        pixels weighted by `weights` (k, H, W), None: alike): the gradient of their mean loss. With
        several processes each renders its share of the views, and the gradients and densification
        statistics are summed over the processes before the step (parallel.reduce_step), so every
        process takes the same step; with one process, k views in turn, summed the same way."""
        opt = self.optimizers()
        g = self.geometry
        opt.zero_grad(set_to_none=True)
        stats = parallel.StepStats(g) if densify is not None and densify.collects_stats(step) else None
        loss_sum = torch.zeros((), device=self.device)
        for k in parallel.share(len(indices), *parallel.rank_and_world(self)):
            out = self.render_view(indices[k])
            loss = self.photometric_loss(out["rgb"], targets[k].to(self.device), None if weights is None else weights[k])
            self.manual_backward(loss)
            if stats is not None:
                densify.collect_stats(g, out, self.scene.cameras[indices[k]], step)
            loss_sum = loss_sum + loss.detach()
        loss = parallel.reduce_step(self, [getattr(g, name) for name in PARAM_NAMES], len(indices), loss_sum, stats)
        opt.step()
        self.log("train/loss", loss, prog_bar=True)

    # ----- views shared out over processes -------------------------------------------------------
    def map_views(self, n: int, fn: Callable[[List[int]], torch.Tensor], item_shape: Sequence[int],
                  dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """`fn(items)` -> (len(items), *item_shape) over range(n): with one process `fn` of all of
        them; with several each runs its share and the results are gathered in order
        (parallel.map_views), and the editor's counters and the clamped-pixel count then hold the
        work of every process."""
        if parallel.world_size(self) == 1:
            return fn(list(range(n)))
        before = self.work_counts()
        out = parallel.map_views(self, n, fn, item_shape, dtype)
        self.set_work_counts(parallel.sum_increments(self, before, self.work_counts()))
        return out

    def work_counts(self) -> Dict[str, int]:
        """The counters that work shared out over processes adds to: the editor's, and the count
        of render pixels clamped on their way to it."""
        return {**{f"guidance.{k}": int(v) for k, v in self.guidance.counters().items()},
                "render_pixels_clamped": int(self.counts.get("render_pixels_clamped", 0))}

    def set_work_counts(self, counts: Dict[str, int]) -> None:
        for key, value in counts.items():
            if key.startswith("guidance."):
                setattr(self.guidance, key[len("guidance."):], int(value))
            elif value or key in self.counts:
                self.counts[key] = int(value)

    # ----- checkpoint ----------------------------------------------------------------------------
    def extra_state(self) -> dict:
        # The editor's counters too: a resumed run reports the whole run's UNet evaluations.
        return {"timings": dict(self.timings), "counts": dict(self.counts), "warnings": list(self.warnings),
                "guidance_counters": dict(self.guidance.counters())}

    def load_extra_state(self, state: dict) -> None:
        self.timings = dict(state.get("timings", {}))
        self.counts = dict(state.get("counts", {}))
        self.warnings = list(state.get("warnings", []))
        for name, value in state.get("guidance_counters", {}).items():
            setattr(self.guidance, name, int(value))

    # ----- outputs -------------------------------------------------------------------------------
    def evaluation_region(self, index: int) -> Optional[torch.Tensor]:
        """(H, W) bool: pixels that should NOT change at view `index`, or None if unknown.

        With a ground truth: where the true edited scene renders like the source, away from the
        true region. Otherwise subclasses may use their own 3D mask.
        """
        truth = getattr(self, "truth", None)
        return None if truth is None else truth.unchanged(index, self.source_renders[index])

    def size_metrics(self) -> Dict[str, object]:
        """Gaussians added and pruned by this run (and by the true edit, if known), and the bytes
        of save/edited.ply against the source scene written in the same layout."""
        added = sum(self.counts.get(k, 0) for k in ("added_init", "added_cycles", "densified"))
        pruned = self.counts.get("pruned", 0)
        after = self.geometry.num_gaussians
        if self.n_source + added - pruned != after:
            self.warn(f"Gaussian counts do not add up: {self.n_source} before + {added} added - {pruned} pruned "
                      f"!= {after} after")
        # Source rows no output row descends from (a split keeps its children's source index).
        kept = self.geometry.source_index[self.geometry.source_index >= 0].unique().numel()
        out: Dict[str, object] = {"gaussians_added": added, "gaussians_pruned": pruned,
                                  "source_deleted": self.n_source - int(kept)}
        if self.truth is not None:
            out["true_gaussians_added"] = self.truth.gaussians_added()
        path = self.save_dir / "edited.ply"
        out["ply_bytes"] = path.stat().st_size
        out["source_ply_bytes"] = ply_bytes_with_rows(path, self.n_source)
        return out

    def on_export(self) -> None:
        """`launch.py --export resume=<ckpt>`: write the scene of that checkpoint as a PLY and the
        formats of `system.export` (`--export region`: the edited region too)."""
        path = self.save_path(f"export_step{self.global_step}.ply")
        self.geometry.save_ply(str(path))
        log.info("export: %d Gaussians written to %s", self.geometry.num_gaussians, path)
        self.write_formats(f"export_step{self.global_step}")

    def write_formats(self, stem: str) -> Dict[str, int]:
        """Beside save/<stem>.ply (already written): the viewer formats of `system.export`, and with
        `export.region` the edited region alone (the selected and the added Gaussians) as
        save/<stem>_region.ply and the same formats. Returns {file name: bytes}."""
        cfg = self.cfg.export
        paths = export_scene(self.geometry.to_ply_gaussians(), self.save_dir / stem, cfg.formats())
        if cfg.region:
            region = self.geometry.editable_rows()
            if bool(region.any()):
                paths += export_scene(self.geometry.select(region).to_ply_gaussians(), self.save_dir / f"{stem}_region",
                                      ["ply", *cfg.formats()])
                log.info("export: the edited region, %d Gaussians, written to %s_region.*", int(region.sum()), stem)
            else:
                self.warn("export.region: the edit selected and added no Gaussians, so no region files were written")
        return {p.name: p.stat().st_size for p in paths}

    def edit_mask_arrays(self) -> Dict[str, Any]:
        """More arrays for save/edit_mask.npz (a system's own; none here)."""
        return {}

    def evaluation_views(self) -> List[int]:
        """The views the result is scored and shown at: the test views (the training views when
        there are none), at most `eval.max_test_views`."""
        return (self.scene.test_indices or self.scene.train_indices)[: self.cfg.eval.max_test_views]

    @torch.no_grad()
    def write_outputs(self, extra_metrics: Optional[dict] = None) -> dict:
        """edited.ply, before/after renders, a turntable video and metrics.json (rank 0 alone, with
        several processes: the others return {} at once)."""
        self.set_stage("output")
        if not self.writes_outputs:
            return {}
        t0 = time.perf_counter()
        self.geometry.save_ply(str(self.save_dir / "edited.ply"))
        # Which rows of edited.ply the edit selected or added (the viewer highlights them).
        g = self.geometry
        np.savez_compressed(self.save_dir / "edit_mask.npz", mask=g.mask.cpu().numpy(),
                            generation=g.generation.cpu().numpy(), source_index=g.source_index.cpu().numpy(),
                            **self.edit_mask_arrays())
        export_bytes = self.write_formats("edited")
        scene = self.scene
        views = self.evaluation_views()
        after = {i: self.render_view(i)["rgb"].clamp(0, 1) for i in views}
        rows = [[self.source_renders[i], after[i]] for i in views]
        if self.truth is not None:
            rows = [r + [self.truth.edited_render(i)] for r, i in zip(rows, views)]
        self.save_image_grid("before_after.png", rows)

        metrics: Dict[str, object] = {
            "prompt": self.cfg.prompt,
            "gaussians_before": self.n_source,
            "gaussians_after": self.geometry.num_gaussians,
            **{f"count_{k}": v for k, v in self.counts.items()},
            **self.guidance.counters(),  # with several processes, every process's work (map_views)
            # The UNet's wall seconds (this process's calls) and the views per model call at each resolution.
            "unet_seconds": round(float(self.guidance.unet_seconds), 3),
            "guidance_batch_size": self.guidance.batches_chosen(),
            "prior_wait_seconds": round(float(getattr(self, "prior_wait_seconds", 0.0)), 3),
            "world_size": parallel.world_size(self),
        }
        # Fidelity of what should not have changed, against the source renders.
        regions = {i: self.evaluation_region(i) for i in views}
        if all(r is not None for r in regions.values()):
            a = torch.stack([after[i] for i in views])
            s = torch.stack([self.source_renders[i] for i in views])
            m = torch.stack([regions[i] for i in views])
            metrics["psnr_unedited"] = psnr(a, s, m)
            metrics["ssim_unedited"] = ssim(a, s, m)
            alpha = torch.stack([self.source_alpha(i) for i in views])
            metrics.update(unedited_scores(a, s, m, alpha, self.cfg.eval.opaque_alpha))
        if self.truth is not None:
            scores, inside = self.truth.scores(views, torch.stack([after[i] for i in views]),
                                               torch.stack([self.source_renders[i] for i in views]))
            metrics.update(scores)
            self.save_image_grid("errors_vs_truth.png", [
                [after[i], self.truth.edited_render(i), error_map(after[i], self.truth.edited_render(i), m)]
                for i, m in zip(views, inside)])
        if self.cfg.eval.clip_model:
            from gs_regional.metrics.clip import ClipMetrics

            clip = ClipMetrics(self.cfg.eval.clip_model, device=self.device)
            src = torch.stack([self.source_renders[i] for i in views])
            edi = torch.stack([after[i] for i in views])
            metrics["clip_direction_similarity"] = clip.direction_similarity(
                src, edi, self.cfg.eval.source_caption, self.cfg.eval.edit_caption or self.cfg.prompt
            )
            metrics["clip_image_similarity"] = clip.image_similarity(src, edi)
        metrics.update(self.size_metrics())
        metrics["export_bytes"] = export_bytes
        metrics.update(extra_metrics or {})

        path_views = order_by_azimuth(scene.cameras, scene.train_indices or scene.test_indices)
        frames = []
        for cam in camera_path([scene.cameras[i] for i in path_views], self.cfg.eval.turntable_frames):
            before = self.renderer.render(self.source_model, cam.to(self.device))["rgb"]
            now = self.renderer.render(self.geometry, cam.to(self.device))["rgb"]
            frames.append(torch.cat([before, now], dim=1).clamp(0, 1))
        self.save_video("turntable.mp4", frames, fps=self.cfg.eval.fps)
        self.add_time("output", time.perf_counter() - t0)
        metrics["seconds"] = {k: round(v, 3) for k, v in self.timings.items()}
        metrics["seconds_total"] = round(sum(v for k, v in self.timings.items()), 3)
        metrics["warnings"] = list(self.warnings)
        self.write_metrics_json(metrics)
        return metrics
