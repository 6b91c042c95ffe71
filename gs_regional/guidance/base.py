"""The guidance interface shared by `instructpix2pix`, `simulated-editor` and user plugins."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional, Sequence

import torch
import torch.nn.functional as F

from gs_regional.data.cameras import Camera
from gs_regional.utils.base import Configurable


def gaussian_blur(maps: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian filter of (B, H, W) maps, reflect-padded."""
    if sigma <= 0:
        return maps
    radius = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=maps.dtype, device=maps.device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    m = maps[:, None]
    h, w = m.shape[-2:]
    pad_w, pad_h = min(radius, w - 1), min(radius, h - 1)
    m = F.pad(m, (pad_w, pad_w, 0, 0), mode="reflect" if pad_w > 0 else "replicate")
    m = F.conv2d(m, k[radius - pad_w : radius + pad_w + 1].view(1, 1, 1, -1))
    m = F.pad(m, (0, 0, pad_h, pad_h), mode="reflect" if pad_h > 0 else "replicate")
    m = F.conv2d(m, k[radius - pad_h : radius + pad_h + 1].view(1, 1, -1, 1))
    return m[:, 0]


class Guidance(Configurable):
    """A 2D editor. Images are (B, H, W, 3) float tensors in [0, 1].

    Counters (reported by systems): `unet_evals` (one guided step on B images = 3*B),
    `vae_encodes`, `vae_decodes` (per image).
    """

    @dataclass
    class Config:
        pass

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where)
        self.reset_counters()

    def reset_counters(self) -> None:
        self.unet_evals = 0
        self.vae_encodes = 0
        self.vae_decodes = 0

    def counters(self) -> Dict[str, int]:
        return {"unet_evals": self.unet_evals, "vae_encodes": self.vae_encodes, "vae_decodes": self.vae_decodes}

    def relevance(
        self,
        images: torch.Tensor,
        prompt: str,
        timestep: int = 600,
        samples: int = 1,
        seed: int = 0,
        cameras: Optional[Sequence[Camera]] = None,
    ) -> torch.Tensor:
        """Per-view relevance maps (B, H, W) in [0, 1], each normalised to its own max."""
        raise NotImplementedError

    def mask(
        self,
        images: torch.Tensor,
        prompt: str,
        threshold: float = 0.6,
        blur_sigma: float = 2.0,
        timestep: int = 600,
        samples: int = 1,
        seed: int = 0,
        cameras: Optional[Sequence[Camera]] = None,
    ) -> torch.Tensor:
        """Binary 2D masks (B, H, W) float: threshold at γ, Gaussian-filter specks away, re-binarise.

        γ = 0 means "everything" (a global edit) and returns all ones without running the model.
        """
        b, h, w = images.shape[:3]
        if threshold <= 0:
            return torch.ones(b, h, w, device=images.device)
        rel = self.relevance(images, prompt, timestep=timestep, samples=samples, seed=seed, cameras=cameras)
        binary = (rel >= threshold).float()
        return (gaussian_blur(binary, blur_sigma) > 0.5).float()

    def edit(
        self,
        images: torch.Tensor,
        cond_images: torch.Tensor,
        prompt: str,
        t_start: Optional[int] = None,
        seed: int = 0,
        cameras: Optional[Sequence[Camera]] = None,
    ) -> torch.Tensor:
        """Edited images (B, H, W, 3): noise `images` to `t_start` (None: pure noise, a full edit) and
        denoise conditioned on `cond_images` and `prompt`."""
        raise NotImplementedError


def check_images(images: torch.Tensor, what: str = "images") -> torch.Tensor:
    """Validate a (B, H, W, 3) float batch in [0, 1]; a single (H, W, 3) image is batched."""
    if not isinstance(images, torch.Tensor):
        raise TypeError(f"{what} must be a torch.Tensor of shape (B, H, W, 3), got {type(images).__name__}")
    if images.dim() == 3:
        images = images[None]
    if images.dim() != 4 or images.shape[-1] != 3:
        raise ValueError(f"{what} must have shape (B, H, W, 3), got {tuple(images.shape)}")
    if not images.is_floating_point():
        raise TypeError(f"{what} must be float in [0, 1], got dtype {images.dtype}")
    lo, hi = float(images.min()), float(images.max())
    if lo < -1e-3 or hi > 1 + 1e-3:
        raise ValueError(f"{what} must be in [0, 1], got values in [{lo:.3g}, {hi:.3g}]")
    return images.clamp(0, 1)
