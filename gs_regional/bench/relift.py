"""The lift of saved localizations again, with its edge colour test at other ratios: for each trial
of a truth-suite output (or one trial), the 2D masks its localization saved (save/localization.npz)
and exact 2D masks of its known region, lifted as the trial's config lifts them but with
`EDGE_COLOUR_RATIO` replaced; the median mask IoU, precision and recall of each ratio. With
`--thresholds`, each case is also lifted at each of those `mask_threshold`s and keeps its best IoU:
the median of those bests says how far the lift's bias alone could take the IoU (were each case
given its own), apart from what the masks themselves get wrong. With `--grow PX`, the exact masks are
also lifted grown by PX pixels ("grown"): what masks that reach that far past the part allow the lift,
as relevance maps from coarse latents do. With `--breakdown`, instead, where
each run's selection departs from the truth (`breakdown`): whether its false positives were covered
by the masks whole, in part or selected by their neighbours, and how many selected Gaussians
straddle the masks' edge; `--exact` breaks down the exact 2D masks' lift the same way (what even
perfect masks cannot tell apart).

    python scripts/relift.py OUT_OR_TRIAL [--edge-ratios 0 0.5] [--thresholds 0.3 0.4 0.5 0.6 0.7 0.8 0.9] [--grow 1]
    python scripts/relift.py OUT_OR_TRIAL --breakdown [--exact]

No editor runs: a 32-case draw re-lifts in under a minute on 2 cores (about two with 7 thresholds).
"""
import argparse
import glob
import os
import statistics


def trials(path: str) -> list:
    """The trial dirs under a truth-suite OUT (OUT/runs/<case>/<name>@<time>), or `path` itself."""
    if os.path.isfile(os.path.join(path, "save", "localization.npz")):
        return [path]
    found = sorted(glob.glob(os.path.join(path, "runs", "*", "*@*")))
    return [t for t in found if os.path.isfile(os.path.join(t, "save", "localization.npz"))]


def saved_lift(trial: str) -> tuple:
    """What a trial's localization saved, set up again: (its config, its ground truth, the saved
    localization (npz), the renderer it used, the localization's cameras). A trial whose lift
    saved no 2D masks (a given selection, or no lift) stops with its path named."""
    import numpy as np
    import torch

    from gs_regional.bench.launching import trial_truth
    from gs_regional.renderers.select import make_renderer
    from gs_regional.stages.localize import LOCALIZATION_FILE

    cfg, scene = trial_truth(trial)
    saved = np.load(os.path.join(trial, "save", LOCALIZATION_FILE))
    if "masks" not in saved:
        raise SystemExit(f"{trial}: its localization saved no 2D masks (a given selection, or no lift)")
    renderer = make_renderer(cfg.system.renderer_type, cfg.system.get("renderer", {}), torch.device("cpu"))
    return cfg, scene.ground_truth, saved, renderer, [scene.cameras[int(i)] for i in saved["views"]]


def trial_lift(cfg, model, renderer, cameras) -> dict:
    """The keyword arguments of `localize_gaussians` as the trial's config lifts (its views'
    renders as the edge colour test's images)."""
    import torch

    from gs_regional.config import parse_structured
    from gs_regional.stages.localize import LocalizeConfig

    with torch.no_grad():
        images = torch.stack([renderer.render(model, cam)["rgb"].clamp(0, 1) for cam in cameras])
    lc = parse_structured(LocalizeConfig, cfg.system.get("localization", {}), where="system.localization")
    return dict(lc.lift(), images=images)


def relift(trial: str, ratios, thresholds=(), grow: int = 0) -> dict:
    """{ratio: {"masks": mask_metrics of the saved masks' lift, "exact": of the exact masks', with
    `grow` > 0 "grown": of the exact masks grown by that many pixels, and with `thresholds`
    "best_<each of those>": (the best IoU over them, the threshold that gives it)}}."""
    import torch

    from gs_regional.metrics.region import mask_metrics, splat_selection
    from gs_regional.stages.localize import localize_gaussians
    from gs_regional.utils.image import dilate

    cfg, gt, saved, renderer, cameras = saved_lift(trial)
    model = gt.source
    trials_lift = trial_lift(cfg, model, renderer, cameras)
    with torch.no_grad():
        masks = [torch.from_numpy(m) for m in saved["masks"]]
        first = None
        out = {}
        for ratio in ratios:
            lift = dict(trials_lift, edge_ratio=ratio)
            if first is None:  # its pixel weights and neighbourhoods serve every lift below
                first = localize_gaussians(model, renderer, cameras, masks, **lift)
                exact = [splat_selection(v, gt.region) > 0.5 for v in first["views"]]
                sources = [("masks", masks), ("exact", exact)] + ([("grown", [dilate(e, grow) for e in exact])] if grow else [])

            def scored(these, **changed) -> dict:
                return mask_metrics(localize_gaussians(model, renderer, cameras, these, reuse=first, **{**lift, **changed})[
                    "selected"], gt.region)

            out[ratio] = {}
            for name, these in sources:
                out[ratio][name] = scored(these)
                if thresholds:
                    out[ratio][f"best_{name}"] = max((scored(these, threshold=t)["mask_iou"] or 0.0, t) for t in thresholds)
    return out


# A straddler: a selected Gaussian with at least this much rendering weight (pixels, summed over the
# views) on each side of the 2D masks, and between these shares of it inside them.
STRADDLE_MIN_PX = 1.0
STRADDLE_SHARES = (0.2, 0.8)


def breakdown(trial: str, exact: bool = False) -> dict:
    """Where a trial's selection departs from the truth, from its saved 2D masks: its false positives
    (selected, not the truth's) and misses (the truth's, not selected) by the share of their own
    rendering weight the masks cover, before neighbour pooling: "unseen" (no view sees them; they
    took their neighbours' score), "covered" (at least the upper STRADDLE_SHARES inside), "partly"
    (from half), "pooled" (under half: the neighbours' votes decided); and the straddlers
    (selected, STRADDLE_MIN_PX or more on each side, their share inside within STRADDLE_SHARES),
    with how many are the truth's. Counts of Gaussians; and the rendering weight (pixels, summed
    over the views) inside the masks of the false positives and of the truth ("inside_px").
    `exact`: the same of the exact 2D masks' lift (the trial's lift of its known region's render):
    what no mask can tell apart."""
    import torch

    from gs_regional.metrics.region import SEEN_MIN_WEIGHT, splat_selection
    from gs_regional.stages.localize import localize_gaussians, mask_votes, view_weights

    cfg, gt, saved, renderer, cameras = saved_lift(trial)
    model = gt.source
    with torch.no_grad():
        views = view_weights(model, renderer, cameras)
        if exact:
            masks = [splat_selection(v, gt.region) > 0.5 for v in views]
            lift = trial_lift(cfg, model, renderer, cameras)
            # the pixel weights found above serve the lift too (no second render of every view)
            selected = localize_gaussians(model, renderer, cameras, masks, reuse={"views": views}, **lift)["selected"].cpu()
        else:
            masks = [torch.from_numpy(m) for m in saved["masks"]]
            selected = torch.from_numpy(saved["selected"]).bool()
        num, den = mask_votes(views, masks)
    inside, total = num.sum(0).cpu(), den.sum(0).cpu()
    share = torch.where(total > 0, inside / total.clamp_min(1e-12), torch.zeros_like(total))
    truth = gt.region.cpu().bool()
    unseen = total < SEEN_MIN_WEIGHT
    low, high = STRADDLE_SHARES

    def why(rows: torch.Tensor) -> dict:
        seen = rows & ~unseen
        return {"all": int(rows.sum()), "unseen": int((rows & unseen).sum()), "covered": int((seen & (share >= high)).sum()),
                "partly": int((seen & (share >= 0.5) & (share < high)).sum()), "pooled": int((seen & (share < 0.5)).sum())}

    straddle = (selected & (inside >= STRADDLE_MIN_PX) & (total - inside >= STRADDLE_MIN_PX)
                & (share > low) & (share < high))
    return {"false_positives": why(selected & ~truth), "misses": why(~selected & truth),
            "straddlers": {"all": int(straddle.sum()), "truth": int((straddle & truth).sum())},
            "selected": int(selected.sum()), "truth": int(truth.sum()),
            "inside_px": {"false_positives": float(inside[selected & ~truth].sum()), "truth": float(inside[truth].sum())}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("path", help="a truth-suite OUT dir (its runs/) or one trial dir")
    ap.add_argument("--edge-ratios", type=float, nargs="+", default=[0.0, 0.5],
                    help="EDGE_COLOUR_RATIO values to lift with (0: no edge colour test)")
    ap.add_argument("--thresholds", type=float, nargs="+", default=[],
                    help="mask_threshold values each case is also lifted at, keeping its best IoU")
    ap.add_argument("--grow", type=int, default=0, metavar="PX",
                    help="also lift the exact masks grown by PX pixels (masks reaching that far past the part)")
    ap.add_argument("--breakdown", action="store_true",
                    help="instead: where each run's selection departs from the truth (false positives and misses "
                         "by the share of their rendering weight the masks cover; straddlers)")
    ap.add_argument("--exact", action="store_true",
                    help="with --breakdown: of the exact 2D masks' lift instead of the saved masks'")
    args = ap.parse_args(argv)
    found = trials(args.path)
    if not found:
        raise SystemExit(f"{args.path}: no trial with a save/localization.npz")
    if args.breakdown:
        return print_breakdowns(found, args.exact)
    results = []
    for t in found:
        results.append(relift(t, args.edge_ratios, args.thresholds, args.grow))
        print(f"{len(results)}/{len(found)} {t}", flush=True)
    sources = ("masks", "exact") + (("grown",) if args.grow else ())
    names = {"masks": "", "exact": ", exact masks", "grown": f", exact masks grown {args.grow} px"}
    print("| edge ratio | " + " | ".join(f"IoU{names[src]} | precision | recall" for src in sources) + " |\n| --- |"
          + " --- | --- | --- |" * len(sources))
    for ratio in args.edge_ratios:
        med = {(src, key): statistics.median(r[ratio][src][key] or 0.0 for r in results)
               for src in sources for key in ("mask_iou", "mask_precision", "mask_recall")}
        print(f"| {ratio} | " + " | ".join(f"{med[(src, key)]:.3f}" for src in sources
                                         for key in ("mask_iou", "mask_precision", "mask_recall")) + " |")
    for ratio in args.edge_ratios if args.thresholds else ():
        best = {src: [r[ratio][f"best_{src}"] for r in results] for src in sources}
        print(f"edge ratio {ratio}, each case at its best of mask_threshold {args.thresholds}: " + "; ".join(
            f"{src} median IoU {statistics.median(b[0] for b in best[src]):.3f} (its threshold: median "
            f"{statistics.median(b[1] for b in best[src]):.2f}, {min(b[1] for b in best[src]):.2f}-"
            f"{max(b[1] for b in best[src]):.2f})" for src in sources))
    return 0


def print_breakdowns(found: list, exact: bool = False) -> int:
    """`--breakdown` (`--exact`: of the exact masks' lift): a row per trial, then the totals."""
    kinds = ("unseen", "covered", "partly", "pooled")
    print(f"{'exact 2D masks' if exact else 'the saved masks'}, lifted as each trial lifts them")
    print("| trial | selected | truth | false positives: all / " + " / ".join(kinds) + " | misses: all / "
          + " / ".join(kinds) + " | straddlers (the truth's) | px inside the masks: false positives / truth |\n"
          "| --- | --- | --- | --- | --- | --- | --- |")
    totals: dict = {}
    for t in found:
        b = breakdown(t, exact)
        for group in ("false_positives", "misses", "straddlers"):
            for key, value in b[group].items():
                totals[(group, key)] = totals.get((group, key), 0) + value
        fp, miss = b["false_positives"], b["misses"]
        print(f"| {os.path.relpath(t)} | {b['selected']} | {b['truth']} | {fp['all']} / "
              + " / ".join(str(fp[k]) for k in kinds) + f" | {miss['all']} / " + " / ".join(str(miss[k]) for k in kinds)
              + f" | {b['straddlers']['all']} ({b['straddlers']['truth']}) | {b['inside_px']['false_positives']:.1f} / "
              f"{b['inside_px']['truth']:.1f} |", flush=True)
    print(f"totals over {len(found)}: false positives {totals[('false_positives', 'all')]} ("
          + ", ".join(f"{k} {totals[('false_positives', k)]}" for k in kinds) + f"); misses {totals[('misses', 'all')]} ("
          + ", ".join(f"{k} {totals[('misses', k)]}" for k in kinds) + f"); straddlers {totals[('straddlers', 'all')]} "
          f"({totals[('straddlers', 'truth')]} of them the truth's)")
    return 0
