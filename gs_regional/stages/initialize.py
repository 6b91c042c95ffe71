"""§3.2: new Gaussians for the region from calibrated monocular depth of the first edited view."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Callable, List, Optional

import torch
import torch.nn.functional as F

from gs_regional.config import need
from gs_regional.data.cameras import Camera
from gs_regional.depth.calibration import calibrated_depth, robust_affine, transfer_depth
from gs_regional.stages.change import match_colors, real_change
from gs_regional.geometry.neighbors import quantile_box, within_radius
from gs_regional.utils.image import components, dilate
from gs_regional.utils.rotations import covariance_to_scales_quats
from gs_regional.utils.sh import rgb_to_sh

log = logging.getLogger(__name__)


@dataclass
class InitConfig:
    alpha_min: float = 0.5  # rendered pixels below this opacity have no trustworthy 3DGS depth
    dilate_px: int = 3  # grow the 2D region: added geometry may stick out of the masked area
    # Gaussians are added only where the edit changes the shape: where the calibrated depth of the
    # edited view differs from the rendered depth by more than `noise_sigmas` x the depth noise
    # (measured outside the region, where nothing changes) and by at least `depth_change`
    # (relative). A colour change alone adds nothing: refinement recolours the existing Gaussians.
    depth_change: float = 0.03
    noise_sigmas: float = 4.0
    min_changed_fraction: float = 0.01
    # The full edits of this many views (largest regions first) are checked. A view whose depth
    # shows no change of shape may still be an addition the editor drew a few pixels off (its
    # position jitter: at 64² a 3 px shift moves the synthetic moustache, 1-5 px thick, off
    # itself), so the edit counts as a recolour only when none shows a change; and one may see the
    # new object edge-on (every view's mask on a round head is about as large), so an addition is
    # placed from the view whose depth shows the largest change. Each view costs one full edit; a
    # first view whose depth places PLACED_ENOUGH per changed pixel is not second-guessed.
    views: int = 2
    scale_evidence: float = 1.5  # see new_gaussians_from_depth: when the edited view's own depth scale is used
    # A calibration fitted on fewer pixels, or whose median relative residual exceeds
    # `max_calibration_residual`, is rejected: no Gaussians from depth, densification only.
    min_calibration_pixels: int = 256
    max_calibration_residual: float = 0.05
    # New Gaussians stand for at least `stride` x `stride` pixels each (`placement_cell`).
    stride: int = 1
    max_new: int = 20000  # cap on the pixels unprojected (evenly subsampled), so on the Gaussians added
    opacity: float = 0.3  # initial opacity of added Gaussians ("modest": they must not hide the surface behind)
    scale_factor: float = 0.5  # Gaussian standard deviation in pixel footprints
    # New points farther than this from every selected Gaussian (as a fraction of the selection's
    # robust bounding-box diagonal) are not part of the region: bleed over the background, depth
    # outliers. 0.5: an object standing on the region (the donut's cherry, as tall as the region
    # is wide) reaches past 0.25 of it (docs/method.md).
    max_distance: float = 0.5
    median: int = 3  # median filter of the monocular disparities: isolated wrong pixels make floaters

    def check(self, where: str = "system.init") -> None:
        need(0 <= self.alpha_min <= 1, f"{where}.alpha_min", "a number in [0, 1]", self.alpha_min)
        need(self.stride >= 1, f"{where}.stride", "an integer >= 1", self.stride)
        need(self.max_new >= 0, f"{where}.max_new", "an integer >= 0", self.max_new)
        need(0 < self.opacity < 1, f"{where}.opacity", "a number in (0, 1)", self.opacity)


def median_filter(x: torch.Tensor, k: int) -> torch.Tensor:
    """k x k median of an (H, W) map (edges replicated)."""
    if k <= 1:
        return x
    r = k // 2
    p = F.pad(x[None, None], (r, r, r, r), mode="replicate")
    return p.unfold(2, k, 1).unfold(3, k, 1).reshape(*x.shape, k * k).median(-1).values


def unproject(camera: Camera, depth: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    """World points of pixel indices `pixels` (K, 2) as (row, col) at camera-space depth `depth` (K,)."""
    v = pixels[:, 0].float() + 0.5
    u = pixels[:, 1].float() + 0.5
    x = (u - camera.cx) / camera.fx * depth
    y = (v - camera.cy) / camera.fy * depth
    pts_cam = torch.stack([x, y, depth], dim=-1)
    c2w = camera.camera_to_world.to(depth.device)
    return pts_cam @ c2w[:3, :3].T + c2w[:3, 3]


def near_region(points: torch.Tensor, region_means: torch.Tensor, max_distance: float, size: float = 0.0) -> torch.Tensor:
    """(K,) bool: points within `max_distance` x (robust bounding-box diagonal of region_means, or
    `size` when larger) of a region Gaussian."""
    if region_means.shape[0] == 0 or max_distance <= 0:
        return torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
    # The box of the 2%-98% quantiles per axis: one stray selected Gaussian must not set the size
    # (the donut add's selection: a single outlier made the diagonal 0.156 instead of 0.096).
    lo, hi = quantile_box(region_means, 0.02)
    radius = max_distance * max(float((hi - lo).norm()), size)
    return within_radius(points, region_means, radius)


def pixels_extent(camera: Camera, pixels: torch.Tensor, depth: torch.Tensor) -> float:
    """The world size of what `pixels` (K, 2) at `depth` (K,) show: the diagonal of their box
    (2%-98% quantiles, in whole pixels) at their median depth."""
    if pixels.shape[0] == 0:
        return 0.0
    lo, hi = quantile_box(pixels.float(), 0.02)
    return float((hi - lo + 1).norm()) * float(depth.median()) / (0.5 * (camera.fx + camera.fy))


def carry_depth(depth: torch.Tensor, known: torch.Tensor, px: int) -> torch.Tensor:
    """(H, W): `depth` of the `known` pixels carried out ring by ring, up to `px` pixels: each
    pixel of the next ring takes the mean depth of its 3x3 neighbours already reached, so beside
    a silhouette it is the silhouette's own depth; +inf beyond `px`."""
    reached = known.to(depth.dtype)[None, None]
    total = torch.where(known, depth, torch.zeros_like(depth))[None, None]
    ones = torch.ones(1, 1, 3, 3, dtype=depth.dtype, device=depth.device)
    for _ in range(px):
        n = F.conv2d(reached, ones, padding=1)
        ring = (reached == 0) & (n > 0)
        total = torch.where(ring, F.conv2d(total, ones, padding=1) / n.clamp_min(1), total)
        reached = torch.where(ring, torch.ones_like(reached), reached)
    return torch.where(reached[0, 0] > 0, total[0, 0], torch.full_like(depth, math.inf))


def calibration_pixels(alpha_3dgs: torch.Tensor, region: torch.Tensor, cfg: InitConfig) -> torch.Tensor:
    """(H, W) bool: the pixels the monocular depth is calibrated on: rendered opaque enough to
    have a 3DGS depth and away from the (dilated) region, where the edit changes nothing."""
    return (alpha_3dgs > cfg.alpha_min) & ~dilate(region, cfg.dilate_px)


MIN_UNCALIBRATED_PIXELS = 64  # opaque pixels needed to compare two disparities without calibration


def changed_pixels(change: torch.Tensor, threshold: float) -> torch.Tensor:
    """(H, W) bool: `change` above `threshold` with another such pixel among its 8 neighbours (a
    change of shape covers more than one pixel; an isolated one is the depth's noise)."""
    above = change > threshold
    kernel = torch.ones(1, 1, 3, 3, device=change.device)
    neighbours = F.conv2d(above.float()[None, None], kernel, padding=1)[0, 0] - 1
    return above & (neighbours >= 0.5)


def blobs_reaching(mask: torch.Tensor, region: torch.Tensor) -> torch.Tensor:
    """(H, W) bool: the 8-connected blobs of `mask` that have a pixel in `region`, whole."""
    labels = components(mask).reshape(-1)
    reach = torch.zeros(labels.numel(), dtype=torch.bool, device=mask.device)
    reach[labels[(mask & region).reshape(-1)]] = True
    return (mask.reshape(-1) & reach[labels.clamp_min(0)]).reshape(mask.shape)


def blobs_less_blurred_rim(blobs: torch.Tensor, changed: torch.Tensor, region: torch.Tensor, depth: torch.Tensor,
                           tolerance: float) -> torch.Tensor:
    """(H, W) bool: `blobs` (of `changed` pixels, reaching into `region`) less the pixels of their
    rim beyond the region (a pixel with an unchanged one among its 8 neighbours) whose `depth` lies
    behind the blob's pixels next to it by more than `tolerance` (relative). There the monocular
    estimator's blur mixes the object's depth with the far background's: on 145951 c23 (a big ball
    on a head) 7 such pixels lay 2-5 radii behind the ball, and Gaussians placed on them floated
    round it in every other view, while the rim pixels at the ball's own depth are its silhouette.
    A rim pixel with no inner one beside it (a blob a pixel or two thin) is kept."""
    inner = blobs & (region | ~dilate(~changed, 1))
    beside = carry_depth(depth, inner, 1)
    return inner | (blobs & ~inner & (depth <= beside * (1 + tolerance)))


def behind_the_object(depth: torch.Tensor, pixels: torch.Tensor, changed: torch.Tensor, size: float) -> torch.Tensor:
    """(K,) bool: the new `pixels` (K, 2) of the object's rim (an unchanged pixel among their 8
    neighbours in `changed`) whose `depth` (H, W) lies behind the object's inner pixels beside them
    by more than `size` (relative: the object's extent over its depth). There the monocular
    estimator's blur mixes the object's depth with what lies behind it, and a round object's own
    rim lies behind its middle by less than its size: on 402113 c03 (a 4-px ball on a head) 3 of
    its 11 pixels lay 8 radii behind it, and where refinement ran twice as long the views' targets
    made one of them an opaque blob beside the ball in every other view. Placed at the inner
    pixels' depth instead, such pixels stand out of the object's silhouette in side views (the
    donut's add lost 3 dB outside the footprint). A rim pixel with no inner one beside it (an
    object a pixel or two thin) is kept."""
    interior = changed & ~dilate(~changed, 1)
    beside = carry_depth(depth, interior, 1)[pixels[:, 0], pixels[:, 1]]
    return depth[pixels[:, 0], pixels[:, 1]] > beside * (1 + size)


# A blob's nearest depth, for its far side: this quantile of its pixels' depths (the estimator's noise
# puts a pixel or two well in front of the object).
NEAR_QUANTILE = 0.1
# How deep an object placed from one view is taken to be, in its widths, halved: its far side is mirrored
# about a plane this many of its radii behind its near depth (1: a ball's own far side; docs/decisions.md).
DEPTH_TO_WIDTH = 0.5


def far_side_depth(pixels: torch.Tensor, depth: torch.Tensor, pixel_size: torch.Tensor) -> tuple:
    """The far side of an object placed from one view's depth, mirrored about its middle: ((K,)
    bool, the `pixels` (K, 2) whose far side lies more than their `pixel_size` (K,) (a pixel's
    width at their depth) behind them; (K,) its depth, 2 (d_near + r) - `depth`, d_near the
    nearest depth (NEAR_QUANTILE) of the pixel's 8-connected blob of placed pixels and r the blob's
    radius (that of a disc of its area, in pixel widths at that depth): a ball's middle lies a
    radius behind its nearest point.

    Why: a depth map places the side of the object the view sees, a shell. From the side that shell
    is seen edge-on, and a ball added on a head came out a crescent in the views that see it from
    the side (381946 c23, +7.25 dB); the cycles place only what their targets show and the scene
    lacks, and not enough to fill it. An object is taken to be about as deep as it is wide; where
    it is flatter (a moustache on a face) the mirrored side lies inside what it rests on, hidden.
    Not the silhouette's depth as the middle: there the estimator's blur mixes the object with
    what lies behind it, and the mirrored side went as far behind."""
    h = int(pixels[:, 0].max()) + 1
    w = int(pixels[:, 1].max()) + 1
    grid = torch.zeros(h, w, dtype=torch.bool, device=pixels.device)
    grid[pixels[:, 0], pixels[:, 1]] = True
    labels = components(grid)[pixels[:, 0], pixels[:, 1]]
    _, blob = torch.unique(labels, return_inverse=True)
    n = int(blob.max()) + 1
    # each blob's NEAR_QUANTILE of depth (its pixels by blob, then by depth)
    by_depth = torch.argsort(depth, stable=True)
    grouped = by_depth[torch.argsort(blob[by_depth], stable=True)]
    area = torch.bincount(blob, minlength=n)
    start = torch.cumsum(area, 0) - area
    near = depth[grouped[start + (NEAR_QUANTILE * (area - 1).to(depth.dtype)).long()]]
    middle = near[blob] + DEPTH_TO_WIDTH * (area[blob].to(depth.dtype) / math.pi).sqrt() * pixel_size
    far = 2 * middle - depth
    return far - depth > pixel_size, far


def rate_on(mask: torch.Tensor, where: torch.Tensor) -> float:
    """The fraction of the `where` pixels that `mask` marks (0 when `where` has none)."""
    return float(mask[where].float().mean()) if bool(where.any()) else 0.0


def clearly_changed(changed: int, expected_by_noise: float, region_pixels: int, cfg: InitConfig) -> bool:
    """Whether `changed` pixels of a region are a change of shape: clearly more than the noise's
    `expected_by_noise` (Poisson: mean + 3 std + 1) and at least `min_changed_fraction` of the
    region (a silhouette a pixel off is no new object)."""
    return changed > max(expected_by_noise + 3 * expected_by_noise ** 0.5 + 1, cfg.min_changed_fraction * region_pixels)


def disparity_change(du: torch.Tensor, de: torch.Tensor, valid: torch.Tensor, cfg: InitConfig) -> Optional[tuple]:
    """The change of shape told from two monocular disparities alone (no rendered depth to
    calibrate on): the estimator sees the edited and the unedited image alike, so the edited
    disparity `de` is mapped onto the unedited one `du` by a robust affine fit over every opaque
    (`valid`) pixel, which a change of shape covering a minority of them does not move. Returns
    ((H, W) what is left, in units of the disparity's spread, > 0 where the edited view is nearer;
    its noise (a Gaussian's std); the threshold `noise_sigmas` x that), or None when there are too
    few opaque pixels to tell."""
    if int(valid.sum()) < MIN_UNCALIBRATED_PIXELS:
        return None
    a, b = robust_affine(de, du, valid)
    spread = float((du[valid] - du[valid].median()).abs().mean())
    if not spread > 0:
        return None
    change = torch.where(valid, (a * de + b - du) / spread, torch.zeros_like(du))
    noise = 1.4826 * float(change[valid].abs().median())
    return change, noise, cfg.noise_sigmas * max(noise, 1e-6)


def shape_change_verdict(found: Optional[tuple], region: torch.Tensor, cfg: InitConfig) -> Optional[dict]:
    """Whether the edited view's monocular depth shows a change of shape in `region`, from a
    `disparity_change` result (`found`; None: too few opaque pixels to tell, and None comes back),
    for a view with no pixels to calibrate on (the region fills it). Noise goes both ways, so the
    pixels that moved *back* by as much as the threshold say how many nearer ones it explains. The
    shape changed when the nearer pixels in the region clearly exceed that count and
    `min_changed_fraction` of the region."""
    if found is None:
        return None
    change, noise, threshold = found
    nearer = int((changed_pixels(change, threshold) & region).sum())
    farther = int((changed_pixels(-change, threshold) & region).sum())
    return {"nearer_pixels": nearer, "farther_pixels": farther, "noise": round(noise, 5),
            "shape_changed": clearly_changed(nearer, farther, int(region.sum()), cfg)}


def unchanged_pixels(found: Optional[tuple], valid: torch.Tensor, cfg: InitConfig) -> torch.Tensor:
    """(H, W) bool: the opaque (`valid`) pixels whose two disparities show no change of shape
    either way (`found`: a `disparity_change` result), `dilate_px` away from any that do: where the
    edit left the depth as it was, so the monocular depth can be calibrated there when the region
    leaves no other pixels."""
    if found is None:
        return torch.zeros_like(valid)
    change, _, threshold = found
    moved = changed_pixels(change, threshold) | changed_pixels(-change, threshold)
    return valid & ~dilate(moved, cfg.dilate_px)


def depth_calibration_pixels(alpha_3dgs: torch.Tensor, region: torch.Tensor, disp_unedited: torch.Tensor,
                             disp_edited: torch.Tensor, cfg: InitConfig) -> torch.Tensor:
    """(H, W) bool: the pixels `new_gaussians_from_depth` calibrated the monocular depth of a view
    on (and measured the editor's noise on): `calibration_pixels`, or, when the region leaves too
    few of them, the opaque pixels the edit leaves unchanged (`unchanged_pixels`). The
    disparities as the estimator gave them (median-filtered here, as there)."""
    calib_px = calibration_pixels(alpha_3dgs, region, cfg)
    if int(calib_px.sum()) >= max(cfg.min_calibration_pixels, 16):
        return calib_px
    valid = alpha_3dgs > cfg.alpha_min
    found = disparity_change(median_filter(disp_unedited, cfg.median), median_filter(disp_edited, cfg.median), valid, cfg)
    return unchanged_pixels(found, valid, cfg)


def _rejected(report: dict, reason: str) -> tuple:
    """The answer of `new_gaussians_from_depth` when the calibration is rejected: nothing added."""
    report.update(rejected=reason, added=0)
    return {}, report, None


def new_gaussians_from_depth(
    camera: Camera,
    unedited: torch.Tensor,  # (H, W, 3) render of the source scene
    edited: torch.Tensor,  # (H, W, 3) first edited view
    region: torch.Tensor,  # (H, W) bool 2D region of the edit
    depth_3dgs: torch.Tensor,  # (H, W) rendered expected depth
    alpha_3dgs: torch.Tensor,  # (H, W) rendered opacity
    disp_unedited: torch.Tensor,  # (H, W) monocular disparity of `unedited`
    disp_edited: torch.Tensor,  # (H, W) monocular disparity of `edited`
    cfg: InitConfig,
    sh_degree: int,
    region_means: Optional[torch.Tensor] = None,  # (M, 3) selected Gaussians, for `max_distance`
    back: bool = False,  # also place the object's far side (`far_side_depth`)
) -> tuple:
    """Returns (params dict for GaussianModel.append, report dict, d_new (H, W) for pictures).

    When the depth calibration cannot be trusted (too few calibration pixels, or a poor fit), no
    Gaussians are returned and `report["rejected"]` says why; `d_new` is then None."""
    device = edited.device
    valid = alpha_3dgs > cfg.alpha_min
    calib_px = calibration_pixels(alpha_3dgs, region, cfg)
    part = region.bool()
    region = dilate(region, cfg.dilate_px)
    report = {"calibration_pixels": int(calib_px.sum())}
    disp_unedited = median_filter(disp_unedited, cfg.median)
    disp_edited = median_filter(disp_edited, cfg.median)
    if report["calibration_pixels"] < max(cfg.min_calibration_pixels, 16):
        # No depth to place new geometry at; whether the shape changes at all can still be told.
        found = disparity_change(disp_unedited, disp_edited, valid, cfg)
        change = shape_change_verdict(found, region, cfg)
        report["uncalibrated"] = change
        if change is not None and not change["shape_changed"]:
            report["added"] = 0  # a recolour: trusted, nothing to add (refinement recolours)
            return {}, report, None
        # A change of shape: the depth is calibrated on the opaque pixels, inside the region too,
        # that the edit leaves as they were (an object added on a part that fills the view, the
        # donut's icing seen from above, covers a minority of it); without them nothing could
        # place the object, and densification alone barely drew it.
        calib_px = unchanged_pixels(found, valid, cfg)
        report["calibration_pixels_unchanged"] = int(calib_px.sum())
        if report["calibration_pixels_unchanged"] < max(cfg.min_calibration_pixels, 16):
            return _rejected(report, f"only {report['calibration_pixels']} pixels outside the region, and "
                             f"{report['calibration_pixels_unchanged']} that the edit leaves unchanged, have a rendered "
                             f"depth to calibrate on (system.init.min_calibration_pixels={cfg.min_calibration_pixels})")
    # The 3DGS depth behind the region, extended to empty pixels by the farthest rendered depth,
    # so geometry sticking out over the background still gets a reference depth.
    far = float(depth_3dgs.detach()[valid].max())
    d3 = torch.where(valid, depth_3dgs, torch.full_like(depth_3dgs, far))
    disp_3dgs = 1.0 / d3
    a_u, b_u = robust_affine(disp_unedited, disp_3dgs, calib_px)
    a_e, b_e = robust_affine(disp_edited, disp_3dgs, calib_px)
    # The edited view is put on the unedited view's calibration (`a_u`, `b_u`) through a map of its
    # own disparity onto the unedited one, fitted outside the region. The estimator sees two
    # near-identical images alike, so an offset is preferred: a second scale fitted on the few
    # pixels outside the region is extrapolated over the region and the background (the donut's
    # recolour showed hundreds of pixels "nearer" that way). Only a map that explains those pixels
    # clearly better (median residual `scale_evidence` x smaller) brings its scale.
    offset = float((disp_unedited - disp_edited)[calib_px].median())
    a_eu, b_eu = robust_affine(disp_edited, disp_unedited, calib_px)
    res_offset = float((disp_edited + offset - disp_unedited)[calib_px].abs().median())
    res_affine = float((a_eu * disp_edited + b_eu - disp_unedited)[calib_px].abs().median())
    if res_offset <= cfg.scale_evidence * res_affine:
        disp_edited_u, report["edited_depth_map"] = disp_edited + offset, "offset"
    else:
        disp_edited_u, report["edited_depth_map"] = a_eu * disp_edited + b_eu, "affine"
    d_mono_u = calibrated_depth(disp_unedited, a_u, b_u)
    d_mono_e = calibrated_depth(disp_edited_u, a_u, b_u)
    # Where the source renders background there is no scene depth to transfer the change onto:
    # the edited view's calibrated depth itself places what the edit puts there.
    d_new = torch.where(valid, transfer_depth(d_mono_e, d_mono_u, d3), d_mono_e)
    # How well each fit explains the rendered depth: the median relative disparity residual on the
    # calibration pixels (≈ the relative depth error of a typical pixel).
    residual = max(
        float(((a * disp + b - disp_3dgs).abs() / disp_3dgs)[calib_px].median())
        for a, b, disp in ((a_u, b_u, disp_unedited), (a_e, b_e, disp_edited))
    )
    # The change of shape, measured in disparity (where the estimator's noise is even; in depth it
    # explodes where the disparity nears zero, over the background) relative to the scene's
    # disparity, positive where the edited view is nearer. Only nearer pixels can need new
    # Gaussians: what moves back is uncovered, not added, and a silhouette blurred or shifted by
    # noise moves both ways.
    relative_change = a_u * (disp_edited_u - disp_unedited) / disp_3dgs
    # Outside the region nothing changes, so the change measured there is the noise of the
    # quantity thresholded below (1.4826 x median absolute value: a Gaussian's std).
    noise = 1.4826 * float(relative_change[calib_px & torch.isfinite(relative_change)].abs().median())
    threshold = max(cfg.depth_change, cfg.noise_sigmas * noise)
    report.update(
        scale_unedited=float(a_u), shift_unedited=float(b_u), scale_edited=float(a_e), shift_edited=float(b_e),
        calibration_residual=residual, depth_noise=noise, depth_threshold=threshold,
    )
    if not residual <= cfg.max_calibration_residual:  # NaN rejects too
        return _rejected(report, f"the monocular depth fits the rendered depth poorly (median relative "
                         f"residual {residual:.3f} > system.init.max_calibration_residual={cfg.max_calibration_residual})")

    edited = match_colors(edited, unedited, calib_px)  # colours of the new Gaussians, in the scene's tone
    depth_changed = changed_pixels(relative_change, threshold)  # nearer by more than the noise
    # An object added on a part grows out of the part's silhouette over what lies behind it (a big
    # ball on a head stands a dozen pixels clear of it, beyond the `dilate_px` the region is grown
    # by): a blob of change of shape that reaches into the region is taken, less the blur on its rim.
    blobs = blobs_reaching(depth_changed, region)
    grown = blobs_less_blurred_rim(blobs, depth_changed, region, d_new, threshold)
    reach = region | grown
    candidates = reach & depth_changed & torch.isfinite(d_new) & (d_new > 0)
    # Outside the region, and away from what grows out of it, nothing changes: what passes the
    # test there is the noise's rate. A region whose changed pixels are not clearly more than that
    # rate predicts has no change of shape (a recolour), and gets no Gaussians.
    quiet = calib_px & ~blobs  # empty: every calibration pixel lies in such a change, none shows noise
    expected = rate_on(depth_changed, quiet) * int(reach.sum())
    report.update(noise_changed_pixels=round(expected, 2))
    if not clearly_changed(int(candidates.sum()), expected, int(reach.sum()), cfg):
        candidates = torch.zeros_like(candidates)
    pixels = candidates.nonzero()
    report.update(
        region_pixels=int(region.sum()),
        skipped_unchanged=int((region & ~depth_changed).sum()),
        grown_out_of_region=int((reach & ~region).sum()),
    )
    if pixels.shape[0] > cfg.max_new:
        # Deterministic even subsample down to the cap.
        keep = torch.linspace(0, pixels.shape[0] - 1, cfg.max_new, device=device).round().long()
        report["skipped_by_cap"] = int(pixels.shape[0] - cfg.max_new)
        pixels = pixels[keep]
    else:
        report["skipped_by_cap"] = 0
    depth = d_new[pixels[:, 0], pixels[:, 1]]
    means = unproject(camera, depth, pixels)
    if region_means is not None:
        # A part smaller than the object put on it (a ball on a nose) would drop the whole object:
        # the distance scales with the larger of the two, the object measured by its pixels.
        size = pixels_extent(camera, pixels, depth)
        near = near_region(means, region_means, cfg.max_distance, size)
        # What is added goes on the localized part. Beside the part's silhouette the scene's depth
        # is whatever lies behind it (the backdrop), and there a small object's disparity, or a
        # large one's edge, is mostly lost to the estimator's blur and the median filter: the
        # transferred depth puts the pixel far behind the part (a 3-px ball on a head at depth 2.2
        # landed at 2.9-4.1). When such pixels show the edit (their colour changed beyond the
        # editor's noise; a silhouette's depth noise does not), are a change on their own (as
        # `clearly_changed` asks of all candidates) and are most of what changed (dropping them
        # would drop the object), they take the depth of the geometry beside them: the part's and
        # the accepted new pixels' depth, carried out from them. A few far pixels at a larger
        # object's edge are still dropped: the object's own pixels cover it better.
        shows_edit = real_change(edited, unedited, calib_px, cfg.noise_sigmas, explain_blur=False)[0] > 0
        moved = ~near & shows_edit[pixels[:, 0], pixels[:, 1]]
        expected_shown = rate_on(depth_changed & shows_edit, quiet) * int(region.sum())
        if int(moved.sum()) < int(near.sum()) or not clearly_changed(int(moved.sum()), expected_shown, int(region.sum()), cfg):
            moved = torch.zeros_like(moved)
        if bool(moved.any()):
            known = part & torch.isfinite(d_new)
            known[pixels[near, 0], pixels[near, 1]] = True
            onto = carry_depth(d_new, known, cfg.dilate_px)[pixels[:, 0], pixels[:, 1]]
            moved = moved & (onto < depth)
            depth = torch.where(moved, onto, depth)
            means = torch.where(moved[:, None], unproject(camera, depth, pixels), means)
            near = near | (moved & near_region(means, region_means, cfg.max_distance, size))
            d_new = d_new.clone()
            d_new[pixels[:, 0], pixels[:, 1]] = depth
        report["moved_onto_part"] = int((moved & near).sum())
        report["skipped_far_from_region"] = int((~near).sum())
        pixels, depth, means = pixels[near], depth[near], means[near]
    report["skipped_blurred_rim"] = 0
    if pixels.shape[0]:  # the object's rim blurred with what lies behind it (inside the region too)
        placed = torch.full_like(d_new, math.inf)
        placed[pixels[:, 0], pixels[:, 1]] = depth
        blurred = behind_the_object(placed, pixels, depth_changed, pixels_extent(camera, pixels, torch.ones_like(depth)))
        report["skipped_blurred_rim"] = int(blurred.sum())
        pixels, depth, means = pixels[~blurred], depth[~blurred], means[~blurred]
    # The decisions on these pixels (a change of shape or a recolour's edge, enough placed) count pixels.
    report["placed_pixels"] = int(pixels.shape[0])
    pixel_colors = edited[pixels[:, 0], pixels[:, 1]]
    cell = placement_cell(camera, cfg.stride)
    focal = 0.5 * (camera.fx + camera.fy)  # a pixel's width at depth d: d / focal
    far_mask, far = (far_side_depth(pixels, depth, depth / focal) if back and pixels.shape[0]
                     else (torch.zeros_like(depth, dtype=torch.bool), depth))

    near_side = merge_cells(pixels, means, pixel_colors, depth, cell)
    report["merged_pixels"] = report["placed_pixels"] - near_side[0].shape[0]
    report["placed_far_side"] = int(far_mask.sum())
    sides = [cell_gaussians(near_side, camera, cfg.scale_factor)]
    if report["placed_far_side"]:  # merged apart from the near side: a cell holds one depth
        behind, far = pixels[far_mask], far[far_mask]
        sides.append(cell_gaussians(merge_cells(behind, unproject(camera, far, behind), pixel_colors[far_mask], far, cell),
                                    camera, cfg.scale_factor))
    params = gaussian_params(*(torch.cat(x) for x in zip(*sides)), cfg.opacity, sh_degree)
    report["added"] = params["means"].shape[0]
    return params, report, d_new


def cell_gaussians(cells: tuple, camera: Camera, scale_factor: float) -> tuple:
    """(means, colours, log-scales, quats) of Gaussians for `merge_cells`' cells, each as wide as
    the pixels it stands for at its depth and spread along the surface (`surface_covariances`)."""
    points, rgb, cell_depth, covered, blocks = cells
    focal = 0.5 * (camera.fx + camera.fy)  # a pixel's width at depth d: d / focal
    width = (cell_depth / focal * covered.sqrt()).clamp_min(1e-6)
    log_scales, quats = covariance_to_scales_quats(surface_covariances(blocks, points, width, camera, scale_factor))
    return points, rgb, log_scales, quats


def gaussian_params(means: torch.Tensor, colors: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                    opacity: float, sh_degree: int) -> dict:
    """The parameters of new Gaussians for GaussianModel.append: view-independent `colors` at
    `opacity`."""
    k = means.shape[0]
    return {
        "means": means,
        "quats": quats,
        "log_scales": log_scales,
        "opacity_logits": torch.logit(torch.full((k,), opacity, device=means.device)),
        "sh_dc": rgb_to_sh(colors),
        "sh_rest": torch.zeros(k, (sh_degree + 1) ** 2 - 1, 3, device=means.device),
    }


# New Gaussians from a view's depth: at most one per cell of a grid this many cells across the view's
# shorter side (`placement_cell`): one per pixel up to 255² (the truth suite at 64² and 128², the demo
# at 96²), per 4 x 4 pixels at 512², so that above that an edit adds about as many Gaussians as at 128²
# and leaves the detail to densification. One per pixel added 2-4x at 128² what it adds at 64²; a grid
# of 64 (one per 2 x 2 at 128²) added 2.7x fewer there but lost 0.46 dB in the footprint and 2.2 dB
# outside it (docs/decisions.md).
PLACEMENT_GRID_CELLS = 128


def placement_cell(camera: Camera, stride: int = 1) -> int:
    """The side, in pixels, of the cells new Gaussians stand for in `camera`'s view: `stride`, or
    more in a view over PLACEMENT_GRID_CELLS pixels across its shorter side."""
    return max(stride, min(camera.width, camera.height) // PLACEMENT_GRID_CELLS)


def merge_cells(pixels: torch.Tensor, means: torch.Tensor, colors: torch.Tensor, depth: torch.Tensor,
                cell: int) -> tuple:
    """One point per `cell` x `cell` block of image `pixels` (K, 2) (row, col) that holds any: the
    mean of their world `means` (K, 3), `colors` (K, 3) and `depth` (K,). Returns (means, colors,
    depth, covered, blocks), `covered` (M,) the pixels each stands for and `blocks` (M, 2) its
    block's (row, col); at `cell` 1 the inputs as they are."""
    if cell <= 1 or not pixels.shape[0]:
        return means, colors, depth, torch.ones_like(depth), pixels
    block = pixels // cell
    _, inverse = torch.unique(block[:, 0] * (int(block[:, 1].max()) + 1) + block[:, 1], return_inverse=True)
    m = int(inverse.max()) + 1
    covered = torch.zeros(m, device=depth.device, dtype=depth.dtype).index_add_(0, inverse, torch.ones_like(depth))
    blocks = torch.zeros(m, 2, device=pixels.device, dtype=pixels.dtype).index_copy_(0, inverse, block)

    def mean(x: torch.Tensor) -> torch.Tensor:
        return torch.zeros(m, *x.shape[1:], device=x.device, dtype=x.dtype).index_add_(0, inverse, x) / \
            covered.view(-1, *[1] * (x.dim() - 1))

    return mean(means), mean(colors), mean(depth), covered, blocks


# A Gaussian placed from depth reaches along the surface to its grid neighbours: no further than this many
# of its cells' widths (beyond, the depth jumps: the object's edge over what lies behind, not its surface).
SURFACE_REACH = 4.0


def surface_covariances(blocks: torch.Tensor, means: torch.Tensor, width: torch.Tensor, camera: Camera,
                        scale_factor: float) -> torch.Tensor:
    """(M, 3, 3) covariances of Gaussians placed on a grid of cells (`blocks` (M, 2) their (row,
    col), `means` (M, 3) world points, `width` (M,) a cell's width at their depth): spread along
    the surface their grid neighbours span, `scale_factor` x the step to them (the mean of the steps
    either way, each at most SURFACE_REACH widths; the camera's own axis x `width` where neither
    neighbour is placed), and `scale_factor` x `width` across it. Facing the camera that is the
    isotropic Gaussian of `scale_factor` x `width`.

    Why: one Gaussian per pixel samples a surface the view sees obliquely (a ball's rim) sparsely:
    neighbouring pixels lie several pixel widths apart in depth there, and the views from the side
    saw through the gaps between isotropic Gaussians."""
    m = means.shape[0]
    if m == 0:
        return means.new_zeros(0, 3, 3)
    r, c = blocks[:, 0].long() + 1, blocks[:, 1].long() + 1  # one cell of margin all round
    grid = torch.full((int(r.max()) + 2, int(c.max()) + 2), -1, dtype=torch.long, device=means.device)
    grid[r, c] = torch.arange(m, device=means.device)
    rot = camera.camera_to_world[:3, :3].to(means)

    def tangent(dr: int, dc: int, axis: torch.Tensor) -> torch.Tensor:
        total, count = torch.zeros_like(means), torch.zeros(m, 1, dtype=means.dtype, device=means.device)
        for sign in (1, -1):
            other = grid[r + sign * dr, c + sign * dc]
            step = sign * (means[other.clamp_min(0)] - means)
            ok = ((other >= 0) & (step.norm(dim=-1) <= SURFACE_REACH * width))[:, None]
            total, count = total + step * ok, count + ok
        return torch.where(count > 0, total / count.clamp_min(1), axis * width[:, None])

    t_u, t_v = tangent(0, 1, rot[:, 0]), tangent(1, 0, rot[:, 1])
    normal = torch.linalg.cross(t_u, t_v)
    normal = torch.where(normal.norm(dim=-1, keepdim=True) > 1e-12 * width[:, None] ** 2, normal, rot[:, 2].expand_as(normal))
    normal = normal / normal.norm(dim=-1, keepdim=True)

    def outer(a: torch.Tensor) -> torch.Tensor:
        return a[:, :, None] * a[:, None, :]

    return scale_factor ** 2 * (outer(t_u) + outer(t_v) + width[:, None, None] ** 2 * outer(normal))


# A first view whose depth places new Gaussians on at least this fraction of the pixels its edit changes (beyond
# the editor's noise) shows the object well, and no other view's full edit is spent on it: on the
# truth suite's additions (26164, 136818) a second view helped only where the first placed under
# 0.37 per changed pixel (and 0.49 once, +0.5 dB), and took from where it placed more than one.
PLACED_ENOUGH = 0.5


@dataclass
class DepthInit:
    """The view depth initialization uses, and what `new_gaussians_from_depth` made of it."""

    view: int
    edited: torch.Tensor  # its full edit
    params: dict  # the new Gaussians ({} when none)
    report: dict  # metrics.json `init`
    d_new: Optional[torch.Tensor]  # (H, W) the new depth, None when nothing was placed
    disparities: torch.Tensor  # (2, H, W) the monocular disparities of the unedited and the edited view


def initialize_from_views(
    order: List[int],  # the first view, then the others by region size
    edit: Callable[[int], torch.Tensor],  # view -> its full edit
    source: Callable[[int], torch.Tensor],  # view -> (H, W, 3) the source render
    camera: Callable[[int], Camera],
    render: Callable[[int], dict],  # view -> the current scene's render ("depth", "alpha")
    disparity: Callable[[torch.Tensor, List[Camera]], torch.Tensor],  # the depth estimator
    region: Callable[[int], torch.Tensor],  # view -> (H, W) bool, the 2D region
    cfg: InitConfig,
    sh_degree: int,
    region_means: Optional[torch.Tensor] = None,
    changed_px: Optional[float] = None,  # the pixels the first view's edit changes (EditCheck.changed_px)
) -> DepthInit:
    """§3.2 steps 2-5 from each view of `order` (the first `cfg.views` of it): one edit can draw a
    thin new object a few pixels off, its depth then showing no change of shape, or see it
    edge-on, its depth then showing a sliver. The view whose depth shows a change and places the
    most Gaussians is used (else the first); a first view whose calibration is rejected, or whose
    depth places PLACED_ENOUGH per pixel of `changed_px`, ends the search."""
    found, best, placed = None, None, []
    for k, u in enumerate(order):
        if k:
            log.info("initialize: checking the edit of view %d too (view %d's depth %s)", u, found.view,
                     "shows a change of shape" if best[0] else "shows no change of shape")
        cam, unedited, edited = camera(u), source(u), edit(u)
        out = render(u)
        disp = disparity(torch.stack([unedited, edited]), [cam, cam])
        params, report, d_new = new_gaussians_from_depth(
            cam, unedited, edited, region(u), out["depth"], out["alpha"], disp[0], disp[1], cfg, sh_degree,
            region_means=region_means, back=True)
        # A later view's calibration rejected for a poor fit is no evidence either way; a change of
        # shape seen without calibration (the region fills the view) is.
        shows_change = ("rejected" not in report and report["added"] > 0) or \
            bool((report.get("uncalibrated") or {}).get("shape_changed"))
        placed.append(report["added"])
        px = report.get("placed_pixels", 0)
        if found is None or (shows_change, px) > best:  # a change first, then the most placed
            found, best = DepthInit(u, edited, params, report, d_new, disp), (shows_change, px)
        if k == 0 and ("rejected" in report or (changed_px and px >= PLACED_ENOUGH * changed_px)):
            break
    found.report["views_checked"] = order[: k + 1]
    found.report["views_placed"] = placed  # the Gaussians each checked view's depth placed
    return found


def seen_as_edit(points: torch.Tensor, cameras: List[Camera], shows: List[torch.Tensor], surface: List[torch.Tensor],
                 tolerance: float = 0.02) -> torch.Tensor:
    """(K,) bool: the world `points` that a view sees as part of the edit and none contradicts.
    A view sees a point when it projects into its image in front of what the view
    renders there (`surface` (H, W): the current scene's depth, +inf where it renders nothing;
    `tolerance` relative); it supports the point when its edit shows a change on that pixel
    (`shows` (H, W) bool) and contradicts it otherwise: the view sees that place, and the edit put
    nothing there. Behind the surface a view has no say."""
    supported = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    contradicted = torch.zeros_like(supported)
    for cam, show, depth in zip(cameras, shows, surface):
        row, col, z, inside = cam.pixels(points)
        seen = inside & (z < depth[row, col] * (1 - tolerance))
        supported |= seen & show[row, col]
        contradicted |= seen & ~show[row, col]
    return supported & ~contradicted


# What a refinement cycle places of an added object lies within this many times the size of what is
# already added (as `InitConfig.max_distance` measures it): the side of an object that the first
# view's depth did not see lies up to the object's own size from the side it saw.
HOLE_MAX_DISTANCE = 1.0


def new_gaussians_in_holes(
    camera: Camera,
    current: dict,  # the current scene's render of the view: "rgb" (H, W, 3) in [0, 1], "depth", "alpha"
    target: torch.Tensor,  # (H, W, 3) the view's refinement target (an edited view, composited)
    shows: torch.Tensor,  # (H, W) bool: where the target differs from the source render
    added: torch.Tensor,  # (H, W) how much of each pixel the Gaussians the edit added cover
    region: torch.Tensor,  # (H, W) bool: the 2D region (the selection's render and the added Gaussians')
    disparities: torch.Tensor,  # (2, H, W) monocular disparities of `current["rgb"]` and `target`
    others: tuple,  # (cameras, shows, surfaces) of the cycle's other edited views, for `seen_as_edit`
    cfg: InitConfig,
    sh_degree: int,
    region_means: torch.Tensor,  # (M, 3) what is placed stays within `max_distance` (as InitConfig's) of these
    max_distance: float = 0.5,
) -> dict:
    """New Gaussians for the part of an added object that a refinement target shows and the
    current scene lacks: `new_gaussians_from_depth` with the current render as the unedited view
    (its depth changes only where the target draws something nearer), kept where the target's
    change lies a pixel inside the object's missing part (`shows` where `added` < 0.5, eroded: a
    view's target draws the object a pixel or two off, and that offset is its rim) and the other
    edited views see it as part of the edit (`seen_as_edit`); and, where the target changes the
    colour beyond the editor's noise but its depth shows the surface staying where it is, Gaussians
    on that surface (`painted_in_holes`). {} when none."""
    params, report, d_new = new_gaussians_from_depth(
        camera, current["rgb"], target, region, current["depth"], current["alpha"], disparities[0], disparities[1],
        replace(cfg, max_distance=max_distance), sh_degree, region_means=region_means)
    if d_new is None:  # the calibration rejected (or no change of shape): nothing to place or paint on
        return {}
    missing = shows & (added < 0.5)
    row, col, _, _ = camera.pixels(params["means"])
    keep = ~dilate(~missing, 1)[row, col] & seen_as_edit(params["means"], *others)
    params = {name: value[keep] for name, value in params.items()}
    # The surface stays (the depth is not nearer by the threshold the depth path places from), as it
    # does 2 px round: a raised object's rim, drawn a pixel or two off, is not painted round it.
    flat = current["depth"] / d_new.clamp_min(1e-6) - 1 < report["depth_threshold"]
    painted = painted_in_holes(camera, current, target, missing & ~dilate(~flat, 2) & region, region, others, cfg,
                               sh_degree, region_means, max_distance)
    if painted:
        params = {name: torch.cat([value, painted[name]]) for name, value in params.items()}
    return params if params["means"].shape[0] else {}


# A point painted onto a surface counts as seen by another view whose rendered depth there lies within
# this fraction of the point's (seen_as_edit's `tolerance` the other way: in front of the surface by it).
SURFACE_TOLERANCE = 0.02
# Points are painted only where the rendered depth of the pixel's 3 x 3 neighbourhood spans less than this
# many pixel widths (a surface at up to about 75 degrees to the view); a silhouette spans far more.
SMOOTH_PIXEL_WIDTHS = 8.0


def painted_in_holes(
    camera: Camera,
    current: dict,  # the current scene's render of the view: "rgb", "depth", "alpha"
    target: torch.Tensor,  # (H, W, 3) the view's refinement target
    where: torch.Tensor,  # (H, W) bool: the pixels that may take them (the object's missing part, in the region)
    region: torch.Tensor,  # (H, W) bool: the 2D region (the editor's noise is measured outside it)
    others: tuple,  # (cameras, shows, surfaces) of the cycle's other edited views, for `seen_as_edit`
    cfg: InitConfig,
    sh_degree: int,
    region_means: torch.Tensor,
    max_distance: float,
) -> dict:
    """New Gaussians, half a pixel in front of the current surface, for the pixels of `where` that
    the target changes beyond the editor's noise (`real_change`, its noise measured on the opaque
    pixels outside the region) and that the other edited views see as part of the edit, within
    `max_distance` of `region_means`; the target's colours, one per `placement_cell`.

    Why: an object that lies on the part (a moustache on a face) changes the colour but hardly the
    depth. The first view's depth places only the few pixels it sees raised, on the side it sees,
    and densification grows from those: the rest, drawn by later cycles' views, had no Gaussian to
    take it, and a side view's placement left the other half of a moustache out of every view.
    {} when none."""
    opaque = current["alpha"] > cfg.alpha_min
    # Only on a smooth surface: at a silhouette the rendered depth blends the part with what lies
    # behind it, and a point placed there floats beside the part, seen from other views past its edge.
    d = current["depth"][None, None]
    focal = 0.5 * (camera.fx + camera.fy)  # a pixel's width at depth d: d / focal
    step = (F.max_pool2d(d, 3, 1, 1) + F.max_pool2d(-d, 3, 1, 1))[0, 0]  # the depth range of the 3 x 3 pixels
    candidates = where & opaque & (step < SMOOTH_PIXEL_WIDTHS * current["depth"] / focal)
    if not bool(candidates.any()):  # (most views of most cycles: no noise to measure)
        return {}
    changed = real_change(target, current["rgb"], opaque & ~dilate(region, cfg.dilate_px), cfg.noise_sigmas)[0] >= 1
    pixels = (candidates & changed).nonzero()
    if not pixels.shape[0]:
        return {}
    depth = current["depth"][pixels[:, 0], pixels[:, 1]] * (1 - 0.5 / focal)
    means = unproject(camera, depth, pixels)
    # On the surface: the other views see it where their own surface lies within that tolerance
    keep = seen_as_edit(means, *others, tolerance=-SURFACE_TOLERANCE)
    if region_means is not None and region_means.shape[0]:
        keep &= near_region(means, region_means, max_distance, pixels_extent(camera, pixels, depth))
    pixels, depth, means = pixels[keep], depth[keep], means[keep]
    if not pixels.shape[0]:
        return {}
    cells = merge_cells(pixels, means, target[pixels[:, 0], pixels[:, 1]], depth, placement_cell(camera, cfg.stride))
    return gaussian_params(*cell_gaussians(cells, camera, cfg.scale_factor), cfg.opacity, sh_degree)
