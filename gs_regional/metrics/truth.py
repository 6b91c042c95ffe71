"""Scoring against a known truth (DESIGN.md §3.4): on scenes whose edit is known (the simulators'
synthetic scene, `splat-truth`), how the localization and the edited scene compare with the true
region and the true edited scene. Nothing here steers an edit: the system calls it through its
`truth` hook (None when the scene has no ground truth)."""
from __future__ import annotations

from typing import Any, Callable, Dict, List, Optional, Sequence

import torch

from gs_regional.geometry import rows
from gs_regional.metrics.image import psnr, ssim
from gs_regional.metrics.region import (
    SEEN_MIN_WEIGHT, footprint, mask_metrics, region_scores, render_selection, splat_selection,
)
from gs_regional.utils.image import dilate
from gs_regional.utils.sh import sh_to_color



class TruthScoring:
    """The scene's known edit `truth`, rendered with `renderer` at `cameras` on `device()` (the
    module's device, which Lightning sets after this is made)."""

    def __init__(self, truth: Any, renderer, cameras: Sequence, device: Callable[[], torch.device],
                 footprint_threshold: float = 0.1) -> None:
        self.gt, self.renderer, self.cameras, self.device = truth, renderer, cameras, device
        self.footprint_threshold = footprint_threshold
        self._edited: Dict[int, torch.Tensor] = {}

    def camera(self, index: int):
        return self.cameras[index].to(self.device())

    def edited_render(self, index: int) -> torch.Tensor:
        """(H, W, 3) the true edited scene at view `index` (rendered once)."""
        if index not in self._edited:
            with torch.no_grad():
                self._edited[index] = self.renderer.render(self.gt.edited.to(self.device()), self.camera(index))["rgb"]
        return self._edited[index]

    def footprint(self, index: int) -> torch.Tensor:
        """(H, W) bool: the pixels the true edit is about at view `index`: where the true region
        renders in the source scene or the edited scene's region (with what the edit adds)
        renders in the true edited scene."""
        gt, cam, d = self.gt, self.camera(index), self.device()
        weight = torch.maximum(render_selection(gt.source.to(d), self.renderer, cam, gt.region.to(d)),
                               render_selection(gt.edited.to(d), self.renderer, cam, gt.new_region.to(d)))
        return footprint(weight, self.footprint_threshold)

    def unchanged(self, index: int, source: torch.Tensor) -> torch.Tensor:
        """(H, W) bool: the pixels that should not change at view `index` (`source`: its source
        render): where the true edited scene renders like the source, away from the true region."""
        gt, d = self.gt, self.device()
        region = render_selection(gt.source.to(d), self.renderer, self.camera(index), gt.region.to(d))
        changed = ((self.edited_render(index) - source).abs().amax(-1) > 2.0 / 255) | (region > 0.01)
        return ~dilate(changed, 2)

    @torch.no_grad()
    def localization(self, model, selection: torch.Tensor, n_source: int, seen: Optional[torch.Tensor] = None,
                     views: Optional[Sequence] = None, relift: Optional[Callable[[List[torch.Tensor]], torch.Tensor]] = None) -> dict:
        """The localized `selection` (rows of the source) against the true region: mask IoU,
        precision, recall. After a lift also: the IoU over the Gaussians its views see (`seen`: each
        one's rendering weight over them, in pixels; no localizer can find the others), and the
        IoU, precision and recall that the same lift (`relift`: 2D masks -> selected rows of `model`)
        makes of exact 2D masks (`..._exact_masks`), the true region's own render from the views'
        pixel weights (`views`): what the views' resolution allows, apart from the relevance maps'
        errors."""
        truth = self.gt.region.cpu()
        out = dict(mask_metrics(selection.cpu(), truth))
        if seen is None:
            return out
        seen = seen.cpu() >= SEEN_MIN_WEIGHT
        out["mask_iou_seen"] = mask_metrics(selection.cpu()[seen], truth[seen])["mask_iou"]
        out["region_unseen"] = int((truth & ~seen).sum())
        exact = [splat_selection(v, truth.to(self.device())) > 0.5 for v in views]
        from_exact = mask_metrics(rows.source_rows(model, relift(exact), n_source).cpu(), truth)
        out.update({f"{key}_exact_masks": value for key, value in from_exact.items()})
        return out

    @torch.no_grad()
    def scores(self, views: List[int], after: torch.Tensor, source: torch.Tensor) -> tuple:
        """(metrics, footprints): the renders `after` (V, H, W, 3) of the edited scene at `views`
        against the true edited scene, over all pixels, inside its footprint and outside, next to
        what the unedited `source` renders score; and the (V, H, W) footprints."""
        truth = torch.stack([self.edited_render(i) for i in views])
        inside = torch.stack([self.footprint(i) for i in views])
        metrics = {"psnr_vs_true_edit": psnr(after, truth), "ssim_vs_true_edit": ssim(after, truth),
                   "psnr_source_vs_true_edit": psnr(source, truth),  # leaving the scene unedited, for scale
                   "footprint_fraction": float(inside.float().mean())}
        metrics.update(region_scores(after, source, truth, inside))
        return metrics, inside

    @torch.no_grad()
    def recolour_rows(self, model, selection: torch.Tensor, taken: torch.Tensor, views: Sequence[int]) -> dict:
        """How much of a recolour reached the true region's Gaussians, and which stage lost the
        rest. Each true-region row's colour error (base colour against the true edit's, squared)
        is weighted by how much the `views` see it (its rendering weight there, in pixels), as the
        footprint PSNR weighs it. `recolour_done`: the share of doing nothing's error the result
        removed; the error left is split into the rows localization did not select
        (`recolour_left_unselected`), those it selected and the recolour gate declined
        (`..._declined`: not in `taken`) and those that trained (`..._taken`); shares of 1, None
        when no error is left. {} unless both the true edit and the result keep exactly the
        source's rows (a recolour that added, split or pruned nothing)."""
        gt, d = self.gt, self.device()
        n = len(gt.source)
        if len(gt.edited) != n or model.num_gaussians != n or not bool(
                (model.source_index.to(d) == torch.arange(n, device=d)).all()):
            return {}
        source, true = gt.source.to(d), gt.edited.to(d)
        region = gt.region.to(d)
        left, before = torch.zeros(n, device=d), torch.zeros(n, device=d)

        def colour(m, cam):  # each Gaussian's colour as the view sees it (its SH at the view's direction)
            return sh_to_color(m.sh_degree, m.sh.detach(), m.means.detach(), cam.center)

        for i in views:
            cam = self.camera(i)
            seen = self.renderer.pixel_weights(source, cam).totals(cam.height, cam.width, d)
            left += seen * (colour(model, cam) - colour(true, cam)).pow(2).sum(-1) * region
            before += seen * (colour(source, cam) - colour(true, cam)).pow(2).sum(-1) * region
        total, before = float(left.sum()), float(before.sum())
        selected, taken = selection.to(d).bool(), taken.to(d).bool()
        groups = {"unselected": ~selected, "declined": selected & ~taken, "taken": selected & taken}
        out = {"recolour_done": 1.0 - total / before if before > 0 else None}
        out.update({f"recolour_left_{name}": float(left[rows_].sum()) / total if total > 0 else None
                    for name, rows_ in groups.items()})
        return out

    @torch.no_grad()
    def addition_cover(self, model, added: torch.Tensor, views: Sequence[int]) -> dict:
        """How much of the true edit's new object the Gaussians an addition placed draw, over the
        `views`: `added_cover` the share of the true object's coverage (its rendered weight in the
        true edited scene, summed over pixels) that the result's `added` rows cover there too (1: as
        opaque wherever the truth is; an object drawn thin or in part stays under it), and
        `added_cover_outside` their coverage where the true object is not, in the same unit (a
        misplaced or spilled object). {} when the true edit adds nothing."""
        gt, d = self.gt, self.device()
        n = len(gt.source)
        new = gt.new_region.to(d) & (torch.arange(len(gt.edited), device=d) >= n)
        if not bool(new.any()):
            return {}
        inside = outside = total = 0.0
        for i in views:
            cam = self.camera(i)
            truth = render_selection(gt.edited.to(d), self.renderer, cam, new)
            drawn = render_selection(model, self.renderer, cam, added.to(d))
            inside += float(torch.minimum(drawn, truth).sum())
            outside += float((drawn - truth).clamp_min(0).sum())
            total += float(truth.sum())
        return {"added_cover": inside / total, "added_cover_outside": outside / total} if total > 0 else {}

    def gaussians_added(self) -> int:
        return len(self.gt.edited) - len(self.gt.source)
