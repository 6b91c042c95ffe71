"""Which Gaussians an edit run changed, against its known truth: for a trial of a scene with a
ground truth (`synthetic-scene`, `splat-truth`: the truth suite's cases, the demo), the source
Gaussians still editable at the end (save/edit_mask.npz) inside and outside the true region, how
many of them changed colour, and their colour error against the true edit; and the true region's
Gaussians the edit left out. A recolour's loss outside the true footprint shows here as changed
Gaussians outside the region; with each group the band of the recolour gate's blend (the
10th/50th/90th percentile of save/edit_mask.npz `gate_blend`): where the rows it took outside the
region and those it declined inside overlap, no threshold of the blend tells them apart.

    python scripts/changed_gaussians.py TRIAL_DIR [--min-change 0.02]
"""
import argparse
import os
from typing import List, Optional


def report(trial: str, min_change: float = 0.02) -> dict:
    from pathlib import Path

    import torch

    from gs_regional.bench.launching import trial_truth
    from gs_regional.geometry.gaussian_model import GaussianModel
    from gs_regional.launch.view import read_edit_rows
    from gs_regional.utils.sh import sh_to_rgb

    gt = trial_truth(trial)[1].ground_truth
    out = GaussianModel.from_ply(os.path.join(trial, "save", "edited.ply"))
    rows, where = read_edit_rows(Path(trial), out.num_gaussians)
    if rows is None:
        raise SystemExit(f"{trial}: {where}")
    kept = torch.as_tensor(rows["generation"]) == 0  # source rows (added ones have no source colour)
    src = torch.as_tensor(rows["source_index"])[kept]
    editable = torch.as_tensor(rows["mask"]).bool()[kept]
    rgb = sh_to_rgb(out.sh_dc.detach())[kept]
    rgb_source = sh_to_rgb(gt.source.sh_dc.detach())[src]
    # The true edit's colours of the source rows (an addition appends its object after them).
    rgb_true = sh_to_rgb(gt.edited.sh_dc.detach())[: len(gt.source)][src]
    region = gt.region[src]
    changed = (rgb - rgb_source).abs().max(1).values > min_change
    error = (rgb - rgb_true).abs().mean(1)
    groups = {"editable, in the true region": editable & region, "editable, outside it": editable & ~region,
              "in the true region, left out": ~editable & region}
    blend = rows.get("gate_blend")  # a recolour's, over the source's rows (None: an addition)
    blend = None if blend is None else torch.from_numpy(blend)[src]

    def band(m: torch.Tensor) -> Optional[List[float]]:
        """The gate's blend of the rows `m` it judged: 10th, 50th and 90th percentile."""
        if blend is None:
            return None
        judged = blend[m & ~blend.isnan()]
        return [round(float(v), 2) for v in judged.quantile(torch.tensor([0.1, 0.5, 0.9]))] if judged.numel() else []

    return {name: {"gaussians": int(m.sum()), "changed colour": int((changed & m).sum()),
                   "mean colour error vs truth": round(float(error[m].mean()), 4) if m.any() else None,
                   "gate blend": band(m)}
            for name, m in groups.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("trial", help="a trial dir of an edit run (with configs/parsed.yaml and save/)")
    ap.add_argument("--min-change", type=float, default=0.02, help="largest RGB change that counts as unchanged")
    args = ap.parse_args(argv)
    print(f"| {args.trial} | Gaussians | changed colour | mean colour error vs truth | the gate's blend (10/50/90 %) |\n"
          "| --- | --- | --- | --- | --- |")
    for name, r in report(args.trial, args.min_change).items():
        band = "-" if r["gate blend"] is None else " / ".join(f"{v:.2f}" for v in r["gate blend"]) or "none judged"
        print(f"| {name} | {r['gaussians']} | {r['changed colour']} | {r['mean colour error vs truth']} | {band} |")
    return 0
