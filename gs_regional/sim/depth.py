"""`simulated-depth`: a SIMULATED monocular depth estimator for scenes with a known edit.

Returns the TRUE disparity (1 / rendered depth where the render's alpha is high; background
pixels get the far value 0) of the scene an image shows, under an unknown affine map plus
corruption, like the relative disparity a real estimator (Depth Anything) returns:

  * which scene, per pixel: the image is compared (squared error, smoothed over a few pixels) with
    the renders of the source and of the true edited scene at its camera, and each pixel gets the
    disparity of the scene it looks more like (a partly or imperfectly edited image gets the new
    geometry where it shows it);
  * affine map: scale log-uniform in [0.5, 5] and shift in [-0.5, 0.5] x the mean disparity, drawn
    from (seed, camera), so it is unknown to the caller and differs between views but is the same
    for the edited and the unedited image of one view (a real estimator shows two near-identical
    images alike);
  * corruption (0 = exact): Gaussian noise of `noise * corruption` x the image's disparity range
    and a fraction `outliers * corruption` of pixels replaced by random values in that range;
  * a bias of the edit's new geometry (0 = none): where the image shows the edited scene at a depth
    that differs from the source's, the disparity is scaled by 1 + `edit_scale_bias` and shifted by
    `edit_shift_bias` x the mean disparity before the affine map, as a real estimator misjudges
    how far a new object stands out. Calibration on the pixels outside the edit cannot see it.

Images must come with their `cameras=`. The scenes are those of the ground truth handed over with
`attach_ground_truth` (systems hand over `SceneData.ground_truth`, e.g. the synthetic scene's).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List

import torch

from gs_regional.data.cameras import Camera
from gs_regional.depth.base import DepthEstimator
from gs_regional.registry import register
from gs_regional.sim.truth import GroundTruthConsumer, camera_for_image, camera_seed
from gs_regional.utils.image import gaussian_blur


@register("simulated-depth")
class SimulatedDepth(GroundTruthConsumer, DepthEstimator):
    requires_cameras = True  # it renders the true depth of the ground truth's scenes at each view

    @dataclass
    class Config:
        seed: int = 0  # draws the per-view affine map and the noise
        renderer: str = "torch-rasterizer"  # renders the ground truth
        background: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # as the data module
        corruption: float = 1.0  # overall strength of the corruption below (0: exact up to the affine map)
        noise: float = 0.01  # noise std as a fraction of the image's disparity range, at corruption 1
        outliers: float = 0.005  # fraction of pixels replaced by random values, at corruption 1
        edit_scale_bias: float = 0.0  # relative scale error of the disparity of the edit's new geometry
        edit_shift_bias: float = 0.0  # its shift error, as a fraction of the mean disparity
        alpha_threshold: float = 0.5  # below this rendered alpha a pixel is background (far)
        max_cached_views: int = 512

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where or "system.depth")
        if self.cfg.corruption < 0:
            raise ValueError(f"simulated-depth: corruption must be >= 0, got {self.cfg.corruption}")
        self.last_choice: List[str] = []  # "source" / "edited" per image of the last call

    def true_disparity(self, depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """1 / depth where alpha is high, 0 (far) elsewhere."""
        valid = (alpha > self.cfg.alpha_threshold) & (depth > 1e-6)
        return torch.where(valid, 1.0 / depth.clamp_min(1e-6), torch.zeros_like(depth))

    def _disparity(self, images: torch.Tensor, cameras: List[Camera]) -> torch.Tensor:
        h, w = images.shape[1:3]
        c = self.cfg
        out, self.last_choice = [], []
        for img, cam in zip(images.detach().float().cpu(), cameras):
            cam = camera_for_image(cam, h, w, "simulated-depth")
            v = self.truth_renderer.views(cam)
            err_src = gaussian_blur(((img - v["src_rgb"]) ** 2).mean(-1)[None], 1.5)[0]
            err_edit = gaussian_blur(((img - v["edit_rgb"]) ** 2).mean(-1)[None], 1.5)[0]
            use_edit = err_edit < err_src
            tag = "edit" if bool(use_edit.any()) else "src"
            self.last_choice.append("edited" if tag == "edit" else "source")
            disp_src = self.true_disparity(v["src_depth"], v["src_alpha"])
            disp_edit = self.true_disparity(v["edit_depth"], v["edit_alpha"])
            if c.edit_scale_bias != 0 or c.edit_shift_bias != 0:
                new_geometry = (disp_edit - disp_src).abs() > 1e-3 * float(disp_src.abs().max()) + 1e-12
                biased = disp_edit * (1 + c.edit_scale_bias) + c.edit_shift_bias * float(disp_src.mean())
                disp_edit = torch.where(new_geometry, biased, disp_edit)
            disp = torch.where(use_edit, disp_edit, disp_src)

            # the affine map depends on (seed, camera) only; the noise also on which scene it is
            gen = torch.Generator().manual_seed((c.seed * 1_000_003 + camera_seed(cam)) % (2**61 - 1))
            scale = math.exp(float(torch.empty(1).uniform_(math.log(0.5), math.log(5.0), generator=gen)))
            shift = float(torch.empty(1).uniform_(-0.5, 0.5, generator=gen)) * float(disp_src.mean())
            rel = scale * disp + shift
            if c.corruption > 0:
                gen = torch.Generator().manual_seed((c.seed * 1_000_003 + camera_seed(cam) * 2 + (tag == "edit")) % (2**61 - 1))
                lo, hi = float(rel.min()), float(rel.max())
                rel = rel + torch.randn(rel.shape, generator=gen) * c.noise * c.corruption * (hi - lo)
                hit = torch.rand(rel.shape, generator=gen) < c.outliers * c.corruption
                rel = torch.where(hit, lo + (hi - lo) * torch.rand(rel.shape, generator=gen), rel)
            out.append(rel)
        return torch.stack(out).to(images.device)
