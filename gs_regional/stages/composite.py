"""§3.3: the targets of refinement: an edited view kept only where the edit is."""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from gs_regional.stages.change import NOISE_SIGMAS, edit_blend, real_change
from gs_regional.geometry.neighbors import column_quantile
from gs_regional.utils.image import dilate


# The reference never falls below this: an edit whose best-recoloured Gaussians take less of its
# colour reaches none of them, and a reference of 0
# would let every selected Gaussian through when the views recolour nothing.
MIN_GATE_REFERENCE = 0.3


def gate_threshold(blend: torch.Tensor, seen: torch.Tensor, min_blend: float, reference_quantile: float) -> float:
    """The mean edit_blend a `seen` Gaussian must reach to take a recolour (`recoloured`):
    `min_blend` times the `blend` the `reference_quantile` of the seen ones reach, kept within
    [MIN_GATE_REFERENCE, 1] (`reference_quantile` 0: `min_blend` itself). In a part the edit
    covers whole that reference is 1; a part a few pixels across is all edge, and its own
    Gaussians then take as little of the edit's colour as a larger part's rim takes of its bleed."""
    if reference_quantile <= 0 or not bool(seen.any()):
        return min_blend
    best = float(column_quantile(blend[seen][:, None], reference_quantile)[0])
    return min_blend * min(max(best, MIN_GATE_REFERENCE), 1.0)


def recoloured(num: torch.Tensor, den: torch.Tensor, seen: torch.Tensor, min_blend: float,
               reference_quantile: float) -> torch.Tensor:
    """(N,) bool: the `seen` Gaussians whose mean edit_blend (`num` / `den`, rendering-weighted
    over their views) reaches the `gate_threshold`."""
    need = gate_threshold(num / den.clamp_min(1e-12), seen, min_blend, reference_quantile)
    return seen & (num >= need * den)


def part_colours(colours: torch.Tensor, blend: torch.Tensor, seen: torch.Tensor, full_blend: float,
                 quantile: float = 0.95, min_core_fraction: float = 0.2) -> Optional[Tuple[torch.Tensor, float]]:
    """(median colour (3,), reach) of the Gaussians a recolour recolours fully (seen, `blend` >=
    `full_blend`): the colours of the part being recoloured, `reach` the distance from the median
    that `quantile` of them stay within. None unless they are at least `min_core_fraction` of the
    seen ones: a small part, mostly edge, has too few of them to stand for its colours."""
    core = seen & (blend >= full_blend)
    if int(core.sum()) < max(2.0, min_core_fraction * int(seen.sum())):
        return None
    centre = column_quantile(colours[core], 0.5)
    reach = float(column_quantile((colours[core] - centre).norm(dim=-1)[:, None], quantile)[0])
    return centre, reach


def distinct_parts(colours: torch.Tensor, blend: torch.Tensor, seen: torch.Tensor, full_blend: float,
                   quantile: float = 0.95, margin: float = 1.5, min_distance: float = 0.25,
                   min_core_fraction: float = 0.2, part: Optional[Tuple[torch.Tensor, float]] = None) -> torch.Tensor:
    """(N,) bool: Gaussians of a recolour's selection that are a part of their own, not the part
    being recoloured: seen, recoloured by less than `full_blend` (`blend`: mean edit_blend over
    their views), and further in source colour (`colours`, (N, 3)) from the part's median colour
    than `margin` times its reach and at least `min_distance` (RGB in [0, 1]) from it. The part's
    colours are `part` ((median, reach), `part_colours`), or else those of the Gaussians these
    votes recolour fully (`part_colours` with `quantile`, `min_core_fraction`; none found: no
    Gaussian is distinct).

    The editor spills about half of its colour onto a small part enclosed by the edited one (eyes
    in a head), which is as much as the edited part's own edge takes; the edge shares the part's
    colours, the enclosed part does not."""
    if part is None:
        part = part_colours(colours, blend, seen, full_blend, quantile, min_core_fraction)
        if part is None:
            return torch.zeros_like(seen)
    centre, reach = part
    distance = (colours - centre).norm(dim=-1)
    return seen & (blend < full_blend) & (distance > max(margin * reach, min_distance))


def still_distinct(was: torch.Tensor, colours: torch.Tensor, blend: torch.Tensor, seen: torch.Tensor,
                   full_blend: float, part: Tuple[torch.Tensor, float], min_distance: float) -> torch.Tensor:
    """(N,) bool: the Gaussians found a part of their own in an earlier cycle (`was`) that still are:
    seen, recoloured by less than `full_blend`, and at least `min_distance` (RGB) from the part's
    median colour (`part`, `part_colours` of this cycle's votes). Later cycles edit renders that
    already carry the edit; the Gaussians they recolour fully take in the part's dark edge, and the
    colours that stand for the part widen until an enclosed part falls inside them."""
    return was & seen & (blend < full_blend) & ((colours - part[0]).norm(dim=-1) > min_distance)


def outlying_pieces(pieces: torch.Tensor, core: torch.Tensor, seen: torch.Tensor, share: float) -> torch.Tensor:
    """(N,) bool: the selected Gaussians whose connected piece of the selection (`pieces`: each
    selected row's piece, -1 for the others, `neighbors.components` over their nearest neighbours)
    has under `share` times the fraction of `core` Gaussians (ones the edit recolours fully) among
    its `seen` ones that the whole selection has.

    Why: a mask that reaches a pixel past the part selects the rim of what stands in front of it
    (the top of a head before a recoloured backdrop), a ring of its own in 3D, and the editor's
    bleed recolours that rim in every view by about as much as the part's own weakly edited edge;
    a few of the ring's Gaussians, their weight on pixels the bleed covers whole, even fully."""
    selected = pieces >= 0
    cores = torch.bincount(pieces[core & selected], minlength=pieces.shape[0]).float()
    views = torch.bincount(pieces[seen & selected], minlength=pieces.shape[0]).float()
    overall = float(cores.sum()) / max(float(views.sum()), 1.0)
    weak = cores < share * overall * views
    return selected & weak[pieces.clamp_min(0)]


# An addition's target takes the edit only where a pixel takes more than half of the new object's
# colour (`edit_blend`): the half-blend contour is where a symmetric blur (the editor's spill, the
# antialiasing) leaves the object's true edge; below it the faint added Gaussians that fit the spill
# grow a halo. Not exactly 0.5: a spill at full strength mixes exactly half, and float rounding
# would decide which side such a pixel falls.
MIN_OBJECT_BLEND = 0.52
# An addition also keeps the editor's clear changes within this many pixels of the region and of
# the added Gaussians: room for the geometry it adds (a recolour gets no margin).
ADDITION_MARGIN_PX = 6
# A pixel the region covers by at least this fraction keeps the edit fully, below it in proportion.
FULL_COVERAGE = 0.5


def composite_target(
    edited: torch.Tensor,  # (H, W, 3) the 2D editor's output
    source: torch.Tensor,  # (H, W, 3) render of the unedited scene
    region: torch.Tensor,  # (H, W) in [0, 1]: how much of each pixel the localized Gaussians cover
    added: Optional[torch.Tensor] = None,  # (H, W) in [0, 1]: the same for Gaussians the edit added; None: a recolour
    margin_px: int = ADDITION_MARGIN_PX,
    noise_sigmas: float = NOISE_SIGMAS,
    full_coverage: float = FULL_COVERAGE,
    opaque: Optional[torch.Tensor] = None,  # (H, W) bool: where the source renders opaque; None: everywhere
    min_blend: float = MIN_OBJECT_BLEND,
) -> torch.Tensor:
    """The edited view where the edit is, the source render elsewhere: the editor's bleed and the
    blur and tone drift of regenerating the whole image never become targets outside the region,
    nor on the parts of the region the edit leaves alone.

    The editor's noise is measured beyond `margin_px` of the region (and of the added Gaussians),
    where it only regenerates the image (`real_change`: its tone drift there fitted and taken out
    of the whole view, then the robust std of what still differs from the source). The target
    keeps the edited view where it differs from the source by more than `noise_sigmas` x that
    noise (fully from twice that), and
    only where the region renders: fully where it covers at least `full_coverage` of the pixel,
    in proportion below. An edit that may add geometry
    (`added` given, possibly all zero) keeps such changes also within `margin_px` of the region
    and the added Gaussians: room for geometry the edit adds. There, and over the region, a pixel
    takes the edit only where it takes at least `min_blend` of the edit's nearby colour
    (`edit_blend`): the editor spills the new object's colour a couple of pixels round it, a clear
    change too, and trained on it the added Gaussians grew a halo round the object (0 keeps it).

    The tone drift is fitted only where the source renders something (`opaque`): empty background
    holds no colour to fit a gain on, and a gain fitted to its clipped noise would crush the whole
    target to black in views that the region fills."""
    near = region > 0.05
    if added is not None:
        near = near | (added > 0.05)
    near = dilate(near, margin_px) if margin_px > 0 else near
    far = ~near
    # The edited pixel already mixes the region's new look with what the region covers only
    # partly, so weighting it by the coverage once more would under-edit the region's silhouette.
    # The weight still fades out where the region barely reaches, where the editor's bleed would pass.
    weight = (region / full_coverage).clamp(0, 1) if full_coverage > 0 else (region > 0).to(region.dtype)
    if bool(far.any()):
        raw_change = (edited - source).abs().amax(-1)
        raw_noise = 1.4826 * float(raw_change[far].median())
        # Inside the object, 2 px from its silhouette: there the regenerated view's blur mixes
        # the object with the background, which is no tone drift.
        inside = None if opaque is None else ~dilate(~opaque, 2)
        changed, edited, change = real_change(edited, source, far, noise_sigmas, tone=inside)
        weight = weight * changed
        if added is not None and margin_px > 0:
            # Beyond the region only clear changes count (the editor's bleed is a change too, but
            # weaker than what it paints): the margin's threshold leaves the tone drift in.
            # What a blurred source explains is no change here either (`change` is real_change's):
            # the seams between parts, which regenerating the view softens, are no room for new geometry.
            weight = torch.maximum(weight, (near & (change > noise_sigmas * raw_noise)).to(weight.dtype))
            if min_blend > 0:
                weight = weight * (edit_blend(edited, source) >= min_blend).to(weight.dtype)
    return weight[..., None] * edited + (1 - weight[..., None]) * source
