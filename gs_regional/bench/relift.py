"""The lift of saved localizations again, with its edge colour test at other ratios: for each trial
of a truth-suite output (or one trial), the 2D masks its localization saved (save/localization.npz)
and exact 2D masks of its known region, lifted as the trial's config lifts them but with
`EDGE_COLOUR_RATIO` replaced; the median mask IoU, precision and recall of each ratio. With
`--thresholds`, each case is also lifted at each of those `mask_threshold`s and keeps its best IoU:
the median of those bests says how far the lift's bias alone could take the IoU (were each case
given its own), apart from what the masks themselves get wrong.

    python scripts/relift.py OUT_OR_TRIAL [--edge-ratios 0 0.5] [--thresholds 0.3 0.4 0.5 0.6 0.7 0.8 0.9]

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


def relift(trial: str, ratios, thresholds=()) -> dict:
    """{ratio: {"masks": mask_metrics of the saved masks' lift, "exact": of the exact masks', and with
    `thresholds` "best_masks" / "best_exact": (the best IoU over them, the threshold that gives it)}}."""
    import numpy as np
    import torch

    from gs_regional.bench.launching import trial_truth
    from gs_regional.config import parse_structured
    from gs_regional.metrics.region import mask_metrics, splat_selection
    from gs_regional.renderers.select import make_renderer
    from gs_regional.stages.localize import LOCALIZATION_FILE, LocalizeConfig, localize_gaussians

    cfg, scene = trial_truth(trial)
    gt = scene.ground_truth
    saved = np.load(os.path.join(trial, "save", LOCALIZATION_FILE))
    if "masks" not in saved:
        raise SystemExit(f"{trial}: its localization saved no 2D masks (a given selection, or no lift)")
    renderer = make_renderer(cfg.system.renderer_type, cfg.system.get("renderer", {}), torch.device("cpu"))
    cameras = [scene.cameras[int(i)] for i in saved["views"]]
    model = gt.source
    with torch.no_grad():
        images = torch.stack([renderer.render(model, cam)["rgb"].clamp(0, 1) for cam in cameras])
        masks = [torch.from_numpy(m) for m in saved["masks"]]
        lc = parse_structured(LocalizeConfig, cfg.system.get("localization", {}), where="system.localization")
        first = None
        out = {}
        for ratio in ratios:
            lift = dict(lc.lift(), edge_ratio=ratio, images=images)
            if first is None:  # its pixel weights and neighbourhoods serve every lift below
                first = localize_gaussians(model, renderer, cameras, masks, **lift)
                exact = [splat_selection(v, gt.region) > 0.5 for v in first["views"]]

            def scored(these, **changed) -> dict:
                return mask_metrics(localize_gaussians(model, renderer, cameras, these, reuse=first, **{**lift, **changed})[
                    "selected"], gt.region)

            out[ratio] = {}
            for name, these in (("masks", masks), ("exact", exact)):
                out[ratio][name] = scored(these)
                if thresholds:
                    out[ratio][f"best_{name}"] = max((scored(these, threshold=t)["mask_iou"] or 0.0, t) for t in thresholds)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("path", help="a truth-suite OUT dir (its runs/) or one trial dir")
    ap.add_argument("--edge-ratios", type=float, nargs="+", default=[0.0, 0.5],
                    help="EDGE_COLOUR_RATIO values to lift with (0: no edge colour test)")
    ap.add_argument("--thresholds", type=float, nargs="+", default=[],
                    help="mask_threshold values each case is also lifted at, keeping its best IoU")
    args = ap.parse_args(argv)
    found = trials(args.path)
    if not found:
        raise SystemExit(f"{args.path}: no trial with a save/localization.npz")
    results = []
    for t in found:
        results.append(relift(t, args.edge_ratios, args.thresholds))
        print(f"{len(results)}/{len(found)} {t}", flush=True)
    print("| edge ratio | IoU | precision | recall | IoU, exact masks | precision | recall |\n| --- | --- | --- | --- | --- | --- | --- |")
    for ratio in args.edge_ratios:
        med = {(src, key): statistics.median(r[ratio][src][key] or 0.0 for r in results)
               for src in ("masks", "exact") for key in ("mask_iou", "mask_precision", "mask_recall")}
        print(f"| {ratio} | " + " | ".join(f"{med[(src, key)]:.3f}" for src in ("masks", "exact")
                                         for key in ("mask_iou", "mask_precision", "mask_recall")) + " |")
    for ratio in args.edge_ratios if args.thresholds else ():
        best = {src: [r[ratio][f"best_{src}"] for r in results] for src in ("masks", "exact")}
        print(f"edge ratio {ratio}, each case at its best of mask_threshold {args.thresholds}: " + "; ".join(
            f"{src} median IoU {statistics.median(b[0] for b in best[src]):.3f} (its threshold: median "
            f"{statistics.median(b[1] for b in best[src]):.2f}, {min(b[1] for b in best[src]):.2f}-"
            f"{max(b[1] for b in best[src]):.2f})" for src in ("masks", "exact")))
    return 0
