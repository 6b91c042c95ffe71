"""The depth-estimator interface: relative disparity from images."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import torch

from gs_regional.data.cameras import Camera
from gs_regional.utils.base import Configurable


class DepthEstimator(Configurable):
    @dataclass
    class Config:
        pass

    def disparity(self, images: torch.Tensor, cameras: Optional[Sequence[Camera]] = None) -> torch.Tensor:
        """Relative (affine-ambiguous) disparity (B, H, W) at the input resolution for
        (B, H, W, 3) images in [0, 1]; larger = nearer."""
        raise NotImplementedError
