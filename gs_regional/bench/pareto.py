"""Speed against accuracy: the regional edit at several budgets, the whole-scene in2n
baseline at several step counts and the ablations of the method's parts, on known edits, charted
as quality against cost with the Pareto front of each method.

    python scripts/pareto.py [--quick] [--out outputs/pareto] [--edits add recolor ...]

Writes OUT/pareto.json (one record per run: edit, method, settings and the metrics of
save/metrics.json listed in gs_regional/bench/sweeps.py) and OUT/pareto_<edit>.png: in-region PSNR against
the true edit and PSNR of the unedited region (against the source), each against the edit's wall
seconds (every stage but writing the outputs; noisy on a shared CPU) and against the UNet
evaluations a real InstructPix2Pix would spend. The dashed line is doing nothing. The launch.py
trials land in OUT/runs/.

Full (the default; 39 runs, about 30 min on this 2-core CPU): the synthetic `recolor`, `add` and
`global` edits with the regional edit at 1x30 (m 4), 2x40 (m 6), 3x40 (m 6) and 3x100 (m 8, the
demo's budget) cycles x iterations, in2n at 100/300/600 steps and the four ablations at 3x40 (m 6);
the donut truths (`configs/donut_recolor.yaml`, `donut_add.yaml`; 45,624 Gaussians, skipped with a
message without ../shared/data/donut) with the regional edit at 1x30 and 3x40 and in2n at 300 steps
only (a donut run costs several times a synthetic one here). Every run uses 24 cameras at 64²
(gs_regional/bench/sweeps.py).
--quick (a test runs it; about 30 s): the synthetic `add` only, 16 cameras at 48², the regional
edit at 1x10 (m 3) and 2x15 (m 4), in2n at 40 steps, the plain vote at 1x10.
"""
import os
from typing import List

from gs_regional.bench import sweeps
from gs_regional.bench.sweeps import ABLATIONS, METHOD_COLORS, Run, fmt, regional_budget

QUALITY = (("psnr_region_vs_true_edit", "in-region PSNR vs true edit (dB)"),
           ("psnr_unedited", "unedited-region PSNR vs source (dB)"))
COST = (("edit_seconds", "wall seconds of the edit"), ("unet_evals", "UNet evaluations (IP2P)"))


def budget_label(cycles: int, iterations: int, m: int) -> str:
    return f"{cycles}x{iterations} m{m}"


def plan(quick: bool, edits: List[str]) -> List[Run]:
    runs = []
    for edit in sweeps.available_edits(edits):
        donut = edit.startswith("donut")
        if quick:
            budgets, ref, steps = [(1, 10, 3), (2, 15, 4)], (1, 10, 3), [40]
            ablations = {"plain-vote": ABLATIONS["plain-vote"]}
        elif donut:
            budgets, ref, steps, ablations = [(1, 30, 4), (3, 40, 6)], (3, 40, 6), [300], {}
        else:
            budgets = [(1, 30, 4), (2, 40, 6), (3, 40, 6), (3, 100, 8)]
            ref, steps, ablations = (3, 40, 6), [100, 300, 600], ABLATIONS
        for b in budgets:
            runs.append(Run(edit, "regional-edit", budget_label(*b), regional_budget(*b)))
        for n in steps:
            runs.append(Run(edit, "in2n", f"{n} steps", [f"system.max_steps={n}"]))
        for name, overrides in ablations.items():
            runs.append(Run(edit, name, budget_label(*ref), regional_budget(*ref) + overrides))
    return runs


def chart(records: List[dict], edit: str, path: str) -> None:
    plt = sweeps.pyplot()
    fig, axes = plt.subplots(len(QUALITY), len(COST), figsize=(11, 8), squeeze=False)
    mine = [r for r in records if r["edit"] == edit]
    for row, (qkey, qlabel) in enumerate(QUALITY):
        for col, (ckey, clabel) in enumerate(COST):
            ax = axes[row][col]
            for method, color in METHOD_COLORS.items():
                pts = [(r[ckey], r[qkey]) for r in mine
                       if r["method"] == method and r[qkey] is not None and r[ckey] is not None]
                if not pts:
                    continue
                ax.scatter(*zip(*pts), color=color, label=method, zorder=3)
                if len(pts) > 1:
                    front = sweeps.pareto_front(pts)
                    ax.step(*zip(*front), where="post", color=color, alpha=0.6)
            if qkey == "psnr_region_vs_true_edit":
                nothing = [r["psnr_region_source_vs_true_edit"] for r in mine if r["psnr_region_source_vs_true_edit"] is not None]
                if nothing:
                    ax.axhline(nothing[0], color="grey", ls="--", label="doing nothing")
            ax.set_xlabel(clabel)
            ax.set_ylabel(qlabel)
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(f"speed against accuracy: {edit} edit (simulated editor; one marker per run, lines: Pareto fronts)")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None) -> int:
    ap = sweeps.arg_parser(__doc__, "pareto.json")
    ap.add_argument("--edits", nargs="+", default=None,
                    help="which edits (default: add for --quick, else recolor add global donut_recolor donut_add)")
    args = ap.parse_args(argv)
    edits = args.edits or (["add"] if args.quick else ["recolor", "add", "global", "donut_recolor", "donut_add"])
    unknown = [e for e in edits if e not in sweeps.EDITS]
    if unknown:
        ap.error(f"unknown edit(s) {unknown}; known: {', '.join(sweeps.EDITS)}")
    header = {"quick": args.quick, "scene": sweeps.scene_overrides(args.quick)}
    records = sweeps.records_for(args, lambda: plan(args.quick, edits), "pareto.json", header)
    for edit in dict.fromkeys(r["edit"] for r in records):
        chart(records, edit, os.path.join(args.out, f"pareto_{edit}.png"))
    sweeps.print_table(
        records, ["edit", "method", "settings", "edit s", "UNet evals", "in-region PSNR (doing nothing)", "unedited PSNR",
                  "Gaussians added"], ["edit", "method", "label"],
        lambda r: [f"{r['edit_seconds']:.1f}", str(r["unet_evals"]),
                   f"{fmt(r['psnr_region_vs_true_edit'])} ({fmt(r['psnr_region_source_vs_true_edit'])})",
                   fmt(r["psnr_unedited"]), str(r["gaussians_added"])])
    return 0
