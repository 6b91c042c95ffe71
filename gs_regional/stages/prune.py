"""After refinement: the Gaussians an edit added that contribute nothing."""
from __future__ import annotations

import logging
from typing import Sequence

import torch

from gs_regional.data.cameras import Camera
from gs_regional.geometry import rows

log = logging.getLogger(__name__)


@torch.no_grad()
def rendered_weight(model, renderer, cameras: Sequence[Camera]) -> torch.Tensor:
    """(N,) each Gaussian's alpha-compositing weight summed over every pixel of `cameras` (in
    pixels: 1 = one pixel's full colour). One view at a time, so memory stays O(N)."""
    total = torch.zeros(model.num_gaussians, device=model.means.device)
    for cam in cameras:
        total += renderer.pixel_weights(model, cam).totals(cam.height, cam.width, total.device)
    return total


@torch.no_grad()
def useless_added(model, renderer, cameras: Sequence[Camera], min_weight: float, min_opacity: float) -> torch.Tensor:
    """(N,) bool: Gaussians added by an edit (generation > 0) whose rendered weight over `cameras`
    is below `min_weight` pixels (hidden inside the object, behind others, outside every view) or
    whose opacity is below `min_opacity`. Gaussians of the source scene are never flagged."""
    added = model.generation > 0
    if not bool(added.any()):
        return added
    weak = model.opacities < min_opacity
    return added & (weak | (rendered_weight(model, renderer, cameras) < min_weight))


@torch.no_grad()
def prune_useless_added(model, renderer, cameras: Sequence[Camera], min_weight: float, min_opacity: float, optimizer,
                        agree=lambda rows_: rows_) -> int:
    """Remove the Gaussians an edit added that contribute nothing to `cameras` (`useless_added`),
    sparing the last descendant of every source row; `agree`: the rows every process of a run on
    several devices prunes (rank 0's). Returns how many."""
    useless = agree(rows.spare_last_descendants(model, useless_added(model, renderer, cameras, min_weight, min_opacity)))
    n = int(useless.sum())
    if n:
        rows.keep(model, ~useless, optimizer)
    log.info("refine: pruned %d of the %d added Gaussians that contribute nothing", n, int((model.generation > 0).sum()) + n)
    return n
