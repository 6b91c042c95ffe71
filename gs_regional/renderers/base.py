"""The renderer interface shared by `torch-rasterizer` and `gsplat-rasterizer`."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional

import torch

from gs_regional.data.cameras import Camera
from gs_regional.utils.base import Configurable


class Renderer(Configurable):
    """Renders a GaussianModel from a Camera.

    `render(model, camera, background=None, override_color=None)` returns a dict:
      rgb     (H, W, 3) float, composited over `background`
      depth   (H, W)    expected depth  sum_i w_i z_i / alpha  (0 where alpha is 0)
      alpha   (H, W)    accumulated opacity sum_i w_i
      means2d (N, 2)    screen-space means; `.retain_grad()` is called so that densification
                        can read the view-space positional gradient after backward
      radii   (N,)      pixel radius of each Gaussian, 0 where not visible
      visible (N,)      bool
    `override_color` (N, C) replaces the SH colours with any per-Gaussian feature (C may be != 3);
    then `rgb` has C channels and the background is zero. Used to lift 2D masks to 3D.
    """

    @dataclass
    class Config:
        background: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
        tile_size: int = 16
        near_plane: float = 0.01
        far_plane: float = 1e10
        eps2d: float = 0.3  # low-pass added to the 2D covariance diagonal, pixels^2

    def render(
        self,
        model,
        camera: Camera,
        background: Optional[torch.Tensor] = None,
        override_color: Optional[torch.Tensor] = None,
    ) -> Dict[str, torch.Tensor]:
        raise NotImplementedError

    def default_background(self, device) -> torch.Tensor:
        return torch.tensor(self.cfg.background, dtype=torch.float32, device=device)
