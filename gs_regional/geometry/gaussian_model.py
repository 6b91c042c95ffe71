"""The `gaussian-model` geometry: a set of 3D Gaussians as an nn.Module.

Parameter layout (N Gaussians, SH degree D, K = (D+1)^2 coefficients):
  means          (N, 3)
  quats          (N, 4)  (w, x, y, z), not necessarily normalised
  log_scales     (N, 3)
  opacity_logits (N,)    opacity = sigmoid(logit)
  sh_dc          (N, 3)     SH coefficient 0 per colour channel
  sh_rest        (N, K-1, 3) SH coefficients 1..K-1 per channel (empty when D = 0)
Buffers:
  mask           (N,) bool  selected for editing
  generation     (N,) long  0 = original, >0 = added by an edit
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn as nn

from gs_regional.registry import register
from gs_regional.utils.base import BaseModule

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


@register("gaussian-model")
class GaussianModel(BaseModule):
    @dataclass
    class Config:
        ply: Optional[str] = None  # load the scene from this INRIA-layout PLY
        sh_degree: int = 3  # for scenes created from points; a PLY's own degree wins
        drop_nonfinite: bool = False  # drop Gaussians with NaN/inf values instead of failing

    def __init__(self, cfg=None, n: int = 0, sh_degree: Optional[int] = None) -> None:
        super().__init__(cfg)
        degree = self.cfg.sh_degree if sh_degree is None else sh_degree
        self.sh_degree = int(degree)
        k = (self.sh_degree + 1) ** 2
        self.means = nn.Parameter(torch.zeros(n, 3))
        self.quats = nn.Parameter(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1))
        self.log_scales = nn.Parameter(torch.zeros(n, 3))
        self.opacity_logits = nn.Parameter(torch.zeros(n))
        self.sh_dc = nn.Parameter(torch.zeros(n, 3))
        self.sh_rest = nn.Parameter(torch.zeros(n, k - 1, 3))
        self.register_buffer("mask", torch.zeros(n, dtype=torch.bool))
        self.register_buffer("generation", torch.zeros(n, dtype=torch.long))

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def num_gaussians(self) -> int:
        return self.means.shape[0]

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def normalized_quats(self) -> torch.Tensor:
        return self.quats / self.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    @property
    def sh(self) -> torch.Tensor:
        """All SH coefficients, (N, K, 3)."""
        return torch.cat([self.sh_dc[:, None, :], self.sh_rest], dim=1)
