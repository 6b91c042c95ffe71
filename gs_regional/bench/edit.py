"""Speed and quality of `regional-edit` against the whole-scene `in2n` baseline on the synthetic
`add` edit with the simulated editor (CPU). Each run is a full `launch.py` run; the numbers come
from its save/metrics.json.

    python scripts/bench_edit.py [--in2n-steps 300 600 1200] [--out outputs/bench_edit]

For each method it prints wall seconds per stage and in total, the UNet evaluations a real
InstructPix2Pix would spend on the same schedule (the simulator counts them as IP2P would), the
PSNR against the true edited scene on held-out views and the PSNR of the unedited region. The
in2n baseline is run at several step counts to find the cost at which it matches regional-edit's
PSNR against the truth.
"""
import argparse
import json
import os

from gs_regional.bench.launching import ROOT, run


def row(label: str, m: dict) -> str:
    stages = ", ".join(f"{k} {v:.1f}" for k, v in m["seconds"].items())
    return (f"| {label} | {m['seconds_total']:.1f} | {m['unet_evals']} | {m['psnr_vs_true_edit']:.2f} | "
            f"{m['psnr_unedited']:.2f} | {m['gaussians_after']} | {stages} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.path.join(ROOT, "outputs", "bench_edit"))
    ap.add_argument("--in2n-steps", type=int, nargs="+", default=[300, 600, 1200])
    ap.add_argument("extra", nargs="*", help="overrides applied to every run (key=value)")
    args = ap.parse_args(argv)
    results = {"regional-edit": run(args.out, "regional", "configs/demo.yaml", *args.extra)}
    for steps in args.in2n_steps:
        results[f"in2n {steps} steps"] = run(args.out, f"in2n{steps}", "configs/in2n.yaml", f"system.max_steps={steps}", *args.extra)
    print("\n| method | seconds (all stages) | UNet evals (IP2P) | PSNR vs true edit | PSNR unedited | Gaussians | seconds per stage |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for label, m in results.items():
        print(row(label, m))
    ours = results["regional-edit"]
    matching = [(k, m) for k, m in results.items() if k != "regional-edit" and m["psnr_vs_true_edit"] >= ours["psnr_vs_true_edit"]]
    if matching:
        k, m = min(matching, key=lambda km: km[1]["seconds_total"])
        print(f"\ncheapest in2n run at >= regional-edit's PSNR vs truth: {k}: "
              f"{m['seconds_total'] / ours['seconds_total']:.1f}x the seconds, "
              f"{m['unet_evals'] / max(ours['unet_evals'], 1):.1f}x the UNet evaluations")
    else:
        best = max((m for k, m in results.items() if k != "regional-edit"), key=lambda m: m["psnr_vs_true_edit"])
        print(f"\nno in2n run reached regional-edit's PSNR vs truth ({ours['psnr_vs_true_edit']:.2f} dB); "
              f"best in2n: {best['psnr_vs_true_edit']:.2f} dB at {best['seconds_total']:.1f} s "
              f"({best['seconds_total'] / ours['seconds_total']:.1f}x the seconds, "
              f"{best['unet_evals'] / max(ours['unet_evals'], 1):.1f}x the UNet evaluations)")
    with open(os.path.join(args.out, "bench_edit.json"), "w") as f:
        json.dump(results, f, indent=2)
    return 0
