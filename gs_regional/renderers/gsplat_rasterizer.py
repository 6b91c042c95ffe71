"""The `gsplat-rasterizer`: the same interface over gsplat's CUDA kernels (optional, GPU only).

gsplat is an optional dependency (`pip install 'gs_regional[gsplat]'`); without it, or without a
CUDA GPU, constructing this renderer fails with a message that says so. The pure-PyTorch
`torch-rasterizer` implements the same semantics and runs everywhere.
"""
from __future__ import annotations

import weakref
from typing import Dict, Optional

import torch

from gs_regional.data.cameras import Camera
from gs_regional.registry import register
from gs_regional.renderers.base import Renderer

try:
    import gsplat as _gsplat

    _GSPLAT_IMPORT_ERROR: Optional[BaseException] = None
except Exception as e:  # ImportError, or a gsplat whose CUDA extension fails to load
    _gsplat = None
    _GSPLAT_IMPORT_ERROR = e

INSTALL_HINT = (
    "install it with `pip install 'gs_regional[gsplat]'` on a machine with a CUDA GPU, "
    "or use `renderer_type: torch-rasterizer` (pure PyTorch, runs on CPU and GPU)"
)


def gsplat_available() -> bool:
    """True when gsplat imports and a CUDA device is present."""
    return _gsplat is not None and torch.cuda.is_available()


def mirror_grad(src: torch.Tensor, index: int = 0) -> torch.Tensor:
    """`src[index]` as a tensor whose `.grad` receives src's gradient slice after backward.

    gsplat's means2d is (C, N, 2) and is what its kernels consume, so a plain view `src[0]` would
    never get a gradient (it is not on the path to the loss). A hook copies the slice over. The hook
    holds the view weakly: a strong reference would close a cycle through the autograd graph
    (src's node -> hook -> view -> view's node -> src's node) that Python's collector cannot see,
    so every render's graph, and the parameters' gradient accumulators in it, would live forever.
    """
    view = src[index]
    if src.requires_grad:
        view_ref = weakref.ref(view)

        def hook(grad: torch.Tensor) -> None:
            v = view_ref()
            if v is None:  # the caller let the view go: nobody reads its gradient
                return
            g = grad[index].detach()
            v.grad = g.clone() if v.grad is None else v.grad + g

        view.retain_grad()
        src.register_hook(hook)
    return view


@register("gsplat-rasterizer")
class GsplatRasterizer(Renderer):
    """gsplat.rasterization (gsplat 1.x), render_mode "RGB+ED", classic mode, unpacked."""

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where)
        if _gsplat is None:
            raise ImportError(
                f"renderer 'gsplat-rasterizer' needs the gsplat package, which could not be "
                f"imported ({type(_GSPLAT_IMPORT_ERROR).__name__}: {_GSPLAT_IMPORT_ERROR}); "
                f"{INSTALL_HINT}"
            )
        if not torch.cuda.is_available():
            raise RuntimeError(
                "renderer 'gsplat-rasterizer' needs a CUDA GPU (gsplat's kernels are CUDA only) "
                f"but torch.cuda.is_available() is False; {INSTALL_HINT}"
            )

    def _render(
        self, model, camera: Camera, bg: Optional[torch.Tensor], override_color: Optional[torch.Tensor]
    ) -> Dict[str, torch.Tensor]:
        means = model.means
        if not means.is_cuda:
            raise RuntimeError(
                "renderer 'gsplat-rasterizer' needs the model on a CUDA device; call "
                "model.cuda() first (or use torch-rasterizer on CPU)"
            )
        device = means.device
        viewmats = camera.world_to_camera.to(device=device, dtype=torch.float32)[None]
        Ks = camera.K.to(device=device)[None]
        if override_color is not None:
            colors, sh_degree, backgrounds = override_color, None, None
            channels = override_color.shape[1]
        else:
            colors = torch.cat([model.sh_dc[:, None, :], model.sh_rest], dim=1)
            sh_degree, channels = model.sh_degree, 3
            backgrounds = bg.float()[None]
        render_colors, render_alphas, meta = _gsplat.rasterization(
            means=means,
            quats=model.quats,
            scales=torch.exp(model.log_scales),
            opacities=torch.sigmoid(model.opacity_logits),
            colors=colors,
            viewmats=viewmats,
            Ks=Ks,
            width=int(camera.width),
            height=int(camera.height),
            near_plane=self.cfg.near_plane,
            far_plane=self.cfg.far_plane,
            eps2d=self.cfg.eps2d,
            sh_degree=sh_degree,
            packed=False,  # meta["means2d"] is then (1, N, 2), indexable per Gaussian
            tile_size=self.cfg.tile_size,
            backgrounds=backgrounds,
            render_mode="RGB+ED",
            rasterize_mode="classic",
        )
        radii = meta["radii"][0]
        if radii.dim() == 2:  # gsplat >= 1.5 reports per-axis radii
            radii = radii.max(dim=-1).values
        radii = radii.to(torch.int32)
        return {
            "rgb": render_colors[0, ..., :channels],
            "depth": render_colors[0, ..., channels],
            "alpha": render_alphas[0, ..., 0],
            "means2d": mirror_grad(meta["means2d"]),
            "radii": radii,
            "visible": radii > 0,
        }
