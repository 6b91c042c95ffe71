"""Example plugin: a `grayscale-editor` guidance ("make it black and white") without any model.

Use it from YAML like any built-in guidance:

    system:
      guidance_type: grayscale-editor
      guidance:
        strength: 1.0

`relevance()` is the colour saturation (chroma, max - min over RGB) of each pixel: exactly where
desaturating changes the image, so the regional pipeline localises the colourful parts of the
scene. `edit()` blends the images towards their luminance; a lower start timestep blends less, as
partial denoising from a lower noise level keeps more of the input. The prompt text is ignored.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Sequence

import torch

from gs_regional.config import ConfigError
from gs_regional.guidance.base import Guidance, check_images
from gs_regional.registry import register


@register("grayscale-editor")
class GrayscaleEditor(Guidance):
    @dataclass
    class Config:
        strength: float = 1.0  # 1: fully grey; 0: unchanged
        luma: List[float] = field(default_factory=lambda: [0.299, 0.587, 0.114])  # Rec. 601 weights
        num_train_timesteps: int = 1000  # t_start is read on this scale

    def __init__(self, cfg=None, where: str = "system.guidance") -> None:
        super().__init__(cfg, where)
        if not 0.0 <= self.cfg.strength <= 1.0:
            raise ConfigError(f"{where}.strength must be in [0, 1], got {self.cfg.strength}")
        if len(self.cfg.luma) != 3 or abs(sum(self.cfg.luma) - 1.0) > 1e-3:
            raise ConfigError(f"{where}.luma must be 3 weights that sum to 1, got {list(self.cfg.luma)}")

    def luminance(self, images: torch.Tensor) -> torch.Tensor:
        w = torch.tensor(self.cfg.luma, dtype=images.dtype, device=images.device)
        return (images * w).sum(-1)

    def relevance(self, images, prompt, timestep=600, samples=1, seed=0, cameras=None) -> torch.Tensor:
        images = check_images(images)
        chroma = images.amax(-1) - images.amin(-1)  # (B, H, W): 0 for greys, 1 for pure colours
        peak = chroma.flatten(1).amax(1).clamp_min(1e-6)[:, None, None]
        return (chroma / peak).clamp(0, 1)

    def edit(
        self,
        images: torch.Tensor,
        cond_images: torch.Tensor,
        prompt: str,
        t_start: Optional[int] = None,
        seed: int = 0,
        cameras: Optional[Sequence] = None,
    ) -> torch.Tensor:
        images = check_images(images)
        check_images(cond_images, "cond_images")
        amount = self.cfg.strength
        if t_start is not None:
            amount *= min(max(float(t_start) / self.cfg.num_train_timesteps, 0.0), 1.0)
        grey = self.luminance(images)[..., None].expand_as(images)
        return (images + amount * (grey - images)).clamp(0, 1)
