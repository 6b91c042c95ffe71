"""§3.3: the targets of refinement: an edited view kept only where the edit is."""
from __future__ import annotations

from typing import Optional

import torch

from gs_regional.edit.initialize import match_colors
from gs_regional.utils.image import dilate


def composite_target(
    edited: torch.Tensor,  # (H, W, 3) the 2D editor's output
    source: torch.Tensor,  # (H, W, 3) render of the unedited scene
    region: torch.Tensor,  # (H, W) in [0, 1]: how much of each pixel the localized Gaussians cover
    added: Optional[torch.Tensor] = None,  # (H, W) in [0, 1]: the same for Gaussians the edit added; None: a recolour
    margin_px: int = 6,
    noise_sigmas: float = 4.0,
) -> torch.Tensor:
    """The edited view where the edit is, the source render elsewhere: the editor's bleed and the
    blur and tone drift of regenerating the whole image never become targets outside the region,
    nor on the parts of the region the edit leaves alone.

    The editor's noise is measured beyond `margin_px` of the region (and of the added Gaussians),
    where it only regenerates the image: first its tone drift there is fitted (a gain and an offset
    per channel) and taken out of the whole view; then 1.4826 x the median of what still differs
    from the source is the noise (a Gaussian's std). The target keeps the edited view where it
    differs from the source by more than `noise_sigmas` x that noise (fully from twice that), and
    only where the region renders (its coverage as the weight). An edit that may add geometry
    (`added` given, possibly all zero) keeps such changes also within `margin_px` of the region
    and the added Gaussians: room for geometry the edit adds."""
    near = region > 0.05
    if added is not None:
        near = near | (added > 0.05)
    near = dilate(near, margin_px) if margin_px > 0 else near
    far = ~near
    weight = region.clamp(0, 1)
    if bool(far.any()):
        raw_change = (edited - source).abs().amax(-1)
        raw_noise = 1.4826 * float(raw_change[far].median())
        if int(far.sum()) >= 16:  # enough pixels to see what regenerating the view did to its tone
            edited = match_colors(edited, source, far)
        change = (edited - source).abs().amax(-1)
        threshold = max(noise_sigmas * 1.4826 * float(change[far].median()), 1.0 / 255)
        weight = weight * ((change - threshold) / threshold).clamp(0, 1)
        if added is not None and margin_px > 0:
            # Beyond the region only clear changes count (the editor's bleed is a change too, but
            # weaker than what it paints): the margin's threshold leaves the tone drift in.
            weight = torch.maximum(weight, (near & (raw_change > noise_sigmas * raw_noise)).to(weight.dtype))
    return weight[..., None] * edited + (1 - weight[..., None]) * source
