"""`reconstruct`: fit a 3DGS to posed photos (for scenes that come without a trained splat).

The original 3DGS recipe, shortened for small images on a CPU:
  * initialisation from the scene's SfM points (or random points in the camera rig's bounds);
  * one random training view per step, loss (1 - l) L1 + l (1 - SSIM);
  * exponentially decaying position learning rate;
  * progressive SH: degree d's coefficients get gradients only from step d * sh_degree_every
    (until then they stay exactly zero, so the renderer's full-degree evaluation equals the
    lower-degree one);
  * densification (clone / split by the view-space gradient, in NDC units like 3DGS), pruning of
    transparent (and, optionally, huge) Gaussians, periodic opacity resets;
  * at the end: held-out PSNR/SSIM (every `data.test_every`-th camera), save/reconstructed.ply,
    save/test_views.png (photo | render) and save/metrics.json.

Resuming from any checkpoint gives the same Gaussians as an uninterrupted run: the view order,
backgrounds and split samples come from generators seeded by (seed, step), and the densification
statistics and Adam moments are part of the checkpoint.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import List, Optional

import torch

from gs_regional.config import ConfigError
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.geometry.strategy import DensifyStrategy
from gs_regional.metrics.image import psnr, ssim, ssim_loss_value
from gs_regional.registry import register
from gs_regional.renderers.select import check_renderer_config, make_renderer
from gs_regional.systems.base import GaussianSystem

log = logging.getLogger(__name__)


@register("reconstruct")
class Reconstruct(GaussianSystem):
    @dataclass
    class Config(GaussianSystem.Config):
        renderer_type: str = "auto"  # gsplat-rasterizer on a CUDA device when gsplat imports, else torch-rasterizer
        renderer: dict = field(default_factory=dict)
        sh_degree: int = 3
        sh_degree_every: int = 1000  # one more active SH degree every n steps (0: all at once)
        init: str = "points"  # "points" (SfM points of the scene) or "random"
        random_points: int = 20000
        init_opacity: float = 0.1
        max_steps: int = 3000
        lambda_dssim: float = 0.2
        seed: int = 0
        lr_means_final_factor: float = 0.01  # exponential decay of the position learning rate
        # 3DGS's densification (its statistics are gathered from step 0); `budget` counts from the
        # number of initial points
        densify: DensifyStrategy = field(default_factory=DensifyStrategy)
        # Colour behind the Gaussians in training and evaluation; unset: the mean colour of the
        # training photos (the least wrong guess where nothing covers the image).
        background: Optional[List[float]] = None
        random_background: bool = False  # train over random colours (pushes towards opaque scenes)
        max_test_views: int = 6  # photo | render pairs in save/test_views.png (metrics use all)

    def __init__(self, cfg=None, resumed: bool = False) -> None:
        super().__init__(cfg, resumed=resumed)
        cfg = self.cfg
        if cfg.init not in ("points", "random"):
            raise ConfigError(f"system.init must be 'points' or 'random', got '{cfg.init}'")
        if not 0 <= cfg.sh_degree <= 4:
            raise ConfigError(f"system.sh_degree must be in 0..4, got {cfg.sh_degree}")
        if cfg.background is not None and len(cfg.background) != 3:
            raise ConfigError(f"system.background must be 3 values (r, g, b in [0, 1]), got {list(cfg.background)}")
        cfg.densify.check("system.densify")
        # Built in setup(), for the device the trainer places the module on; checked now.
        check_renderer_config(cfg.renderer_type, cfg.renderer)
        self.geometry: Optional[GaussianModel] = None
        self.seconds_before = 0.0  # fit time of the runs this one resumes
        self.steps_before = 0  # steps of the checkpoint loaded (--export does not restore global_step)
        self.initial_count = 0  # Gaussians at the start of the fit (what densify.budget counts from)

    @property
    def total_steps(self) -> int:
        return self.cfg.max_steps

    # ----- scene ---------------------------------------------------------------------------------
    def setup(self, stage: Optional[str] = None) -> None:
        if self.geometry is not None:
            return
        self.started = time.perf_counter()
        dm = self.datamodule
        if dm is None or not hasattr(dm, "scene"):
            raise ConfigError(
                f"reconstruct needs a scene datamodule (data_type: scene-datamodule), got {type(dm).__name__}"
            )
        dm.setup(stage)
        self.scene = scene = dm.scene
        if scene.images is None:
            raise ConfigError(
                f"reconstruct needs photos, but the scene '{scene.source}' has none (its cameras name "
                "no image files, or data.load_images is false)"
            )
        if not scene.train_indices:
            raise ConfigError(f"scene '{scene.source}' has no training views (data.test_every holds out every camera)")
        cfg = self.cfg
        gen = torch.Generator().manual_seed(cfg.seed)
        if cfg.init == "points" and scene.points is not None:
            xyz, rgb = (torch.as_tensor(a, dtype=torch.float32) for a in scene.points)
        else:
            if cfg.init == "points":
                log.warning("scene '%s' has no SfM points: starting from %d random points", scene.source, cfg.random_points)
            # A cube around the camera rig, as the 3DGS trainer does for synthetic scenes.
            centers = scene.camera_centers
            mid, radius = centers.mean(0), scene.extent
            xyz = mid + (torch.rand(cfg.random_points, 3, generator=gen) * 2 - 1) * radius
            rgb = torch.rand(cfg.random_points, 3, generator=gen)
        self.geometry = GaussianModel.from_points(xyz, rgb, sh_degree=cfg.sh_degree, opacity=cfg.init_opacity)
        self.renderer = make_renderer(cfg.renderer_type, cfg.renderer, self.trainer.strategy.root_device)
        self.initial_count = self.geometry.num_gaussians
        if cfg.background is not None:
            self.background = torch.tensor(list(cfg.background), dtype=torch.float32)
        else:
            self.background = torch.stack([scene.images[i].reshape(-1, 3).mean(0) for i in scene.train_indices]).mean(0)

    def active_sh_degree(self, step: int) -> int:
        every = self.cfg.sh_degree_every
        return self.cfg.sh_degree if every <= 0 else min(self.cfg.sh_degree, step // every)

    # ----- training ------------------------------------------------------------------------------
    def training_step(self, batch, batch_idx):
        cfg, scene, g, d = self.cfg, self.scene, self.geometry, self.cfg.densify
        step = self.global_step
        self.set_stage("fit")
        opt = self.optimizers()
        # Position learning rate decays exponentially, as in 3DGS.
        frac = min(step / max(cfg.max_steps, 1), 1.0)
        for group in opt.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = cfg.lr.means * scene.extent * (cfg.lr_means_final_factor**frac)
        # Everything random in a step is drawn from (seed, step): resuming needs no RNG state.
        gen = torch.Generator().manual_seed(cfg.seed * 104729 + step)
        idx = scene.train_indices[int(torch.randint(len(scene.train_indices), (1,), generator=gen))]
        bg = torch.rand(3, generator=gen) if cfg.random_background else self.background
        cam = scene.cameras[idx]
        out = self.renderer.render(g, cam.to(self.device), background=bg.to(self.device))
        target = scene.images[idx].to(self.device)
        l1 = (out["rgb"] - target).abs().mean()
        loss = (1 - cfg.lambda_dssim) * l1 + cfg.lambda_dssim * (1 - ssim_loss_value(out["rgb"], target))
        opt.zero_grad(set_to_none=True)
        self.manual_backward(loss)
        if g.sh_rest.grad is not None:
            # Coefficients of the degrees not active yet get no gradient, so Adam leaves them at 0.
            g.sh_rest.grad[:, (self.active_sh_degree(step) + 1) ** 2 - 1 :] = 0
        d.collect_stats(g, out, cam, step)
        opt.step()
        self.log("train/loss", loss.detach(), prog_bar=True)
        self.log("train/gaussians", float(g.num_gaussians), prog_bar=True)
        # The graph still references the parameters' gradient accumulators, whose recorded shapes
        # would be stale once densification changes the number of Gaussians.
        del out, loss, l1
        d.refine(
            g, step, scene.extent, opt.optimizer, last_step=cfg.max_steps - 1, base_count=self.initial_count,
            generator=torch.Generator().manual_seed(cfg.seed * 7919 + step),
        )
        return None

    # ----- outputs -------------------------------------------------------------------------------
    def on_train_start(self) -> None:
        if not hasattr(self, "started"):
            self.started = time.perf_counter()

    def elapsed(self) -> float:
        """Wall seconds of the fit so far, the runs this one resumes included."""
        return self.seconds_before + time.perf_counter() - getattr(self, "started", time.perf_counter())

    @torch.no_grad()
    def evaluate_and_save(self, seconds: Optional[float] = None) -> dict:
        """Held-out metrics, save/reconstructed.ply, save/test_views.png and save/metrics.json
        (`seconds`: the fit time to report; default: the time so far)."""
        self.set_stage("evaluate")
        scene, g = self.scene, self.geometry
        views = scene.test_indices or scene.train_indices
        bg = self.background.to(self.device)
        renders = [self.renderer.render(g, scene.cameras[i].to(self.device), background=bg)["rgb"].clamp(0, 1) for i in views]
        truth = [scene.images[i].to(self.device) for i in views]
        g.save_ply(str(self.save_dir / "reconstructed.ply"))
        n_show = self.cfg.max_test_views
        self.save_image_grid("test_views.png", [[t, r] for t, r in zip(truth[:n_show], renders[:n_show])])
        metrics = {
            "psnr_test": psnr(torch.stack(renders), torch.stack(truth)),
            "ssim_test": ssim(torch.stack(renders), torch.stack(truth)),
            "n_gaussians": g.num_gaussians,
            "test_views": len(views),
            "held_out": bool(scene.test_indices),  # False: measured on training views
            "resolution": [int(scene.cameras[0].width), int(scene.cameras[0].height)],
            "steps": max(int(self.global_step), self.steps_before),
            "seconds": round(self.elapsed() if seconds is None else seconds, 3),
        }
        self.write_metrics_json(metrics)
        log.info(
            "reconstruct: %s PSNR %.2f dB, SSIM %.4f, %d Gaussians, %.0f s",
            "held-out" if scene.test_indices else "training-view", metrics["psnr_test"], metrics["ssim_test"],
            g.num_gaussians, metrics["seconds"],
        )
        return metrics

    def on_train_end(self) -> None:
        # The fit's time, frozen before the evaluation: the final checkpoint is written after it.
        self.fit_seconds = self.elapsed()
        self.evaluate_and_save(seconds=self.fit_seconds)

    def on_export(self) -> None:
        self.evaluate_and_save(seconds=self.seconds_before)  # the fit's time, not the export's

    # ----- checkpoints ---------------------------------------------------------------------------
    def extra_state(self) -> dict:
        return {"seconds": getattr(self, "fit_seconds", None) or self.elapsed(), "steps": int(self.global_step), "initial_count": self.initial_count}

    def load_extra_state(self, state: dict) -> None:
        self.seconds_before = float(state.get("seconds", 0.0))
        self.steps_before = int(state.get("steps", 0))
        self.initial_count = int(state.get("initial_count", self.initial_count))
