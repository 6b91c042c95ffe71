"""`simulated-editor`: a SIMULATOR of a 2D instruction editor, NOT a diffusion model.

It answers `relevance` and `edit` by rendering the TRUE edited scene of the attached ground truth
(`attach_ground_truth`; systems hand over the data module's, e.g. the synthetic scene's
`make_edit`) at the camera of each image, then degrading the answer with the failure modes a real
InstructPix2Pix shows, each with a configurable strength:

  relevance: the true region's rendered weight, grown by `spread` px and blurred (`blur`), with
             spatially correlated noise (`noise`), fading in views far from the front
             (`side_miss_*`: fully missed beyond `side_miss_end` degrees, as IP2P loses the
             region in side views), plus `leakage`: a
             related part that should not change (e.g. the body under the head) lights up at a
             fraction of the peak. Normalised per view to [0, 1] like the real maps.
  edit:      the true edited render, shifted by a per-view `position_jitter` (px) and recoloured by
             a per-view `color_jitter`, both seeded by (config seed, call seed, camera) and growing
             with t_start (largest for a full edit from pure noise, t_start=None) and shrinking as
             the input already shows the edit (partial denoising keeps existing structure); a little `bleed`
             of the edit's colour a couple of pixels past its area; then blended into the input
             as lerp(images, target, k(t_start)) with k = 1 - alphabar(t_start) of Stable
             Diffusion's schedule (k(None) = 1), so an edit from a lower t_start keeps more of the
             input, as partial denoising does. Only where the source and edited renders differ
             (plus bleed) is the image changed; elsewhere the input comes back with tiny noise.

It exists so that the 3D part of the method (lifting masks, depth-initialised geometry, sequential
refinement) can be measured against a known answer on CPU. The prompt is not read: the edit is the
ground truth's; `cond_images` are validated but the camera defines the view. Images must
come with their `cameras=`. Counters report what a real IP2P run would spend: 3*B UNet evaluations
per denoising step for the steps at or below t_start out of `num_inference_steps` (DDIM, leading
spacing, offset 1, as diffusers sets it up for Stable Diffusion), 2*B per relevance sample.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import torch
import torch.nn.functional as F

from gs_regional.data.cameras import Camera
from gs_regional.guidance.base import Guidance
from gs_regional.registry import register
from gs_regional.sim.truth import GroundTruthConsumer, camera_for_image, camera_seed
from gs_regional.utils.image import gaussian_blur


def _alphas_cumprod() -> torch.Tensor:
    """Stable Diffusion's training schedule (scaled linear betas 0.00085 -> 0.012, 1000 steps)."""
    betas = torch.linspace(0.00085**0.5, 0.012**0.5, 1000, dtype=torch.float64) ** 2
    return torch.cumprod(1 - betas, 0)


_ALPHAS_CUMPROD = _alphas_cumprod()


def edit_strength(t_start: Optional[int]) -> float:
    """How much of the input a partial denoise from t_start replaces: 1 - alphabar_t (1 for None)."""
    if t_start is None:
        return 1.0
    t = min(max(int(t_start), 0), 999)
    return float(1 - _ALPHAS_CUMPROD[t])


def denoising_steps(t_start: Optional[int], num_inference_steps: int = 20) -> int:
    """Denoising steps a DDIM run from t_start takes (None: all of them)."""
    if t_start is None:
        return num_inference_steps
    ratio = 1000 // num_inference_steps
    timesteps = [i * ratio + 1 for i in range(num_inference_steps)]  # leading spacing, offset 1
    return sum(1 for t in timesteps if t <= t_start)


def _mix_seed(*parts: int) -> int:
    s = 0
    for p in parts:
        s = (s * 1_000_003 + int(p)) % (2**61 - 1)
    return s


def _shift(x: torch.Tensor, dx: float, dy: float) -> torch.Tensor:
    """Translate (H, W, C) by (dx, dy) pixels, bilinear, edges repeated."""
    h, w = x.shape[:2]
    ys = torch.arange(h, dtype=x.dtype) - dy
    xs = torch.arange(w, dtype=x.dtype) - dx
    gy, gx = torch.meshgrid(2 * (ys + 0.5) / h - 1, 2 * (xs + 0.5) / w - 1, indexing="ij")
    grid = torch.stack([gx, gy], -1)[None]
    out = F.grid_sample(x.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0].permute(1, 2, 0)


@register("simulated-editor")
class SimulatedEditor(GroundTruthConsumer, Guidance):
    requires_cameras = True  # it renders the true edited scene at each view

    @dataclass
    class Config(Guidance.Config):
        seed: int = 0  # base seed of the per-view randomness (combined with the call's seed and the camera)
        renderer: str = "torch-rasterizer"  # renders the ground truth
        background: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # as the data module
        # --- relevance failure modes ---
        spread: int = 1  # px, the map covers a little more than the region (real maps are blobby)
        blur: float = 1.5  # px, Gaussian blur of the map (real maps are soft, from 64x64 latents)
        noise: float = 0.1  # std of spatially correlated noise, relative to the region's peak
        noise_scale: float = 2.0  # px, correlation length of that noise
        side_miss_start: float = 60.0  # degrees from the front where the region starts to fade
        side_miss_end: float = 110.0  # degrees beyond which the region is missed completely
        leakage: float = 0.35  # the related part lights up at this fraction of the region's peak
        # --- edit failure modes (values at a full edit, t_start=None; scaled by t_start/1000) ---
        color_jitter: float = 0.06  # std of the per-view colour gain (offset: half of it)
        position_jitter: float = 1.5  # px, std of the per-view shift of the edit
        bleed: float = 2.0  # px, how far the edit's colour spreads past its area
        bleed_strength: float = 0.5  # how strongly it does
        residual_noise: float = 0.003  # std of the noise on the rest of the image
        # A denoise from t_start re-generates the WHOLE image, not only the edit: detail is lost
        # (blur, px) and the tone drifts per view (std of a colour gain; offset: half of it). Both
        # are scaled by k(t_start), so they are strongest for a full edit and small at t=250.
        regen_blur: float = 0.8
        regen_drift: float = 0.03
        edit_threshold: float = 0.02  # a pixel is part of the edit where renders differ by more
        num_inference_steps: int = 20  # only for counting UNet evaluations
        max_cached_views: int = 512  # renders of the true scenes kept per camera

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where or "system.guidance")
        if not 0 <= self.cfg.side_miss_start <= self.cfg.side_miss_end:
            raise ValueError("simulated-editor: need 0 <= side_miss_start <= side_miss_end (degrees)")

    def _cameras(self, images: torch.Tensor, cameras: List[Camera], op: str) -> List[Camera]:
        h, w = images.shape[1:3]
        return [camera_for_image(c, h, w, f"simulated-editor.{op}") for c in cameras]

    def _angle_from_front(self, camera: Camera) -> float:
        truth = self.ground_truth
        front = truth.front.cpu()
        d = camera.center.cpu() - truth.center.cpu()
        cos = float(d @ front / (d.norm() * front.norm()).clamp_min(1e-9))
        return math.degrees(math.acos(max(-1.0, min(1.0, cos))))

    # ------------------------------------------------------------------ relevance
    def _relevance(
        self, images: torch.Tensor, prompt: str, timestep: int, samples: int, seeds: List[int], cameras: List[Camera]
    ) -> torch.Tensor:
        cams = self._cameras(images, cameras, "relevance")
        c = self.cfg
        out = []
        for cam, seed in zip(cams, seeds):
            maps = self.truth_renderer.region_maps(cam)
            region, related = maps[..., 0], maps[..., 1]
            if c.spread > 0:
                k = 2 * int(c.spread) + 1
                region = F.max_pool2d(region[None, None], k, 1, k // 2)[0, 0]
            a = self._angle_from_front(cam)
            span = max(c.side_miss_end - c.side_miss_start, 1e-6)
            fade = min(max((c.side_miss_end - a) / span, 0.0), 1.0)
            gen = torch.Generator().manual_seed(_mix_seed(c.seed, seed, camera_seed(cam), 1))
            noise = torch.zeros_like(region)
            for _ in range(samples):  # averaging samples reduces the noise, as with the real model
                n = gaussian_blur(torch.randn(1, *region.shape, generator=gen), c.noise_scale)[0]
                noise += n / n.std().clamp_min(1e-8)
            raw = fade * region + c.leakage * related + c.noise * noise / samples
            raw = gaussian_blur(raw[None], c.blur)[0].clamp_min(0)
            peak = raw.max()
            out.append(raw / peak if peak > 1e-8 else torch.zeros_like(raw))
        b = images.shape[0]
        self.unet_evals += 2 * b * samples  # conditional + unconditional prediction per sample
        self.vae_encodes += b
        return torch.stack(out).to(images.device)

    # ------------------------------------------------------------------ edit
    def _jitter(self, camera: Camera, seed: int, t_start: Optional[int], novelty: float = 1.0):
        c = self.cfg
        scale = 1.0 if t_start is None else min(max(t_start, 0), 1000) / 1000.0
        scale *= novelty
        gen = torch.Generator().manual_seed(_mix_seed(c.seed, seed, camera_seed(camera), 2))
        shift = torch.randn(2, generator=gen, dtype=torch.float64) * c.position_jitter * scale
        gain = 1 + torch.randn(3, generator=gen) * c.color_jitter * scale
        offset = torch.randn(3, generator=gen) * c.color_jitter * 0.5 * scale
        return shift, gain, offset, gen

    def view_jitter(self, camera: Camera, seed: int = 0, t_start: Optional[int] = None) -> Dict[str, torch.Tensor]:
        """The per-view perturbation `edit` applies at this camera: shift (dx, dy) in pixels,
        colour gain (3,) and offset (3,); they grow with t_start (largest for None)."""
        shift, gain, offset, _ = self._jitter(camera, seed, t_start)
        return {"shift": shift.float(), "gain": gain, "offset": offset}

    def _regenerate(self, img: torch.Tensor, camera: Camera, seed: int, k: float) -> torch.Tensor:
        """The input as a partial denoise with strength k re-generates it: blurred, tone-shifted."""
        c = self.cfg
        if k <= 0 or (c.regen_blur <= 0 and c.regen_drift <= 0):
            return img
        gen = torch.Generator().manual_seed(_mix_seed(c.seed, seed, camera_seed(camera), 3))
        gain = 1 + torch.randn(3, generator=gen) * c.regen_drift
        offset = torch.randn(3, generator=gen) * c.regen_drift * 0.5
        soft = torch.stack([gaussian_blur(img[..., i][None], c.regen_blur)[0] for i in range(3)], -1)
        return img + k * ((soft * gain + offset).clamp(0, 1) - img)

    def _edit(
        self, images: torch.Tensor, cond_images: torch.Tensor, prompt: str, t_start: Optional[int], seeds: List[int], cameras
    ) -> torch.Tensor:
        cams = self._cameras(images, cameras, "edit")
        c = self.cfg
        steps = denoising_steps(t_start, c.num_inference_steps)
        if steps == 0:
            raise ValueError(f"simulated-editor.edit: t_start={t_start} is below the last DDIM timestep (1): nothing to denoise")
        k = edit_strength(t_start)
        out = []
        for img, cam, seed in zip(images.detach().float().cpu(), cams, seeds):
            v = self.truth_renderer.views(cam)
            diff = torch.maximum((v["edit_rgb"] - v["src_rgb"]).abs().amax(-1), (v["edit_alpha"] - v["src_alpha"]).abs())
            area = ((diff - c.edit_threshold) / (2 * c.edit_threshold)).clamp(0, 1)  # soft edges
            # A partial denoise keeps the structure the input already has: the more the input
            # already shows the edit where it belongs, the less the edit moves from view to view.
            # (A full edit from pure noise does not look at the input.)
            novelty = 1.0
            if t_start is not None and float(area.sum()) > 0:
                err_in = float(((img - v["edit_rgb"]).abs().mean(-1) * area).sum())
                err_src = float(((v["src_rgb"] - v["edit_rgb"]).abs().mean(-1) * area).sum())
                novelty = min(max(err_in / max(err_src, 1e-8), 0.0), 1.0)
            shift, gain, offset, gen = self._jitter(cam, seed, t_start, novelty)
            moved = _shift(torch.cat([v["edit_rgb"], area[..., None]], -1), float(shift[0]), float(shift[1]))
            target = (moved[..., :3] * gain + offset).clamp(0, 1)
            area = moved[..., 3].clamp(0, 1)
            weight, colour = area, target
            if c.bleed > 0 and c.bleed_strength > 0:
                spread = gaussian_blur(area[None], c.bleed)[0]
                ring = ((2 * spread).clamp(0, 1) * (1 - area) * c.bleed_strength)
                # the edit's own colour carried outwards (normalised convolution)
                carried = torch.stack([gaussian_blur((target[..., i] * area)[None], c.bleed)[0] for i in range(3)], -1)
                carried = carried / spread[..., None].clamp_min(1e-6)
                weight = area + ring
                colour = (area[..., None] * target + ring[..., None] * carried) / weight[..., None].clamp_min(1e-6)
            w = (k * weight)[..., None]
            edited = self._regenerate(img, cam, seed, k) * (1 - w) + colour * w
            edited = edited + c.residual_noise * torch.randn(edited.shape, generator=gen)
            out.append(edited.clamp(0, 1))
        b = images.shape[0]
        self.unet_evals += 3 * b * steps
        self.vae_encodes += b + (b if t_start is not None else 0)  # condition image (+ the input to noise)
        self.vae_decodes += b
        return torch.stack(out).to(images.device, images.dtype)
