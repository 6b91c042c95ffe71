"""`reconstruct`: fit a 3DGS to posed photos (for scenes that come without a trained splat)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import torch

from gs_regional.config import ConfigError
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.metrics.image import psnr, ssim, ssim_loss_value
from gs_regional.registry import find, register
from gs_regional.systems.base import BaseSystem
from gs_regional.systems.edit_base import LearningRates


@dataclass
class DensifyConfig:
    start: int = 100
    stop: int = 1500
    every: int = 100
    grad_threshold: float = 0.0002
    opacity_reset_every: int = 1000
    max_gaussians: int = 200000


@register("reconstruct")
class Reconstruct(BaseSystem):
    @dataclass
    class Config:
        renderer_type: str = "torch-rasterizer"
        renderer: dict = field(default_factory=dict)
        sh_degree: int = 3
        init: str = "points"  # "points" (SfM points of the scene) or "random"
        random_points: int = 20000
        max_steps: int = 3000
        lambda_dssim: float = 0.2
        seed: int = 0
        lr: LearningRates = field(default_factory=LearningRates)
        lr_means_final_factor: float = 0.01  # exponential decay of the position learning rate
        densify: DensifyConfig = field(default_factory=DensifyConfig)
        random_background: bool = False

    def __init__(self, cfg=None, resumed: bool = False) -> None:
        super().__init__(cfg, resumed=resumed)
        self.renderer = find(self.cfg.renderer_type, kind="renderers")(self.cfg.renderer)
        self.geometry: Optional[GaussianModel] = None

    @property
    def total_steps(self) -> int:
        return self.cfg.max_steps

    def setup(self, stage: Optional[str] = None) -> None:
        if self.geometry is not None:
            return
        dm = self.trainer.datamodule
        dm.setup(stage)
        self.scene = scene = dm.scene
        if scene.images is None:
            raise ConfigError(f"reconstruct needs photos, but the scene '{scene.source}' has no images")
        gen = torch.Generator().manual_seed(self.cfg.seed)
        if self.cfg.init == "points" and scene.points is not None:
            xyz, rgb = (torch.as_tensor(a, dtype=torch.float32) for a in scene.points)
        elif self.cfg.init in ("points", "random"):
            if self.cfg.init == "points":
                print(f"reconstruct: scene '{scene.source}' has no SfM points; starting from random points")
            centers = scene.camera_centers
            mid, radius = centers.mean(0), scene.extent
            xyz = mid + (torch.rand(self.cfg.random_points, 3, generator=gen) * 2 - 1) * radius
            rgb = torch.rand(self.cfg.random_points, 3, generator=gen)
        else:
            raise ConfigError(f"system.init must be 'points' or 'random', got '{self.cfg.init}'")
        self.geometry = GaussianModel.from_points(xyz, rgb, sh_degree=self.cfg.sh_degree)

    def configure_optimizers(self):
        lr = self.cfg.lr
        scale = {"means": self.scene.extent}
        groups = [
            {"params": [getattr(self.geometry, n)], "lr": getattr(lr, n) * scale.get(n, 1.0), "name": n}
            for n in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
        ]
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15)

    def training_step(self, batch, batch_idx):
        cfg, scene, g = self.cfg, self.scene, self.geometry
        step = self.global_step
        self.set_stage("fit")
        opt = self.optimizers()
        # Position learning rate decays exponentially, as in 3DGS.
        frac = min(step / max(cfg.max_steps, 1), 1.0)
        for group in opt.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = cfg.lr.means * scene.extent * (cfg.lr_means_final_factor**frac)
        gen = torch.Generator().manual_seed(cfg.seed * 104729 + step)
        idx = scene.train_indices[int(torch.randint(len(scene.train_indices), (1,), generator=gen))]
        bg = torch.rand(3, generator=gen) if cfg.random_background else torch.zeros(3)
        out = self.renderer.render(g, scene.cameras[idx].to(self.device), background=bg.to(self.device))
        target = scene.images[idx].to(self.device)
        loss = (1 - cfg.lambda_dssim) * (out["rgb"] - target).abs().mean() + cfg.lambda_dssim * (
            1 - ssim_loss_value(out["rgb"], target)
        )
        opt.zero_grad(set_to_none=True)
        self.manual_backward(loss)
        d = cfg.densify
        if step < d.stop and out["means2d"].grad is not None:
            g.add_densification_stats(out["means2d"].grad, out["visible"])
        opt.step()
        with torch.no_grad():
            if d.start <= step < d.stop and step % d.every == 0 and step > 0:
                g.densify_and_prune(
                    grad_threshold=d.grad_threshold,
                    scene_extent=scene.extent,
                    max_gaussians=d.max_gaussians,
                    optimizer=opt.optimizer,
                )
            if d.opacity_reset_every and step > 0 and step % d.opacity_reset_every == 0 and step < d.stop:
                g.reset_opacity(optimizer=opt.optimizer)
        self.log("train/loss", loss.detach(), prog_bar=True)
        self.log("train/gaussians", float(g.num_gaussians), prog_bar=True)
        return None

    @torch.no_grad()
    def on_train_end(self) -> None:
        self.set_stage("evaluate")
        scene, g = self.scene, self.geometry
        views = scene.test_indices or scene.train_indices
        renders = [self.renderer.render(g, scene.cameras[i].to(self.device))["rgb"].clamp(0, 1) for i in views]
        truth = [scene.images[i].to(self.device) for i in views]
        metrics = {
            "psnr_test": psnr(torch.stack(renders), torch.stack(truth)),
            "ssim_test": ssim(torch.stack(renders), torch.stack(truth)),
            "n_gaussians": g.num_gaussians,
            "test_views": len(views),
            "steps": self.global_step,
            "seconds": round(time.perf_counter() - self.fit_started, 3) if hasattr(self, "fit_started") else None,
        }
        g.save_ply(str(self.save_dir / "reconstructed.ply"))
        self.save_image_grid("test_views.png", [[t, r] for t, r in zip(truth[:6], renders[:6])])
        self.write_metrics_json(metrics)
        print(f"reconstruct: held-out PSNR {metrics['psnr_test']:.2f} dB, SSIM {metrics['ssim_test']:.4f}, {g.num_gaussians} Gaussians")

    def on_train_start(self) -> None:
        self.fit_started = time.perf_counter()
