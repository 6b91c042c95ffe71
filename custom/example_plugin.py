"""Example plugin: a `grayscale-editor` guidance ("make it black and white") without any model.

Use it from YAML like any built-in guidance:

    system:
      guidance_type: grayscale-editor
      guidance:
        strength: 1.0

A guidance plugin implements only `_relevance` and `_edit`. The public `relevance`, `mask` and
`edit` it inherits from `Guidance` check the arguments first (image shapes and range, the prompt,
`timestep` / `t_start` in [0, num_train_timesteps), one camera per image), so these two methods
receive valid (B, H, W, 3) batches in [0, 1] and need no checks of their own.

`_relevance` is the colour saturation (chroma, max - min over RGB) of each pixel: exactly where
desaturating changes the image, so the regional pipeline localises the colourful parts of the
scene. `_edit` blends the images towards their luminance; a lower start timestep blends less, as
partial denoising from a lower noise level keeps more of the input. The prompt text is ignored.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional

import torch

from gs_regional.config import ConfigError
from gs_regional.guidance.base import Guidance
from gs_regional.registry import register


@register("grayscale-editor")
class GrayscaleEditor(Guidance):
    @dataclass
    class Config(Guidance.Config):  # inherits batch_size (views per call)
        strength: float = 1.0  # 1: fully grey; 0: unchanged
        luma: List[float] = field(default_factory=lambda: [0.299, 0.587, 0.114])  # Rec. 601 weights

    def __init__(self, cfg=None, where: str = "system.guidance") -> None:
        super().__init__(cfg, where)
        if not 0.0 <= self.cfg.strength <= 1.0:
            raise ConfigError(f"{where}.strength must be in [0, 1], got {self.cfg.strength}")
        if len(self.cfg.luma) != 3 or abs(sum(self.cfg.luma) - 1.0) > 1e-3:
            raise ConfigError(f"{where}.luma must be 3 weights that sum to 1, got {list(self.cfg.luma)}")

    def luminance(self, images: torch.Tensor) -> torch.Tensor:
        w = torch.tensor(self.cfg.luma, dtype=images.dtype, device=images.device)
        return (images * w).sum(-1)

    def _relevance(self, images, prompt, timestep, samples, seeds, cameras) -> torch.Tensor:
        chroma = images.amax(-1) - images.amin(-1)  # (B, H, W): 0 for greys, 1 for pure colours
        peak = chroma.flatten(1).amax(1).clamp_min(1e-6)[:, None, None]
        return (chroma / peak).clamp(0, 1)

    def _edit(self, images, cond_images, prompt, t_start: Optional[int], seeds, cameras) -> torch.Tensor:
        amount = self.cfg.strength
        if t_start is not None:  # t_start is in [0, num_train_timesteps) here
            amount *= t_start / self.num_train_timesteps
        grey = self.luminance(images)[..., None].expand_as(images)
        return (images + amount * (grey - images)).clamp(0, 1)
