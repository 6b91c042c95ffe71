"""Small public API for users and tests."""
from __future__ import annotations

from typing import Dict, List, Sequence

import torch

from gs_regional.data.cameras import Camera
from gs_regional.registry import find

_renderers: Dict[str, object] = {}


def load_cameras(path: str) -> List[Camera]:
    """Cameras from a scene folder or a camera file (COLMAP sparse/0, transforms.json, cameras.json)."""
    from gs_regional.data.loaders import load_cameras as _load

    return _load(path)


def render(
    model,
    camera: Camera,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    renderer: str = "torch-rasterizer",
) -> Dict[str, torch.Tensor]:
    """Render `model` from `camera`; returns rgb (H,W,3), depth (H,W), alpha (H,W) and more."""
    if renderer not in _renderers:
        _renderers[renderer] = find(renderer, kind="renderers")()
    device = model.means.device
    bg = torch.as_tensor(background, dtype=torch.float32, device=device)
    return _renderers[renderer].render(model, camera.to(device), background=bg)
