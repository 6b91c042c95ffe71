"""§3.3: the targets of refinement: an edited view kept only where the edit is."""
from __future__ import annotations

from typing import Optional

import torch

from gs_regional.utils.image import dilate


def composite_target(
    edited: torch.Tensor,  # (H, W, 3) the 2D editor's output
    source: torch.Tensor,  # (H, W, 3) render of the unedited scene
    region: torch.Tensor,  # (H, W) in [0, 1]: how much of each pixel the localized Gaussians cover
    added: Optional[torch.Tensor] = None,  # (H, W) in [0, 1]: the same for Gaussians the edit added; None: a recolour
    margin_px: int = 6,
    noise_sigmas: float = 4.0,
) -> torch.Tensor:
    """The edited view where the region renders (its coverage as the weight), the source render
    elsewhere: the editor's bleed and the blur and tone drift of regenerating the whole image
    never become targets outside the region.

    An edit that may add geometry (`added` given, possibly all zero) also keeps the pixels within
    `margin_px` of the region and the added Gaussians that the editor changed by more than
    `noise_sigmas` x its noise, measured beyond that margin, where it only regenerates the image
    (1.4826 x the median change: a Gaussian's std)."""
    weight = region.clamp(0, 1)
    if added is not None and margin_px > 0:
        near = dilate((region > 0.05) | (added > 0.05), margin_px)
        change = (edited - source).abs().amax(-1)
        noise = 1.4826 * float(change[~near].median()) if bool((~near).any()) else 0.0
        weight = torch.maximum(weight, (near & (change > noise_sigmas * noise)).to(weight.dtype))
    return weight[..., None] * edited + (1 - weight[..., None]) * source
