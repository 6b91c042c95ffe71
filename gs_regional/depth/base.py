"""The depth-estimator interface: relative disparity from images.

Template method: `disparity` checks the images and cameras once, then calls the estimator's
`_disparity`; an estimator implements only `_disparity`."""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence

import torch

from gs_regional.data.cameras import Camera
from gs_regional.utils.base import Configurable, component_name
from gs_regional.utils.image import check_cameras, check_images, check_output_shape


class DepthEstimator(Configurable):
    @dataclass
    class Config:
        pass

    # True for estimators that cannot work without one camera per image (simulators rendering a
    # known scene): `disparity` then rejects a call without cameras.
    requires_cameras: bool = False

    def disparity(self, images: torch.Tensor, cameras: Optional[Sequence[Camera]] = None) -> torch.Tensor:
        """Relative (affine-ambiguous) disparity (B, H, W) at the input resolution for
        (B, H, W, 3) images in [0, 1] (a single (H, W, 3) image is batched); larger = nearer.
        `cameras`, when given, are one per image."""
        where = f"{component_name(self)}.disparity"
        images = check_images(images, f"{where}: images")
        cameras = check_cameras(cameras, images.shape[0], where, self.requires_cameras)
        return check_output_shape(self._disparity(images, cameras), images.shape[:3], where)

    def _disparity(self, images: torch.Tensor, cameras: Optional[List[Camera]]) -> torch.Tensor:
        """Implement this: `images` are a checked (B, H, W, 3) batch in [0, 1] and `cameras`
        None or a list of one camera per image."""
        raise NotImplementedError(f"{type(self).__name__} must implement _disparity(images, cameras)")
