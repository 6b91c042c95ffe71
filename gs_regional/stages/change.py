"""How far a 2D editor's output really changed a view: its tone drift fitted away
(`match_colors`), the blur of regenerating the view explained away (`regeneration_change`), the
rest measured against the editor's noise (`real_change`). Initialization, the first-view check,
the composite and the recolour's gate all read an edit through these."""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from gs_regional.utils.image import components, dilate, gaussian_blur

# An editor's change counts where it exceeds this many times its noise (a Gaussian's std measured
# where the edit leaves the view alone): the composite, the first-view check and initialization's
# recolour test read an edit with the same threshold.
NOISE_SIGMAS = 4.0


def match_colors(image: torch.Tensor, reference: torch.Tensor, pixels: torch.Tensor,
                 max_gain: Optional[float] = None) -> torch.Tensor:
    """Per-channel gain and offset fitted (least squares on `pixels`) to map `image` onto
    `reference`: a full 2D edit re-generates the whole view and shifts its tone, which is not a
    change of the region. `max_gain`: the gain is kept within [1 / max_gain, max_gain] (and the
    offset fitted for it), for pixels whose narrow range of colours could not tell a gain that
    holds for the whole view."""
    # Closed form in float64 (not a LAPACK solve, whose last bits can depend on memory alignment:
    # a view edited alone and in a batch must give the same target).
    x, y = image[pixels].double(), reference[pixels].double()  # (K, 3)
    out = torch.empty_like(image)
    for c in range(3):
        dx, dy = x[:, c] - x[:, c].mean(), y[:, c] - y[:, c].mean()
        if float(dx.std()) < 1e-3:  # no contrast to fit a gain on: shift only
            gain, offset = 1.0, float((y[:, c] - x[:, c]).mean())
        else:
            gain = float((dx * dy).sum() / (dx * dx).sum())
            if max_gain is not None:
                gain = min(max(gain, 1.0 / max_gain), max_gain)
            offset = float(y[:, c].mean() - gain * x[:, c].mean())
        out[..., c] = image[..., c] * gain + offset
    return out.clamp(0, 1)


# A regenerated view's tone drifts by a few percent; a larger gain fitted on the calm pixels comes
# from their narrow range of colours (a sliver of one material) and would not hold for the rest.
MAX_TONE_GAIN = 1.25
MIN_TONE_PIXELS = 64  # fewer calm pixels of the object than this: no tone fit
# A blob of change touching the region counts as an object grown out of it when at least this
# share of it lies over what is behind the region (or near it): an object added on a part grows
# over what lies behind it (all of it), an edit of a neighbouring part does not (about half).
BLOB_BEHIND = 0.75
# ... and when it rests on the region along a good part of its width: its pixels in the margin at
# least this share of margin x sqrt(its size) (a width-scale contact, the same at any resolution):
# an object resting on a part touches it along its width, one placed off the part at a corner.
BLOB_CONTACT = 0.5
# The contact is counted this many pixels beyond the margin: where an object meets the region's
# edge, regenerating softens both edges and a blurred source explains that pixel (`real_change`),
# so the object's change stops a pixel short of the edge (a big ball on a head's far slope, seen
# from the side: 1 px in the margin, 15 one pixel further).
BLOB_SOFT_EDGE_PX = 1


def real_change(edited: torch.Tensor, source: torch.Tensor, calm: torch.Tensor, noise_sigmas: float,
                tone: Optional[torch.Tensor] = None, explain_blur: bool = True, blur_in_noise: bool = True) -> tuple:
    """Where the 2D editor really changed the view, beyond what regenerating it does everywhere.

    `calm` (H, W) bool are pixels the edit should leave alone. On the calm pixels of `tone` (all of
    them when None) the editor's tone drift is fitted (a gain and an offset per channel, given at
    least MIN_TONE_PIXELS) and taken out of the whole view; then 1.4826 x the median of what still
    differs from the source on those pixels (on all calm ones when there was no fit) is its noise
    (a Gaussian's std): a tone map fitted on the object says nothing of the empty background.
    With `explain_blur`, what a blurred source explains is no change (`regeneration_change`);
    `blur_in_noise=False` measures the noise on the plain difference instead of on that one.
    Returns ((H, W) in [0, 1]: 0 up to `noise_sigmas` x that noise, 1 from twice that; the
    tone-matched `edited`; the (H, W) change it was measured on, before the noise threshold)."""
    fit = calm if tone is None else calm & tone
    if int(fit.sum()) >= MIN_TONE_PIXELS:  # enough pixels to see what regenerating the view did to its tone
        edited = match_colors(edited, source, fit, max_gain=MAX_TONE_GAIN)
        calm = fit
    plain = (edited - source).abs().amax(-1)
    change = regeneration_change(edited, source) if explain_blur else plain
    noise = change if blur_in_noise else plain
    threshold = max(noise_sigmas * 1.4826 * float(noise[calm].median()), 1.0 / 255)
    return ((change - threshold) / threshold).clamp(0, 1), edited, change


REGEN_BLURS = (0.5, 1.0, 1.5, 2.0)  # px: the detail a regenerated view may lose


def regeneration_change(edited: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
    """(H, W): how far each pixel of `edited` is from the source as the editor may regenerate it.
    A 2D editor redraws the whole view and loses fine detail everywhere (the VAE, the partial
    denoise): against the sharp source, every textured pixel of a region the edit leaves alone
    looks changed, its blurred copy became a target and the region's Gaussians drifted towards it
    (sprinkles smeared). A pixel counts as changed by what neither the source nor a blurred source
    (any of REGEN_BLURS) explains: a new colour or a new object differs from all of them. (The
    blur cannot be estimated on the calm pixels: they are often untextured.)"""
    change = (edited - source).abs().amax(-1)
    channels = source.permute(2, 0, 1)
    for sigma in REGEN_BLURS:
        blurred = gaussian_blur(channels, sigma).permute(1, 2, 0)
        change = torch.minimum(change, (edited - blurred).abs().amax(-1))
    return change


def recoloured_fraction(
    edited: torch.Tensor,  # (H, W, 3) the editor's full edit of a view
    source: torch.Tensor,  # (H, W, 3) render of the unedited scene
    region: torch.Tensor,  # (H, W) bool: where the localized Gaussians render
    added: torch.Tensor,  # (H, W) bool: where the Gaussians the edit added render
    calm: torch.Tensor,  # (H, W) bool: pixels the edit leaves alone (the editor's noise is measured there)
    noise_sigmas: float = NOISE_SIGMAS,
    margin_px: int = 2,
) -> Optional[float]:
    """The fraction of the region's pixels, beyond `margin_px` of the added geometry, whose colour
    the editor really changed (`real_change`): what the edit recolours besides what it adds. The
    added object's rim, shadow and bleed fall within the margin. None when no pixel of the
    region lies beyond it, or fewer than 16 are calm."""
    rest = region & ~dilate(added, margin_px)
    if not bool(rest.any()) or int(calm.sum()) < 16:
        return None
    changed, _, _ = real_change(edited, source, calm, noise_sigmas)
    return float((changed[rest] >= 0.5).float().mean())


def edit_change(
    edited: torch.Tensor,  # (H, W, 3) the 2D editor's output
    source: torch.Tensor,  # (H, W, 3) render of the unedited scene
    region: torch.Tensor,  # (H, W) bool: where the localized Gaussians render
    opaque: Optional[torch.Tensor] = None,  # (H, W) bool: where the source renders opaque; None: everywhere
    margin_px: int = 2,
    noise_sigmas: float = NOISE_SIGMAS,
    behind: Optional[torch.Tensor] = None,  # (H, W) bool: where the source shows something behind the region
) -> Optional[Tuple[float, float, float]]:
    """(pixels of the editor's change near `region`, pixels of it in all, the fraction of
    `region`'s pixels it changes): the change is `real_change`, beyond `noise_sigmas` x the
    editor's noise measured on the opaque pixels beyond `margin_px` of `region`. Near: within
    `margin_px` of `region`, or in a connected blob of change that rests on that margin
    (BLOB_CONTACT) and lies over `behind` or near the region for at least BLOB_BEHIND of its
    pixels: an object added on a part grows out of it over what lies behind (a big ball put on a
    head, seen from the side, covers none of the head), while an edit of another part changes that
    part, beside the region rather than behind it, and an object placed off the part touches it
    at a corner at most. Empty background (not `opaque`, not near the region) is left out: no
    Gaussian renders there, and its noise, clipped at black, would set the threshold below the
    blur of regenerating the object. None when fewer than 16 calm pixels are left."""
    near = dilate(region, margin_px) if margin_px > 0 else region
    seen = torch.ones_like(near) if opaque is None else near | opaque.to(near.device)
    calm = seen & ~near
    if int(calm.sum()) < 16:
        return None
    # A pixel a blurred source explains is no change: the sharp edges of every part, which
    # regenerating the view softens, would outweigh a small edit. The noise is measured on the
    # plain difference: blur-explained, it falls so low on small views (48²) that those edges
    # count as changes again.
    changed, _, _ = real_change(edited, source, calm, noise_sigmas, explain_blur=True, blur_in_noise=False)
    changed = changed * seen
    if behind is not None:
        # Per blob of change (labelled by one of its pixel indices): its size, how many of its
        # pixels lie in the region's margin, and how many near the region or behind it.
        moved = changed >= 0.5
        blob = components(moved)[moved]
        size = torch.bincount(blob, minlength=near.numel()).float()
        touching = dilate(region, margin_px + BLOB_SOFT_EDGE_PX)
        contact = torch.bincount(blob, touching[moved].float(), minlength=near.numel())
        over = torch.bincount(blob, (near | behind.to(near.device))[moved].float(), minlength=near.numel())
        rests = contact >= BLOB_CONTACT * max(margin_px, 1) * size.sqrt()  # > 0 for every blob
        grown = torch.zeros_like(near)
        grown[moved] = (rests & (over >= BLOB_BEHIND * size))[blob]
        near = near | grown
    filled = float((changed[region] >= 0.5).float().mean()) if bool(region.any()) else 0.0
    return float(changed[near].sum()), float(changed.sum()), filled


SPILL_SIGMA = 2.0  # px: the neighbourhood whose edited colour a pixel is compared with


def edit_blend(edited: torch.Tensor, source: torch.Tensor, sigma: float = SPILL_SIGMA) -> torch.Tensor:
    """(H, W): how much of the edit's nearby colour each pixel of `edited` (a target: the source
    wherever the edit is not) takes, 0 (its source colour) to about 1 (the edit itself).

    The edit's nearby colour is the local mean of `edited`, each pixel weighted by its squared
    change: inside an edited area that is the pixel's own edited colour, whatever the texture
    (blend 1), while a pixel beside the area onto which the editor's colour spilled (bleed) is a
    partial mix of its source colour with it: the projection of its change onto the way from its
    source colour to that colour is a fraction well under 1 (the simulator's bleed: at most 0.5)."""
    d = edited - source
    w = d.pow(2).sum(-1)
    den = gaussian_blur(w[None], sigma)[0]
    near = gaussian_blur((edited * w[..., None]).permute(2, 0, 1), sigma).permute(1, 2, 0) / den[..., None].clamp_min(1e-12)
    way = near - source
    blend = (d * way).sum(-1) / way.pow(2).sum(-1).clamp_min(1e-12)
    return torch.where(den > 1e-12, blend, torch.zeros_like(blend))
