"""Model no more than the scene needs: the Gaussians an edit adds against its quality,
over the densification threshold, the densification budget and the threshold of the pruning after
refinement, one knob at a time with the others at the regional edit's defaults.

    python scripts/compactness.py [--quick] [--out outputs/compactness] [--edits add donut_add] [--replot]

Writes OUT/compactness.json (one record per run: edit, knob, value and the metrics of
save/metrics.json listed in gs_regional/bench/sweeps.py, plus `net_added`; and `knees`: per edit and knob the
knee and whether the default sits there) and OUT/compactness_<edit>.png: the in-region PSNR against
the true edit and the PSNR of the unedited region against `net_added`, the Gaussians the edit leaves
in the scene (gaussians_after - gaussians_before: added from depth and by densification, less those
pruned), one line per knob, the default starred, the true edit's count as a vertical line and doing
nothing as a horizontal one. Prints the table. The launch.py trials land in OUT/runs/.

The knee of a knob: the run with the fewest Gaussians whose in-region PSNR is within KNEE_DB of the
best of that knob's runs (the default included) and whose in-region SSIM is within KNEE_SSIM of
theirs (a PSNR knee alone can hide a loss of structure: the add edit's budget 0 kept the PSNR but
lost 0.02 SSIM). The default sits at the knee when it keeps no more
than KNEE_SLACK x the knee's Gaussians and is itself within those margins of the best.

Full (the default; 14 runs of the synthetic `add` edit, about 15 min on this 2-core CPU, then 7 of
`donut_add`, skipped with a message without ../shared/data/donut): the demo's scene and budget
(40 cameras at 96², 3 cycles x 100 iterations, m 8: the default run is the demo), the
densification threshold at 5e-5 ... 1.5e-3 (default 5e-4), the budget at 0 ... 1000 (default
20000, i.e. no cap here), the pruning threshold at 0 ... 25 pixels of rendered weight (default 1).
The donut (45,624 Gaussians, a run costs several times the synthetic one) gets fewer values per knob.
--quick (a test runs it; about 30 s): the synthetic `add` on 16 cameras at 48², 1x10 (m 3), the
default and one other value per knob.
"""
import os
from typing import Dict, List, Optional

from gs_regional.bench import sweeps
from gs_regional.bench.sweeps import Run, fmt, regional_budget
from gs_regional.systems.regional_edit import RegionalEdit

# knob -> (the override's key, its default (the regional edit's own), its colour in the charts)
_DEFAULTS = RegionalEdit.Config()
KNOBS = {
    "grad_threshold": ("system.densify.grad_threshold", _DEFAULTS.densify.grad_threshold, "tab:blue"),
    "budget": ("system.densify.budget", _DEFAULTS.densify.budget, "tab:orange"),
    "prune_min_weight": ("system.refine.prune_min_weight", _DEFAULTS.refine.prune_min_weight, "tab:green"),
}
# The values swept (the default is the shared default run), from adding a lot to adding nothing.
VALUES = {
    "add": {"grad_threshold": [5e-5, 2e-4, 1e-3, 1.5e-3], "budget": [0, 100, 250, 500, 1000],
            "prune_min_weight": [0.0, 0.1, 5.0, 25.0]},
    "donut_add": {"grad_threshold": [2e-4, 1e-3], "budget": [0, 250], "prune_min_weight": [5.0]},
}
QUICK_VALUES = {"add": {"grad_threshold": [1.5e-3], "budget": [0], "prune_min_weight": [5.0]}}
KNEE_DB = 0.25  # quality within this of the knob's best counts as no loss
KNEE_SSIM = 0.005  # ... and in-region SSIM within this of the knob's best
KNEE_SLACK = 1.1  # the default is at the knee when it keeps at most this x the knee's Gaussians
QUALITY = (("psnr_region_vs_true_edit", "in-region PSNR vs true edit (dB)"),
           ("psnr_unedited", "unedited-region PSNR vs source (dB)"))


def label_of(knob: Optional[str], value) -> str:
    return "default" if knob is None else f"{knob}={value:g}"


def plan(quick: bool, edits: List[str]) -> List[Run]:
    runs = []
    for edit in sweeps.available_edits(edits):
        budget = regional_budget(1, 10, 3) if quick else []  # full: the config's own (the demo's) budget
        runs.append(Run(edit, "regional-edit", "default", budget, {"knob": None, "value": None}, demo_scene=not quick))
        for knob, values in (QUICK_VALUES if quick else VALUES)[edit].items():
            key = KNOBS[knob][0]
            for v in values:
                runs.append(Run(edit, "regional-edit", label_of(knob, v), budget + [f"{key}={v}"],
                                {"knob": knob, "value": v}, demo_scene=not quick))
    return runs


def net_added(r: dict) -> Optional[int]:
    """The Gaussians the edit leaves in the scene: added from depth and by densification, less
    those pruned (comparable to the true edit's `true_gaussians_added`)."""
    if r.get("gaussians_after") is None or r.get("gaussians_before") is None:
        return None
    return r["gaussians_after"] - r["gaussians_before"]


def series(records: List[dict], edit: str, knob: str) -> List[dict]:
    """The runs of `knob` on `edit` (its default run included) that finished, by value."""
    rows = [r for r in records if r["edit"] == edit and not r.get("error")
            and (r["knob"] == knob or r["knob"] is None)]
    return sorted(rows, key=lambda r: KNOBS[knob][1] if r["knob"] is None else r["value"])


def no_loss(rows: List[dict]) -> List[dict]:
    """The rows whose in-region PSNR is within KNEE_DB of the best of `rows` and whose in-region
    SSIM is within KNEE_SSIM of the best (when the rows have SSIMs)."""
    rows = [r for r in rows if r["psnr_region_vs_true_edit"] is not None]
    if not rows:
        return []
    best = max(r["psnr_region_vs_true_edit"] for r in rows)
    ssims = [r.get("ssim_region_vs_true_edit") for r in rows if r.get("ssim_region_vs_true_edit") is not None]
    best_ssim = max(ssims) if ssims else None
    return [r for r in rows if r["psnr_region_vs_true_edit"] >= best - KNEE_DB and (
        best_ssim is None or r.get("ssim_region_vs_true_edit") is None or r["ssim_region_vs_true_edit"] >= best_ssim - KNEE_SSIM)]


def knee(rows: List[dict]) -> Optional[dict]:
    """The run with the fewest Gaussians among those with no loss of quality (`no_loss`)."""
    good = no_loss(rows)
    return min(good, key=lambda r: (r["net_added"], -r["psnr_region_vs_true_edit"])) if good else None


def knees(records: List[dict]) -> Dict[str, Dict[str, dict]]:
    """Per edit and knob: the knee (its value, Gaussians, PSNRs), the best PSNR and whether the
    default sits at the knee."""
    out: Dict[str, Dict[str, dict]] = {}
    for edit in dict.fromkeys(r["edit"] for r in records):
        for knob in KNOBS:
            rows = series(records, edit, knob)
            k = knee(rows)
            default = next((r for r in rows if r["knob"] is None), None)
            if k is None or len(rows) < 2:
                continue
            # At the knee: no loss of quality itself, and at most KNEE_SLACK x the knee's Gaussians.
            at_knee = default is not None and any(r is default for r in no_loss(rows)) and \
                default["net_added"] <= KNEE_SLACK * max(k["net_added"], 0)
            out.setdefault(edit, {})[knob] = {
                "knee_value": KNOBS[knob][1] if k["knob"] is None else k["value"], "knee_label": k["label"],
                "knee_net_added": k["net_added"], "knee_psnr_region": k["psnr_region_vs_true_edit"],
                "knee_psnr_unedited": k["psnr_unedited"], "knee_ssim_region": k["ssim_region_vs_true_edit"],
                "best_psnr_region": max(r["psnr_region_vs_true_edit"] for r in rows
                                        if r["psnr_region_vs_true_edit"] is not None),
                "default_value": KNOBS[knob][1], "default_net_added": None if default is None else default["net_added"],
                "default_psnr_region": None if default is None else default["psnr_region_vs_true_edit"],
                "default_at_knee": at_knee, "swept_values": [KNOBS[knob][1] if r["knob"] is None else r["value"] for r in rows],
            }
    return out


def chart(records: List[dict], edit: str, path: str) -> None:
    plt = sweeps.pyplot()
    fig, axes = plt.subplots(1, len(QUALITY), figsize=(12, 5), squeeze=False)
    mine = [r for r in records if r["edit"] == edit and not r.get("error")]
    default = next((r for r in mine if r["knob"] is None), None)
    for ax, (qkey, qlabel) in zip(axes[0], QUALITY):
        for knob, (_, _, color) in KNOBS.items():
            rows = series(mine, edit, knob)
            pts = [(r["net_added"], r[qkey], r["label"]) for r in rows if r[qkey] is not None]
            if len(pts) < 2:
                continue
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", color=color, label=knob, alpha=0.8)
            k = knee(rows)
            if k is not None and k[qkey] is not None:  # ringed: the knee of this knob
                ax.scatter([k["net_added"]], [k[qkey]], s=220, facecolors="none", edgecolors=color, linewidths=2, zorder=4)
            for x, y, label in pts:
                if label != "default":
                    ax.annotate(label.split("=")[1], (x, y), fontsize=7, color=color, xytext=(3, 3), textcoords="offset points")
        if default is not None and default[qkey] is not None:
            ax.scatter([default["net_added"]], [default[qkey]], marker="*", s=250, color="black", zorder=4, label="default")
        truth = next((r["true_gaussians_added"] for r in mine if r.get("true_gaussians_added") is not None), None)
        if truth is not None:
            ax.axvline(truth, color="grey", ls=":", label=f"true edit ({truth} added)")
            ax.axvline(1.1 * truth, color="grey", ls="-.", alpha=0.5, label="1.1 x true edit")
        if qkey == "psnr_region_vs_true_edit":
            nothing = next((r["psnr_region_source_vs_true_edit"] for r in mine
                            if r["psnr_region_source_vs_true_edit"] is not None), None)
            if nothing is not None:
                ax.axhline(nothing, color="grey", ls="--", label="doing nothing")
        ax.set_xlabel("Gaussians the edit leaves in the scene (added - pruned)")
        ax.set_ylabel(qlabel)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(f"Gaussians added against quality: {edit} edit (simulated editor; one knob at a time, the others at their "
                 f"defaults; ringed: each knob's knee)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None) -> int:
    ap = sweeps.arg_parser(__doc__, "compactness.json")
    ap.add_argument("--edits", nargs="+", default=None, choices=sorted(VALUES),
                    help="which edits (default: add for --quick, else add donut_add)")
    args = ap.parse_args(argv)
    edits = args.edits or (["add"] if args.quick else ["add", "donut_add"])
    if args.quick and edits != ["add"]:
        ap.error("--quick sweeps the synthetic add edit only")
    header = {"quick": args.quick, "scene": sweeps.scene_overrides(args.quick, demo_scene=not args.quick),
              "knee_db": KNEE_DB, "knee_slack": KNEE_SLACK}
    records = sweeps.records_for(args, lambda: plan(args.quick, edits), "compactness.json", header)
    for r in records:
        r["net_added"] = net_added(r)
    table = knees(records)
    sweeps.write_json(os.path.join(args.out, "compactness.json"), {**header, "knees": table, "records": records})
    for edit in dict.fromkeys(r["edit"] for r in records):
        chart(records, edit, os.path.join(args.out, f"compactness_{edit}.png"))
    sweeps.print_table(
        records, ["edit", "run", "added - pruned = left (true edit)", "in-region PSNR (doing nothing)", "in-region SSIM",
                  "unedited PSNR", "edit s"], ["edit", "label"],
        lambda r: [f"{r['gaussians_added']} - {r['gaussians_pruned']} = {r['net_added']} ({r['true_gaussians_added']})",
                   f"{fmt(r['psnr_region_vs_true_edit'])} ({fmt(r['psnr_region_source_vs_true_edit'])})",
                   ssim(r["ssim_region_vs_true_edit"]), fmt(r["psnr_unedited"]), f"{r['edit_seconds']:.1f}"])
    print(f"\nknee per knob: the fewest Gaussians within {KNEE_DB} dB of the knob's best in-region PSNR and "
          f"{KNEE_SSIM} of its best SSIM:\n")
    print("| edit | knob | knee | its Gaussians, PSNR | default | its Gaussians, PSNR | default at the knee? |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for edit, row in table.items():
        for knob, k in row.items():
            print(f"| {edit} | {knob} | {k['knee_value']:g} | {k['knee_net_added']}, {fmt(k['knee_psnr_region'])} | "
                  f"{k['default_value']:g} | {k['default_net_added']}, {fmt(k['default_psnr_region'])} | "
                  f"{'yes' if k['default_at_knee'] else 'no'} |")
    return 0


def ssim(x) -> str:
    return "n/a" if x is None else f"{x:.3f}"
