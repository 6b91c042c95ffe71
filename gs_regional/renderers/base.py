"""The renderer interface shared by `torch-rasterizer` and `gsplat-rasterizer`.

Template method: `render` checks the arguments once (override colours, background) and calls the
renderer's `_render`; a renderer implements only `_render`."""
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

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where)
        if self.cfg.tile_size < 1:
            raise ValueError(f"renderer.tile_size must be >= 1, got {self.cfg.tile_size}")

    def render(
        self,
        model,
        camera: Camera,
        background: Optional[torch.Tensor] = None,
        override_color: Optional[torch.Tensor] = None,
    ) -> Dict[str, torch.Tensor]:
        means = model.means
        n = means.shape[0]
        if override_color is not None:
            if override_color.dim() != 2 or override_color.shape[0] != n:
                raise ValueError(
                    f"override_color must be (N, C) with N = {n} Gaussians, got "
                    f"{tuple(override_color.shape)}"
                )
            bg = None  # the background is zero for features
        else:
            bg = self.default_background(means.device) if background is None else background
            bg = torch.as_tensor(bg, device=means.device, dtype=means.dtype).reshape(-1)
            if bg.numel() != 3:
                raise ValueError(f"background must have 3 values, got {bg.numel()}")
        return self._render(model, camera, bg, override_color)

    def _render(
        self, model, camera: Camera, background: Optional[torch.Tensor], override_color: Optional[torch.Tensor]
    ) -> Dict[str, torch.Tensor]:
        """Implement this: the dict described above. `background` is a (3,) tensor on the model's
        device and dtype, None when `override_color` (N, C) is given (checked, N rows)."""
        raise NotImplementedError(f"{type(self).__name__} must implement _render(model, camera, background, override_color)")

    def default_background(self, device) -> torch.Tensor:
        return torch.tensor(self.cfg.background, dtype=torch.float32, device=device)

    def pixel_weights(self, model, camera: Camera) -> "PixelWeights":
        """The compositing weights of `model` seen from `camera`, as a linear map (see
        `PixelWeights`). This generic version renders once per use; a renderer that can keep the
        weights (the torch-rasterizer) overrides it so that repeated uses cost no new render."""
        return RenderedPixelWeights(self, model, camera)


class PixelWeights:
    """w_i(x), the alpha-compositing weight of Gaussian i at pixel x, for fixed geometry.

    `splat(feats)` (N, C) -> (H, W, C): sum_i w_i(x) f_i, a render of per-Gaussian features on a zero
    background; `gather(image)` (H, W) or (H, W, C) -> (N,) or (N, C): sum_x w_i(x) image(x), its
    adjoint. Localization lifts 2D masks with `gather` and renders selections back with `splat`.
    """

    def splat(self, feats: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def gather(self, image: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def totals(self, height: int, width: int, device=None) -> torch.Tensor:
        """(N,) each Gaussian's weight summed over every pixel of the view: how much of it the view
        shows, in pixels (`gather` of an all-ones image)."""
        return self.gather(torch.ones(height, width, device=device))


class RenderedPixelWeights(PixelWeights):
    """Any renderer: `splat` renders with `override_color`; `gather` is the gradient of
    sum_x image(x) * render(f)(x) with respect to f, which is exactly sum_x w_i(x) image(x)."""

    def __init__(self, renderer: Renderer, model, camera: Camera) -> None:
        self.renderer, self.model, self.camera = renderer, model, camera

    @torch.no_grad()
    def splat(self, feats: torch.Tensor) -> torch.Tensor:
        return self.renderer.render(self.model, self.camera, override_color=feats)["rgb"]

    def gather(self, image: torch.Tensor) -> torch.Tensor:
        flat = image.dim() == 2
        img = (image[..., None] if flat else image).to(self.model.means.device).float()
        feat = torch.ones(self.model.num_gaussians, img.shape[-1], device=img.device, requires_grad=True)
        with torch.enable_grad():
            out = self.renderer.render(self.model, self.camera, override_color=feat)["rgb"]
            (grad,) = torch.autograd.grad((out * img).sum(), feat)
        return grad[:, 0] if flat else grad
