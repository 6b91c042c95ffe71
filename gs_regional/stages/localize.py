"""§3.1: lift per-view 2D masks to a per-Gaussian mask and render it back."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, ClassVar, Dict, Optional, Sequence

import torch
import torch.nn.functional as F

from gs_regional.config import need
from gs_regional.data.cameras import Camera
from gs_regional.geometry import neighbors
from gs_regional.metrics.region import SEEN_MIN_WEIGHT, render_selection, splat_selection  # noqa: F401 (render_selection, splat_selection: part of this stage's API)
from gs_regional.renderers.base import PixelWeights
from gs_regional.utils.image import dilate, gaussian_blur
from gs_regional.utils.sh import sh_to_color

# The lift's robustness steps (localize_gaussians):
REWEIGHT_ITERS = 2  # re-lifts with each view weighted by its agreement with the 3D mask
AGREEMENT_POWER = 2.0  # a view's weight: IoU(2D mask, rendered 3D mask) ** this
# A Gaussian's votes from a mask's one-pixel edge are dropped where its own colour is closer to the
# outside's local mean than to the interior's by this factor: blobby relevance maps reach a pixel
# past the region, and a surface seen edge-on beside it (a neck under a head) would be selected whole.
EDGE_COLOUR_RATIO = 0.5
# Each Gaussian's pooled vote counts this fraction of the pooled rendering weight a selected one
# typically has (the median over those selected without it) as weight outside the masks: a
# Gaussian the views barely see (a neighbour's behind the region's rim) is not selected on the
# little it shows, all of it inside blobby masks; a part whose Gaussians are all faint still is.
EVIDENCE_PRIOR = 0.02
# The views-disagree stop counts a mask pixel within this many pixels of the other mask as shared:
# a part a few pixels across, its masks a pixel off, is the same place.
AGREEMENT_TOLERANCE_PX = 1


# The trial's save/ file of a localization's evidence (selection, lift scores, neighbourhoods, 2D
# masks), written by the regional edit and read by gs_regional.localize and the studio.
LOCALIZATION_FILE = "localization.npz"


@dataclass
class LocalizeConfig:
    """`system.localization` (§3.1; docs/method.md "Localize")."""

    REMOVED_KEYS: ClassVar[Dict[str, str]] = {
        "reweight_iters": "the lift re-weights its views as the method does; system.ablation.plain_vote=true gives "
                          "the paper's vote (no re-weighting, no neighbour pooling); remove the key",
        **{key: f"it is the constant {key.upper()} of gs_regional/stages/localize.py now; remove the key"
           for key in ("agreement_power", "edge_colour_ratio", "agreement_tolerance_px")},
    }
    # The values a removed key had to have for an older checkpoint to resume as the method now runs.
    RETIRED_VALUES: ClassVar[Dict[str, object]] = {
        "reweight_iters": REWEIGHT_ITERS, "agreement_power": AGREEMENT_POWER, "edge_colour_ratio": EDGE_COLOUR_RATIO,
        "agreement_tolerance_px": AGREEMENT_TOLERANCE_PX,
    }
    max_views: int = 24  # views rendered for the 2D relevance maps, spread over the cameras
    timestep: int = 600  # τ of the noise difference
    gamma: float = 0.6  # threshold of the normalised relevance; 0 selects everything
    samples: int = 1  # noise draws averaged per view
    blur_sigma: float = 2.0  # Gaussian filter that removes isolated specks (pixels)
    mask_threshold: float = 0.5  # a Gaussian is selected if its weighted mask vote exceeds this
    knn: int = 16  # pool votes over the k nearest Gaussians (point expansion)
    expand_radius: float = 0.0  # also select everything within this radius, as a fraction of the scene extent
    # The views disagree about the region when, even in the better half of them (side views may
    # miss it), the 2D masks overlap the rendered 3D mask by less than this (mean IoU): the
    # instruction names nothing the editor finds consistently, and the run stops with the source
    # written unchanged. 0 never stops.
    min_view_agreement: float = 0.3
    # The first full edit checked against the selection, without ground truth: the fraction of the
    # editor's change beyond its noise in that view within 2 px of the localized region
    # (metrics.json `edit_coverage`; gs_regional/stages/first_view.py). Below this, most of what the
    # editor changes is not what localization selected, and the run stops with the source written
    # unchanged. 0 never stops.
    min_edit_coverage: float = 0.5

    def check(self, where: str = "system.localization", num_train_timesteps: int = 1000) -> None:
        need(self.max_views >= 1, f"{where}.max_views", "an integer >= 1", self.max_views)
        need(0 <= self.timestep < num_train_timesteps, f"{where}.timestep",
             f"a timestep in [0, {num_train_timesteps - 1}]", self.timestep)
        need(self.samples >= 1, f"{where}.samples", "an integer >= 1", self.samples)

    def lift(self, plain_vote: bool = False) -> dict:
        """The keyword arguments of `localize_gaussians` (`plain_vote`: the paper's vote, no view
        re-weighting, neighbour pooling or evidence prior)."""
        return dict(threshold=self.mask_threshold, reweight_iters=0 if plain_vote else REWEIGHT_ITERS,
                    agreement_power=AGREEMENT_POWER, knn=1 if plain_vote else self.knn, edge_ratio=EDGE_COLOUR_RATIO,
                    evidence_prior=0.0 if plain_vote else EVIDENCE_PRIOR)


@torch.no_grad()
def edge_colour_references(masks: torch.Tensor, images: torch.Tensor, sigma: float = 1.0) -> tuple:
    """For each 2D mask (B, H, W): its one-pixel edge where a verdict is possible, and there the
    local mean colour (Gaussian-weighted, `sigma` px) of the mask's interior and of the outside,
    from `images` (B, H, W, 3). Returns (edge (B, H, W) bool, mean_in, mean_out (B, H, W, 3)).
    An edge pixel with no interior or no outside pixel nearby gets no verdict (not in `edge`)."""
    inside = masks > 0.5
    interior = F.max_pool2d((~inside).float()[:, None], 3, 1, 1)[:, 0] < 0.5  # not next to the outside
    img = images.to(masks.device).float().permute(0, 3, 1, 2)  # (B, 3, H, W)

    def local_mean(where: torch.Tensor) -> tuple:
        w = where.float()
        den = gaussian_blur(w, sigma)
        mean = torch.stack([gaussian_blur(img[:, c] * w, sigma) for c in range(3)], -1) / den[..., None].clamp_min(1e-6)
        return mean, den > 1e-3

    mean_in, has_in = local_mean(interior)
    mean_out, has_out = local_mean(~inside)
    return inside & ~interior & has_in & has_out, mean_in, mean_out


@torch.no_grad()
def outside_like_edge_votes(
    view: PixelWeights, colours: torch.Tensor, edge: torch.Tensor, mean_in: torch.Tensor, mean_out: torch.Tensor,
    ratio: float,
) -> torch.Tensor:
    """(N,) the part of each Gaussian's mask vote (Σ_x w_i M) in one view that comes from the mask's
    edge pixels (`edge_colour_references`) when the Gaussian's own colour in that view (`colours`
    (N, 3)) is closer, by at least 1 / `ratio`, to the outside's local mean there than to the
    interior's (means weighted by the Gaussian's pixel weights): a vote to drop.

    Why: relevance maps are blobby (from 64x64 latents, blurred), so a mask's edge lies about a
    pixel outside the object's, and a surface seen at a grazing angle next to the region (a neck
    under a head) projects into that one-pixel seam in every view: the lift would select all of
    it. An edge pixel is shared by the region's Gaussians and the outside's; each Gaussian's own
    colour tells which side it is on, so the region's silhouette keeps its votes (dropping the
    pixel for everyone lost them). One extra gather per view: the cost is that of a render."""
    e = edge.float()[..., None]
    g = view.gather(torch.cat([e, mean_in * e, mean_out * e], -1))  # (N, 7)
    w_edge = g[:, 0]
    seen = w_edge > 1e-8
    d_in = (colours - g[:, 1:4] / w_edge.clamp_min(1e-8)[:, None]).norm(dim=1)
    d_out = (colours - g[:, 4:7] / w_edge.clamp_min(1e-8)[:, None]).norm(dim=1)
    return torch.where(seen & (d_out < ratio * d_in), w_edge, torch.zeros_like(w_edge))


def view_weights(model, renderer, cameras: Sequence[Camera]) -> list:
    """The compositing weights of every view (`Renderer.pixel_weights`): found once, then every
    lift and render-back of a localization reuses them (the geometry does not change meanwhile)."""
    return [renderer.pixel_weights(model, cam) for cam in cameras]


def mask_votes(views: Sequence[PixelWeights], masks: Sequence[torch.Tensor]) -> tuple:
    """Per-view votes (V, N) of every Gaussian: numerator Σ_x w_i(v,x)·M_v(x) and denominator
    Σ_x w_i(v,x), where w_i is the Gaussian's alpha-compositing weight."""
    num = torch.stack([v.gather(m.float()) for v, m in zip(views, masks)])
    den = torch.stack([v.totals(*m.shape, m.device) for v, m in zip(views, masks)])
    return num, den


def weighted_scores(num: torch.Tensor, den: torch.Tensor, view_weights: torch.Tensor) -> torch.Tensor:
    """s_i = Σ_v a_v·num_vi / Σ_v a_v·den_vi (0 for Gaussians no view sees)."""
    n = (view_weights[:, None] * num).sum(0)
    d = (view_weights[:, None] * den).sum(0)
    return torch.where(d > 1e-8, n / d.clamp_min(1e-8), torch.zeros_like(n))


def lift_masks(model, renderer, cameras: Sequence[Camera], masks: Sequence[torch.Tensor]) -> torch.Tensor:
    """The plain rendering-weight vote of §3.1 step 4: s_i = Σ_v Σ_x w_i M_v / Σ_v Σ_x w_i."""
    num, den = mask_votes(view_weights(model, renderer, cameras), masks)
    return weighted_scores(num, den, torch.ones(len(cameras), device=num.device))


def covered(cover: torch.Tensor, faint: bool = False) -> torch.Tensor:
    """(H, W) bool: the pixels a selection's render `cover` (`render_selection`) covers by more than
    half; with `faint`, in a view where it covers none by half (a part a pixel or two across), those
    it covers by more than half of its most."""
    peak = float(cover.max())
    return cover > (0.5 * peak if faint and peak <= 0.5 else 0.5)


def mask_agreement(views: Sequence[PixelWeights], masks: Sequence[torch.Tensor], selected: torch.Tensor,
                   faint: bool = False, tolerance_px: int = 0) -> torch.Tensor:
    """IoU, per view, of the 2D mask with the render of the 3D selection (V,): the pixels the
    selection covers by more than half. With `faint` (the views-disagree stop), a view in which it
    covers no pixel by half (a part a pixel or two across) uses the pixels it covers by more than
    half of its most, whose IoU is otherwise 0 whatever the mask; the lift's view weights keep the
    plain rule, so such views have no say in the lift.

    `tolerance_px` > 0 (the stop) counts a pixel of either mask as shared when the other mask
    lies within that many pixels of it: the IoU 1 / (1/p + 1/q - 1) of those fractions p, q of
    each mask (at 0 that is the plain IoU).
    Relevance maps reach a pixel or two past the region; on a part 3 px across that halves the
    plain IoU though both masks lie on the same spot, while a mask elsewhere stays apart."""
    out = []
    for view, m in zip(views, masks):
        r = covered(splat_selection(view, selected), faint)
        m = m.to(r.device) > 0.5
        # a, b: the pixels of each mask within tolerance_px of the other (0: both the intersection,
        # and the expression is the plain IoU exactly: integer counts, one rounding)
        a = float((m & dilate(r, tolerance_px)).sum())
        b = float((r & dilate(m, tolerance_px)).sum())
        out.append(a * b / (b * float(m.sum()) + a * float(r.sum()) - a * b) if a * b > 0 else 0.0)
    return torch.tensor(out, device=selected.device)


def neighbourhoods(means: torch.Tensor, k: int) -> torch.Tensor:
    """(N, min(k, N)) row indices: each Gaussian itself, then its k - 1 nearest other Gaussians
    (exact; a voxel-grid search, no N x N distances)."""
    others = neighbors.knn(means, k - 1)[1] if k > 1 else means.new_zeros((means.shape[0], 0), dtype=torch.long)
    return torch.cat([torch.arange(means.shape[0], device=means.device)[:, None], others], 1)


def knn_pool(num: torch.Tensor, den: torch.Tensor, neighbourhood: torch.Tensor) -> tuple:
    """Sum votes over each Gaussian's neighbourhood (rows of `neighbourhoods`), so a Gaussian that
    few views see well takes the verdict of its well-seen neighbours."""
    return num[neighbourhood].sum(1), den[neighbourhood].sum(1)


def fill_unseen_scores(scores: torch.Tensor, seen: torch.Tensor, neighbourhood: torch.Tensor) -> torch.Tensor:
    """(N,) `scores` with those of the Gaussians no view sees (`seen` < SEEN_MIN_WEIGHT pixels)
    replaced, layer by layer inward, by the mean score of their neighbours (rows of
    `neighbourhoods`) that have one: the seen ones, then those filled in an earlier layer.

    Why: a part's inside and its hidden side show the views nothing, and their pooled vote is
    mostly the evidence prior's, so they were left out (a whole part's recall 0.8: IoU counts every
    Gaussian). No view contradicts them either: the nearest evidence is their neighbours'. Each
    layer works on the rows still open (linear in N); one that no chain of neighbours reaches from
    a seen Gaussian keeps its own score."""
    open_rows = (seen < SEEN_MIN_WEIGHT).nonzero().squeeze(1)
    if open_rows.numel() == 0:
        return scores
    scores, known = scores.clone(), seen >= SEEN_MIN_WEIGHT
    rows = neighbourhood[open_rows, 1:]  # not itself
    while open_rows.numel():
        labelled = known[rows].to(scores.dtype)
        count = labelled.sum(1)
        reached = count > 0
        if not bool(reached.any()):
            break
        mean = (labelled * scores[rows]).sum(1) / count.clamp_min(1)
        scores[open_rows[reached]] = mean[reached]
        known[open_rows[reached]] = True
        open_rows, rows = open_rows[~reached], rows[~reached]
    return scores


def localize_gaussians(
    model, renderer, cameras: Sequence[Camera], masks: Sequence[torch.Tensor], threshold: float = 0.5,
    reweight_iters: int = REWEIGHT_ITERS, agreement_power: float = AGREEMENT_POWER, knn: int = 16,
    images: Optional[torch.Tensor] = None, edge_ratio: float = 0.0, reuse: Optional[dict] = None,
    evidence_prior: float = 0.0,
) -> dict:
    """§3.1 step 4 with four robustness steps of our own (all can be switched off):

    * edge test (`edge_ratio` > 0, needs the views' `images` (V, H, W, 3)): a Gaussian's votes from
      a mask's one-pixel edge are dropped in a view where its own colour looks like the outside's
      rather than the interior's (`outside_like_edge_votes`); 0 changes nothing.

    * view reweighting: a 2D editor fails in some views (side views, leakage). After a first lift,
      each view's vote is weighted by (IoU of its 2D mask with the render of the 3D mask) **
      `agreement_power`, and
      the lift is repeated `reweight_iters` times; views that disagree with the consensus fade.
    * neighbour pooling (point expansion): votes are summed over the `knn` nearest Gaussians, so
      rarely seen Gaussians follow their neighbourhood.
    * evidence prior (`evidence_prior` > 0, EVIDENCE_PRIOR): each pooled vote also counts that
      fraction of the median pooled weight of the Gaussians selected without it as weight outside
      the masks, so one that shows the views next to nothing is not selected; 0 changes nothing.
    * with neighbour pooling, the Gaussians no view sees take their neighbours' scores
      (`fill_unseen_scores`).
    `reuse`: the result of an earlier lift of the same geometry from the same cameras with the same
    `knn`: its pixel weights and neighbourhoods are taken as they are (no new renders, no new search);
    {"views": the cameras' `view_weights`} alone: those pixel weights, the neighbourhoods searched.
    Returns {"selected": (N,) bool, "scores": (N,), "view_weights": (V,), "views": the
    `PixelWeights` of the cameras, to render selections back without new renders, "seen": (N,)
    each Gaussian's rendering weight summed over the views, in pixels, "neighbourhood": the rows
    votes were pooled over (None when knn <= 1)}.
    """
    views = view_weights(model, renderer, cameras) if reuse is None else reuse["views"]
    num, den = mask_votes(views, masks)
    if edge_ratio > 0:
        if images is None:
            raise ValueError("localize_gaussians: edge_ratio > 0 needs the views' images")
        edge, mean_in, mean_out = edge_colour_references(torch.stack([m.float() for m in masks]), images)
        for v, (view, cam) in enumerate(zip(views, cameras)):
            colours = sh_to_color(model.sh_degree, model.sh.detach(), model.means.detach(), cam.center).clamp(0, 1)
            num[v] -= outside_like_edge_votes(view, colours, edge[v], mean_in[v], mean_out[v], edge_ratio)
    # the neighbours do not change between reweighting passes: found once
    if reuse is not None and "neighbourhood" in reuse:
        neighbourhood = reuse["neighbourhood"]
    else:
        neighbourhood = neighbourhoods(model.means.detach(), knn) if knn > 1 else None
    weights = torch.ones(len(cameras), device=num.device)
    for it in range(reweight_iters + 1):
        s_num = (weights[:, None] * num).sum(0)
        s_den = (weights[:, None] * den).sum(0)
        if neighbourhood is not None:
            s_num, s_den = knn_pool(s_num, s_den, neighbourhood)
        scores = torch.where(s_den > 1e-8, s_num / s_den.clamp_min(1e-8), torch.zeros_like(s_num))
        without_prior = scores > threshold
        if evidence_prior > 0 and bool(without_prior.any()):
            scores = s_num / (s_den + evidence_prior * float(s_den[without_prior].median()))
        selected = scores > threshold
        if it < reweight_iters and bool(selected.any()):
            weights = mask_agreement(views, masks, selected) ** agreement_power
            if float(weights.sum()) <= 0:
                break
    seen = den.sum(0)
    if neighbourhood is not None:  # unseen Gaussians render nothing: the view weights above stand
        scores = fill_unseen_scores(scores, seen, neighbourhood)
        selected = scores > threshold
    return {"selected": selected, "scores": scores, "view_weights": weights, "views": views, "seen": seen,
            "neighbourhood": neighbourhood}


def expand_selection(means: torch.Tensor, selected: torch.Tensor, radius: float) -> torch.Tensor:
    """Point expansion: also select every Gaussian within `radius` of a selected one."""
    if radius <= 0 or not bool(selected.any()) or bool(selected.all()):
        return selected
    out = selected.clone()
    out[~selected] = neighbors.within_radius(means[~selected], means[selected], radius)
    return out


@dataclass
class Localization:
    """What `localize_selection` found."""

    selected: torch.Tensor  # (N,) bool, after point expansion
    lifted: dict  # `localize_gaussians`' result (its pixel weights "views", "seen", ...)
    cameras: list
    lift: dict  # the keywords it was lifted with
    metrics: dict  # {"view_weights", "view_agreement"}

    def relift(self, model, renderer, masks: Sequence[torch.Tensor]) -> torch.Tensor:
        """(N,) bool: the same lift of other 2D `masks` (no new renders)."""
        return localize_gaussians(model, renderer, self.cameras, masks, reuse=self.lifted, **self.lift)["selected"]


@torch.no_grad()
def localize_selection(model, renderer, cameras: Sequence[Camera], masks: Sequence[torch.Tensor], images: torch.Tensor,
                       cfg: LocalizeConfig, extent: float, plain_vote: bool = False,
                       agree: Callable[[torch.Tensor], torch.Tensor] = lambda x: x) -> Localization:
    """§3.1 steps 4-5 from the views' 2D `masks`: the lift (`localize_gaussians` with `cfg`'s
    settings), point expansion, and how well the views agree with the selection (`view_agreement`:
    the mean IoU of the 2D masks with the selection in the better half of the views). `agree`: the
    selection every process of a run on several devices edits (rank 0's)."""
    lift = dict(cfg.lift(plain_vote), images=images)
    lifted = localize_gaussians(model, renderer, cameras, masks, **lift)
    selected = agree(expand_selection(model.means.detach(), lifted["selected"], cfg.expand_radius * extent))
    iou = mask_agreement(lifted["views"], masks, selected, faint=True, tolerance_px=AGREEMENT_TOLERANCE_PX)
    metrics = {"view_weights": [round(float(w), 3) for w in lifted["view_weights"]],
               "view_agreement": float(iou.sort(descending=True).values[: (len(iou) + 1) // 2].mean())}
    return Localization(selected, lifted, list(cameras), lift, metrics)


def views_disagree(agreement: float, min_view_agreement: float) -> str:
    """The warning of a run that stops because the views disagree about the region."""
    return (f"localize: the views disagree about the region (its 2D masks overlap the lifted 3D mask by IoU "
            f"{agreement:.2f} in the better half of the views, below system.localization.min_view_agreement="
            f"{min_view_agreement}); the instruction names nothing the editor finds consistently.")
