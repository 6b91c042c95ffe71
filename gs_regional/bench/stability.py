"""Where each method breaks: the severity of each failure mode of the simulated
editor and depth (gs_regional/sim/) swept from none to beyond realistic, one mode at a time with
the others at their defaults, on the synthetic `add` edit; plus an instruction whose region is
empty and a global one.

    python scripts/stability.py [--quick] [--out outputs/stability]

Writes OUT/stability.json (one record per run: mode, severity, method, settings and the metrics
of save/metrics.json, plus `breaks`: per mode and method the first severity at which the in-region
PSNR against the true edit falls below doing nothing + 1 dB), OUT/stability_region.png and
OUT/stability_unedited.png (in-region PSNR vs the true edit, and PSNR of the unedited region vs
the source, against severity; a hollow marker is a run that stopped and wrote the source
unchanged), and prints the table. The launch.py trials land in OUT/runs/.

Methods: the regional edit (3x40 steps, m 6), in2n (150 steps, a dataset edit every 3), and the
ablation the relevance modes attack, the paper's plain vote; the run without depth initialization
is the reference of the depth modes. A method that never calls the failing part (in2n has no
relevance and no depth, no-depth-init no depth) is not re-run: its default run is drawn flat and
the table says "not affected". (The other ablations are in scripts/pareto.py; running them under
every mode would not fit the 30 minutes.)

Full (the default; 78 runs, 17-30 min on this 2-core CPU): 10 modes x 5 severities, 24 cameras at
64², except the depth modes: on the demo's 40 cameras at 96² (at 64² the moustache is too thin for
the simulated depth to see it in the first edited view, so initialization adds next to nothing).
--quick (a test runs it; about 40 s): `leakage` at 3 severities for the regional edit at 1x10,
in2n (40 steps) and the empty instruction, 16 cameras at 48².
"""
import os
from typing import Dict, List, Optional

from gs_regional.bench import sweeps
from gs_regional.bench.sweeps import ABLATIONS, METHOD_COLORS, Run, fmt, regional_budget

G, D = "system.guidance", "system.depth"
# mode -> (the part of the pipeline it corrupts, [(severity label, overrides)], index of the default).
# Severities run from none to beyond anything realistic.
MODES = {
    "side_miss": ("relevance", [
        ("none", [f"{G}.side_miss_start=180", f"{G}.side_miss_end=180"]),
        ("60-110°", [f"{G}.side_miss_start=60", f"{G}.side_miss_end=110"]),
        ("40-80°", [f"{G}.side_miss_start=40", f"{G}.side_miss_end=80"]),
        ("20-50°", [f"{G}.side_miss_start=20", f"{G}.side_miss_end=50"]),
        ("0-20°", [f"{G}.side_miss_start=0", f"{G}.side_miss_end=20"]),
    ], 1),
    "leakage": ("relevance", [(str(v), [f"{G}.leakage={v}"]) for v in (0, 0.35, 0.7, 1.0, 1.5)], 1),
    "relevance_noise": ("relevance", [(str(v), [f"{G}.noise={v}"]) for v in (0, 0.1, 0.3, 0.6, 1.0)], 1),
    "relevance_blur": ("relevance", [(str(v), [f"{G}.blur={v}"]) for v in (0, 1.5, 3, 6, 12)], 1),
    "color_jitter": ("edit", [(str(v), [f"{G}.color_jitter={v}"]) for v in (0, 0.06, 0.15, 0.3, 0.6)], 1),
    "position_jitter": ("edit", [(str(v), [f"{G}.position_jitter={v}"]) for v in (0, 1.5, 4, 8, 16)], 1),
    "regen_drift": ("edit", [(str(v), [f"{G}.regen_drift={v}"]) for v in (0, 0.03, 0.1, 0.2, 0.4)], 1),
    "depth_noise": ("depth", [(str(v), [f"{D}.noise={v}"]) for v in (0, 0.01, 0.05, 0.15, 0.5)], 1),
    "depth_outliers": ("depth", [(str(v), [f"{D}.outliers={v}"]) for v in (0, 0.005, 0.05, 0.2, 0.5)], 1),
    "depth_bias": ("depth", [(str(v), [f"{D}.edit_scale_bias={v}"]) for v in (0, 0.25, 0.5, 1.0, 2.0)], 0),
}
QUICK_MODES = {"leakage": ("relevance", [(str(v), [f"{G}.leakage={v}"]) for v in (0, 0.35, 1.5)], 1)}
# Which parts each method calls, and which methods each kind of mode is run for.
USES = {"regional-edit": {"relevance", "edit", "depth"}, "plain-vote": {"relevance", "edit", "depth"},
        "constant-t": {"relevance", "edit", "depth"}, "no-depth-init": {"relevance", "edit"}, "in2n": {"edit"}}
RUN_FOR = {"relevance": ["regional-edit", "plain-vote"], "edit": ["regional-edit", "in2n"], "depth": ["regional-edit"]}
DRAWN_FOR = {"relevance": ["in2n"], "edit": [], "depth": ["no-depth-init"]}  # flat: not affected
# Kinds swept on the demo's scene (40 cameras at 96²) in the full sweep: at 64² the thin moustache
# is a pixel or two wide, the first full edit's position jitter moves it off its true pixels, the
# simulated depth sees no new geometry there and initialization adds next to nothing to corrupt.
DEMO_SCENE_KINDS = {"depth"}
SCENARIOS = {"empty": ["regional-edit", "plain-vote", "in2n"], "global": ["regional-edit", "in2n"]}


def method_overrides(method: str, quick: bool) -> List[str]:
    if method == "in2n":
        return ["system.max_steps=40"] if quick else ["system.max_steps=150", "system.edit_every=3"]
    budget = regional_budget(1, 10, 3) if quick else regional_budget(3, 40, 6)
    return budget + ABLATIONS.get(method, [])


def plan(quick: bool) -> List[Run]:
    modes = QUICK_MODES if quick else MODES
    run_for = {"relevance": ["regional-edit"]} if quick else RUN_FOR
    drawn_for = {"relevance": ["in2n"]} if quick else DRAWN_FOR
    scenarios = {"empty": ["regional-edit"]} if quick else SCENARIOS
    runs = []
    for demo in (False, True):
        kinds = {k for k, _, _ in modes.values() if (k in DEMO_SCENE_KINDS and not quick) == demo}
        baselines = {m for k in kinds for m in run_for[k] + drawn_for.get(k, [])}
        runs += [Run("add", m, base_mode(demo), method_overrides(m, quick), {"mode": base_mode(demo), "severity": None},
                     demo_scene=demo) for m in METHOD_COLORS if m in baselines]
    for mode, (kind, steps, default) in modes.items():
        for method in run_for[kind]:
            for i, (label, overrides) in enumerate(steps):
                if i != default:
                    runs.append(Run("add", method, f"{mode}={label}", method_overrides(method, quick) + overrides,
                                    {"mode": mode, "severity": label}, demo_scene=on_demo_scene(kind, quick)))
    for edit, methods in scenarios.items():
        for method in methods:
            runs.append(Run(edit, method, "default", method_overrides(method, quick),
                            {"mode": f"{edit} instruction", "severity": None}))
    return runs


def on_demo_scene(kind: str, quick: bool) -> bool:
    return kind in DEMO_SCENE_KINDS and not quick


def base_mode(demo_scene: bool) -> str:
    """The `mode` of the default runs (one set per scene)."""
    return "default on the demo scene" if demo_scene else "default"


def series(records: List[dict], mode: str, method: str, quick: bool) -> Optional[List[Optional[dict]]]:
    """The records of `method` along the severities of `mode` (the default run at the default
    severity; the default run everywhere for a method the mode does not affect), or None if the
    method is neither run nor drawn for this mode."""
    modes = QUICK_MODES if quick else MODES
    kind, steps, default = modes[mode]
    home = base_mode(on_demo_scene(kind, quick))
    base = next((r for r in records if r["edit"] == "add" and r["method"] == method and r["mode"] == home), None)
    if base is None:
        return None
    if kind not in USES[method]:
        return [base] * len(steps)
    by_label = {r["severity"]: r for r in records if r["method"] == method and r["mode"] == mode}
    if not by_label:  # affected, but not run under this mode
        return None
    return [base if i == default else by_label.get(label) for i, (label, _) in enumerate(steps)]


def breaks(records: List[dict], quick: bool) -> Dict[str, Dict[str, str]]:
    """Per mode and method: the first severity at which the in-region PSNR vs the true edit falls
    below doing nothing + 1 dB ("holds" if never)."""
    modes = QUICK_MODES if quick else MODES
    table: Dict[str, Dict[str, str]] = {}
    for mode, (kind, steps, _) in modes.items():
        for method in METHOD_COLORS:
            s = series(records, mode, method, quick)
            if s is None:
                continue
            verdict = "holds"
            for (label, _), r in zip(steps, s):
                if r is not None and fails(r):
                    verdict = f"{label}" + (" (stopped)" if r.get("stopped") else " (error)" if r.get("error") else "")
                    break
            if kind not in USES[method]:
                verdict = f"not affected ({'holds' if verdict == 'holds' else 'below at default'})"
            table.setdefault(mode, {})[method] = verdict
    return table


def fails(r: dict) -> bool:
    q, nothing = r["psnr_region_vs_true_edit"], r["psnr_region_source_vs_true_edit"]
    return q is None or nothing is None or q < nothing + 1.0


def chart(records: List[dict], quick: bool, key: str, ylabel: str, path: str) -> None:
    plt = sweeps.pyplot()
    modes = QUICK_MODES if quick else MODES
    cols = min(len(modes), 5)
    rows = (len(modes) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(max(3.6 * cols, 9), 3.2 * rows + 0.8), squeeze=False)
    for ax, (mode, (kind, steps, default)) in zip(axes.flat, modes.items()):
        xs = list(range(len(steps)))
        for method, color in METHOD_COLORS.items():
            s = series(records, mode, method, quick)
            if s is None:
                continue
            pts = [(x, r[key], bool(r.get("stopped"))) for x, r in zip(xs, s) if r is not None and r[key] is not None]
            if not pts:
                continue
            flat = kind not in USES[method]
            ax.plot([p[0] for p in pts], [p[1] for p in pts], color=color, ls=":" if flat else "-",
                    label=method + (" (not affected)" if flat else ""))
            for x, y, stopped in pts:
                ax.scatter([x], [y], color=color, facecolors="none" if stopped else color, zorder=3, s=25)
        demo = on_demo_scene(kind, quick)
        if key == "psnr_region_vs_true_edit":
            nothing = [r["psnr_region_source_vs_true_edit"] for r in records if r["mode"] == base_mode(demo)
                       and r["psnr_region_source_vs_true_edit"] is not None]
            if nothing:
                ax.axhline(nothing[0] + 1.0, color="grey", ls="--", label="doing nothing + 1 dB")
        ax.set_xticks(xs)
        ax.set_xticklabels([f"{label}*" if i == default else label for i, (label, _) in enumerate(steps)], fontsize=8)
        ax.set_title(f"{mode} ({kind}{', 96² scene' if demo else ''})", fontsize=10)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(modes):]:
        ax.axis("off")
    handles, labels = {}, {}
    for ax in axes.flat:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.legend(list(handles.values()), list(handles.keys()), loc="lower center", ncol=4, fontsize=8)
    fig.suptitle(f"{ylabel} against severity, synthetic add edit (* default; hollow: stopped, source written unchanged)",
                 fontsize=10)
    fig.tight_layout(rect=(0, 0.06, 1, 0.97))
    fig.savefig(path, dpi=80)
    plt.close(fig)


def scenario_rows(records: List[dict]) -> List[str]:
    rows = []
    for r in records:
        if not r["mode"].endswith("instruction"):
            continue
        if r.get("error"):
            rows.append(f"| {r['mode']} | {r['method']} | failed: {r['error']} | | |")
            continue
        if r["edit"] == "empty":  # the right answer is no change: the whole view is unedited region
            verdict = "stopped, source unchanged" if r.get("stopped") else "edited"
            rows.append(f"| {r['mode']} | {r['method']} | {verdict} | unedited PSNR {fmt(r['psnr_unedited'])} | "
                        f"{'; '.join(w[:90] for w in r['warnings']) or '-'} |")
        else:
            verdict = "below doing nothing + 1 dB" if fails(r) else "above doing nothing + 1 dB"
            rows.append(f"| {r['mode']} | {r['method']} | {verdict} | in-region PSNR {fmt(r['psnr_region_vs_true_edit'])} "
                        f"(doing nothing {fmt(r['psnr_region_source_vs_true_edit'])}) | "
                        f"{'; '.join(w[:90] for w in r['warnings']) or '-'} |")
    return rows


def main(argv=None) -> int:
    ap = sweeps.arg_parser(__doc__, "stability.json")
    args = ap.parse_args(argv)
    header = {"quick": args.quick, "scene": sweeps.scene_overrides(args.quick)}
    records = sweeps.records_for(args, lambda: plan(args.quick), "stability.json", header)
    table = breaks(records, args.quick)
    sweeps.write_json(os.path.join(args.out, "stability.json"), {**header, "breaks": table, "records": records})
    chart(records, args.quick, "psnr_region_vs_true_edit", "in-region PSNR vs true edit (dB)",
          os.path.join(args.out, "stability_region.png"))
    chart(records, args.quick, "psnr_unedited", "unedited-region PSNR vs source (dB)",
          os.path.join(args.out, "stability_unedited.png"))
    methods = [m for m in METHOD_COLORS if any(m in row for row in table.values())]
    print("\nfirst severity at which the in-region PSNR vs the true edit falls below doing nothing + 1 dB:\n")
    print("| mode | " + " | ".join(methods) + " |")
    print("| --- |" + " --- |" * len(methods))
    for mode, row in table.items():
        print(f"| {mode} | " + " | ".join(row.get(m, "-") for m in methods) + " |")
    print("\n| instruction | method | outcome | score | warnings |\n| --- | --- | --- | --- | --- |")
    print("\n".join(scenario_rows(records)))
    return 0
