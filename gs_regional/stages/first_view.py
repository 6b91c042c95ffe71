"""§3.2 step 1 and the safe stop: which view is edited first, and whether its full edit lies in
the localized region (no ground truth needed). Plain functions of the views' renders, masks and
edits, so a test can call them without a system: `choose_first_view` takes the views' full edits
through a callable (each edited at most once) and returns a typed `FirstView`."""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from typing import Callable, Dict, List, Optional

import torch

from gs_regional.stages.change import edit_change

log = logging.getLogger(__name__)

# A first edit whose change (beyond the editor's noise) is under this fraction of another view's
# shows nothing of the edit: the region is hidden there.
SHOWS_NOTHING = 0.15
# A full edit whose change covers fewer than this fraction of the view's pixels is too small to say
# where the edit is (at 64², 8 pixels: an object a few pixels across, or a jittered placement
# showing a pixel of it): it cannot stop the run.
MIN_JUDGED_CHANGE = 0.002
# A first view whose selection overlaps its 2D mask by less than this share of the best view's
# overlap hides the region; one that shows it as well keeps the edit even when a tone drift drowns
# the edit's change there.
HIDES_REGION = 0.5
# A full edit lies in the selection when at least `min_edit_coverage` of its change lies there, or
# half of that while it changes at least this fraction of the selection's pixels: a big object
# added on a small part sticks out over what lies behind but covers the part, while an edit placed
# on something else changes next to none of the selection.
MIN_FILLED = 0.1


@dataclass
class EditCheck:
    """What of a full edit's change lies in the localized region of its view."""

    view: int
    coverage: Optional[float]  # the fraction of the change near the region; None: cannot be told
    changed_px: float  # pixels of change beyond the editor's noise
    region_px: int
    region_changed: float  # the fraction of the region's pixels the edit changes
    image_px: int = field(default=0, repr=False)  # pixels of the view
    decides: bool = False  # the check the run goes on (or stops) by
    too_small_to_judge: bool = False  # outside the region, but too small a change to stop the run

    def as_dict(self) -> dict:
        """For metrics.json `edit_coverage_views` (the flags only when set)."""
        out = {k: v for k, v in asdict(self).items() if k not in ("image_px", "decides", "too_small_to_judge")}
        out.update({k: True for k in ("decides", "too_small_to_judge") if getattr(self, k)})
        return out

    @property
    def judged_px(self) -> float:
        """Pixels of change the edit needs for its coverage to stop the run."""
        return MIN_JUDGED_CHANGE * self.image_px

    def agrees(self, min_coverage: float) -> bool:
        """The edit lies in the selection (MIN_FILLED); False when that cannot be told."""
        cov = self.coverage
        return cov is not None and (cov >= min_coverage or (cov >= min_coverage / 2 and self.region_changed >= MIN_FILLED))

    def elsewhere(self, min_coverage: float) -> bool:
        """The edit lies outside the selection (a global edit cannot be told)."""
        return self.coverage is not None and not self.agrees(min_coverage)


@dataclass
class FirstView:
    """The first edited view, its full edit, the checks made on the way, and whether the run stops."""

    view: int
    edited: torch.Tensor
    checks: List[EditCheck]
    stop: bool = False

    @property
    def decided(self) -> EditCheck:
        return next(c for c in self.checks if c.decides)

    @property
    def own(self) -> EditCheck:
        """The check of `view`'s own edit (`decided` may be another view's)."""
        return next(c for c in self.checks if c.view == self.view)


def mask_areas(regions: List[torch.Tensor], masks2d: Optional[torch.Tensor],
               calibratable: Optional[List[bool]] = None) -> torch.Tensor:
    """(V,) what the first view is chosen by (§3.2: v_first = argmax_v Σ M_v, the view where the
    editor is most confident about the region, usually a frontal one): the area of each view's 2D
    mask (`masks2d`; of its localized `regions` when there are none), and -1 for the views that
    are not `calibratable` (too few pixels outside the region for the monocular depth) when any is."""
    areas = masks2d.flatten(1).sum(1).float() if masks2d is not None else torch.stack([r.sum() for r in regions]).float()
    if calibratable is not None and any(calibratable):
        areas = torch.where(torch.tensor(calibratable, device=areas.device), areas, torch.full_like(areas, -1.0))
    return areas


def behind_region(alpha: torch.Tensor, depth: torch.Tensor, region: torch.Tensor) -> torch.Tensor:
    """(H, W) bool: where the source (rendered `alpha`, `depth`) shows something farther than the
    region by more than the region's own depth range (what an object added on it may cover). The
    range is the 5th to 95th percentile of the region's depths: a few stray Gaussians the lift
    selected on the backdrop would otherwise set it."""
    opaque = alpha > 0.5
    d = depth[region & opaque]
    if d.numel() == 0:
        return torch.zeros_like(opaque)
    ordered = d.sort().values  # (torch.quantile refuses more than 16M values)
    near, far = float(ordered[int(0.05 * (len(ordered) - 1))]), float(ordered[int(0.95 * (len(ordered) - 1))])
    return opaque & (depth > far + (far - near))


def check_edit(view: int, edited: torch.Tensor, source: torch.Tensor, region: torch.Tensor, alpha: torch.Tensor,
               depth: torch.Tensor, global_edit: bool = False) -> EditCheck:
    """What of the full edit `edited` of `view` (its source render `source`, rendered `alpha` and
    `depth`, the localized `region` (H, W) bool) lies in the region (`edit_change`). A global edit
    leaves nothing to compare: coverage None."""
    counts = None if global_edit else edit_change(
        edited, source, region, opaque=alpha > 0.5, behind=behind_region(alpha, depth, region))
    near, total, filled = counts if counts is not None else (0.0, 0.0, 0.0)
    return EditCheck(view=view, coverage=near / total if total > 0 else None, changed_px=round(total, 1),
                     region_px=int(region.sum()), region_changed=round(filled, 3),
                     image_px=int(edited.shape[0] * edited.shape[1]))


def choose_first_view(
    views: List[int],  # the localization views
    areas: torch.Tensor,  # (V,) the 2D masks' areas; < 0: a view that cannot be initialized from
    localized: Dict[int, torch.Tensor],  # view -> (H, W) bool, the selection rendered back
    masks2d: List[torch.Tensor],  # (H, W) bool per view: the editor's own 2D masks
    first: int,  # the view the 2D masks are largest in
    edit: Callable[[int], torch.Tensor],  # view -> its full edit (the caller edits each view once)
    check: Callable[[int, torch.Tensor], EditCheck],  # (view, its full edit) -> check_edit
    min_edit_coverage: float,
) -> FirstView:
    """The first view and its full edit, and whether that edit lies outside the selection (`stop`).
    One edit of one view is thin evidence for throwing the run away, so other views are edited
    as the evidence asks (docs/method.md "The safe stops")."""
    low = min_edit_coverage

    def edited_check(u: int):
        out = edit(u)
        return out, check(u, out)

    v, (edited, c) = first, edited_check(first)
    checks = [c]
    overlap = torch.stack([(localized[u] & m).sum() for u, m in zip(views, masks2d)]).float().to(areas.device)
    best = views[int(torch.argmax(torch.where(areas >= 0, overlap, torch.full_like(overlap, -1.0))))]
    hides = float(overlap[views.index(v)]) < HIDES_REGION * float(overlap[views.index(best)])
    if c.changed_px < c.judged_px and best != v and hides:
        # The first edit shows next to nothing and the view hides the region: there the relevance
        # map, normalised to its peak, is noise whose blobs can make the largest 2D mask. The view
        # where the editor's 2D mask and the selection overlap most is edited and used instead.
        v, (edited, c) = best, edited_check(best)
        checks.append(c)
    if c.elsewhere(low):
        # The view where the 2D masks and the selection overlap most is edited too, and decides
        # when the first edit showed almost nothing (SHOWS_NOTHING: initialization moves there) or
        # only just missed (coverage at least half the minimum: a placement jittered off the
        # region's edge; initialization stays with the first view). Only views that can be
        # initialized from (areas >= 0), by overlap.
        others = [views[i] for i in torch.argsort(overlap, descending=True, stable=True).tolist()
                  if views[i] != v and areas[i] >= 0]
        if others:
            u = others[0]
            edited_u, c_u = edited_check(u)
            checks.append(c_u)
            log.info("initialize: the first edit (view %d) lies outside the selection: %s; view %d: %s",
                     v, c.as_dict(), u, c_u.as_dict())
            if c.changed_px < max(SHOWS_NOTHING * c_u.changed_px, c.judged_px):
                v, edited, c = u, edited_u, c_u
            elif c.coverage >= low / 2:
                c = c_u
            elif c_u.agrees(low) and len(others) > 1:
                # The two views disagree: a third view, the next by overlap, decides; when it agrees
                # with the second, the run goes on from the second view. (Only a view that agrees:
                # one "only just missing" would let a wrong selection through.)
                _, c_w = edited_check(others[1])
                checks.append(c_w)
                log.info("initialize: views %d and %d disagree; view %d: %s", v, u, others[1], c_w.as_dict())
                if c_w.agrees(low):
                    v, edited, c = u, edited_u, c_u
    c.decides = True
    stop = False
    if c.elsewhere(low):
        if c.changed_px >= c.judged_px:
            stop = True
        else:
            c.too_small_to_judge = True
            log.info("initialize: the edit of view %d changes %.1f pixels beyond the editor's noise, too few to tell "
                     "whether it lies in the selection; the edit goes on", c.view, c.changed_px)
    return FirstView(view=v, edited=edited, checks=checks, stop=stop)


def stop_message(first: FirstView, min_edit_coverage: float) -> str:
    """The warning of a run that stops because its first edit lies outside the region."""
    decided = first.decided
    if decided.view != first.view:
        # the first edit only just missed and the view where the 2D masks and the selection overlap
        # most decided (initialization stays with the first view)
        lead = (f"view {decided.view}, where the editor's 2D masks and the selection overlap most, changes the image "
                f"outside the localized region too")
        note = f" (view {first.view}, edited first, puts {first.own.coverage or 0:.2f} in it)"
    else:
        lead = f"the first edited view ({decided.view}) changes the image outside the localized region"
        other = next((c for c in first.checks if c is not decided), None)
        note = "" if other is None else (
            f" (view {other.view}, edited first, showed almost nothing of the edit)" if other is first.checks[0] else
            f" (view {other.view}, where the editor's 2D masks and the selection overlap most, puts "
            f"{other.coverage or 0:.2f} in it: the editor edits different things in different views)")
    return (f"initialize: {lead}: a fraction {decided.coverage:.2f} of its change beyond the editor's noise lies in the "
            f"region, below system.localization.min_edit_coverage={min_edit_coverage}, and it changes "
            f"{decided.region_changed:.2f} of the region's pixels{note}; localization selected something other than what "
            f"the editor edits.")
