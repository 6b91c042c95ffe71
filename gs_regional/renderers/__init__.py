from gs_regional.renderers import torch_rasterizer, gsplat_rasterizer  # noqa: F401
