"""`simulated-depth`: a SIMULATED monocular depth estimator for scenes with a known edit.

Returns the TRUE disparity (1 / rendered depth where the render's alpha is high; background
pixels get the far value 0) of the scene an image shows, under an unknown affine map plus
corruption, like the relative disparity a real estimator (Depth Anything) returns:

  * which scene, per pixel: the image is compared (squared error, smoothed over a few pixels) with
    the renders of the source and of the true edited scene at its camera, and each pixel gets the
    disparity of the scene it looks more like (a partly or imperfectly edited image gets the new
    geometry where it shows it). An editor draws an object a few pixels off its true place (the
    simulated editor's position jitter). Compared in place (`follow_drawn_px` 0, the default), the
    estimator sees the new geometry mostly where the drawn object overlaps the true one: it tells the
    method where the truth is, and misses an object drawn clear of it. With `follow_drawn_px` N the
    true edit's changed layer is first moved by the whole pixels (up to N each way) that best explain
    the image, so the estimator sees the object where the image draws it, as a real one does;
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


def shifted(x: torch.Tensor, dx: int, dy: int) -> torch.Tensor:
    """(H, W, ...) translated by whole pixels (dx right, dy down), edges repeated: no value is mixed
    with its neighbours' (a depth edge stays an edge)."""
    h, w = x.shape[:2]
    ys = (torch.arange(h) - dy).clamp(0, h - 1)
    xs = (torch.arange(w) - dx).clamp(0, w - 1)
    return x[ys][:, xs]


def drawn_edit(image: torch.Tensor, views: dict, radius: int) -> tuple:
    """(rgb, depth, alpha, (dx, dy)): the true edited scene's render `views` (a TruthRenderer view)
    with its changed layer (where its colour, depth or alpha differs from the source's) moved by the
    whole-pixel shift within `radius` that best explains `image` (least squared error; the smaller
    shift on a tie), the source's render elsewhere; at `radius` 0 the true edited render as it is."""
    src = {k: views[f"src_{k}"] for k in ("rgb", "depth", "alpha")}
    edit = {k: views[f"edit_{k}"] for k in ("rgb", "depth", "alpha")}
    if radius <= 0:
        return edit["rgb"], edit["depth"], edit["alpha"], (0, 0)
    changed = (((edit["rgb"] - src["rgb"]).abs().amax(-1) > 1e-3) | ((edit["depth"] - src["depth"]).abs() > 1e-6)
               | ((edit["alpha"] - src["alpha"]).abs() > 1e-3))

    def moved(dx: int, dy: int, names=("rgb", "depth", "alpha")) -> dict:
        where = shifted(changed, dx, dy)
        return {k: torch.where(where[..., None] if src[k].dim() == 3 else where, shifted(edit[k], dx, dy), src[k])
                for k in names}

    best, best_err = (0, 0), None
    if bool(changed.any()):
        shifts = sorted(((dx, dy) for dx in range(-radius, radius + 1) for dy in range(-radius, radius + 1)),
                        key=lambda s: s[0] ** 2 + s[1] ** 2)
        for dx, dy in shifts:
            err = float(((image - moved(dx, dy, ("rgb",))["rgb"]) ** 2).sum())
            if best_err is None or err < best_err:
                best, best_err = (dx, dy), err
    out = moved(*best)
    return out["rgb"], out["depth"], out["alpha"], best


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
        # How far (pixels, each way) the estimator follows an object the image draws off its true
        # place (6: 4x the simulated editor's position jitter of a full edit); 0 compares in place.
        follow_drawn_px: int = 0
        alpha_threshold: float = 0.5  # below this rendered alpha a pixel is background (far)
        max_cached_views: int = 512

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where or "system.depth")
        if self.cfg.corruption < 0:
            raise ValueError(f"simulated-depth: corruption must be >= 0, got {self.cfg.corruption}")
        self.last_choice: List[str] = []  # "source" / "edited" per image of the last call
        self.last_shift: List[tuple] = []  # (dx, dy) the edit was found drawn at, per image of the last call

    def true_disparity(self, depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """1 / depth where alpha is high, 0 (far) elsewhere."""
        valid = (alpha > self.cfg.alpha_threshold) & (depth > 1e-6)
        return torch.where(valid, 1.0 / depth.clamp_min(1e-6), torch.zeros_like(depth))

    def _disparity(self, images: torch.Tensor, cameras: List[Camera]) -> torch.Tensor:
        h, w = images.shape[1:3]
        c = self.cfg
        out, self.last_choice, self.last_shift = [], [], []
        for img, cam in zip(images.detach().float().cpu(), cameras):
            cam = camera_for_image(cam, h, w, "simulated-depth")
            v = self.truth_renderer.views(cam)
            edit_rgb, edit_depth, edit_alpha, shift = drawn_edit(img, v, c.follow_drawn_px)
            err_src = gaussian_blur(((img - v["src_rgb"]) ** 2).mean(-1)[None], 1.5)[0]
            err_edit = gaussian_blur(((img - edit_rgb) ** 2).mean(-1)[None], 1.5)[0]
            use_edit = err_edit < err_src
            tag = "edit" if bool(use_edit.any()) else "src"
            self.last_choice.append("edited" if tag == "edit" else "source")
            self.last_shift.append(shift if tag == "edit" else (0, 0))
            disp_src = self.true_disparity(v["src_depth"], v["src_alpha"])
            disp_edit = self.true_disparity(edit_depth, edit_alpha)
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
