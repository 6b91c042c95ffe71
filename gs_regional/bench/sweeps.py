"""What the sweeps (pareto.py, stability.py, compactness.py) share: the methods and their settings,
one run (launching.run: a full launch.py run read back from its save/metrics.json) turned into one
flat record, the JSON they write, and chart helpers.

Runs use a smaller scene than the demo (`scene_overrides`): 24 cameras at 64² (quick: 16 at
48²; `Run.demo_scene` keeps the demo's 40 at 96²), two turntable frames (they do not enter the metrics) and no checkpoints, so a full sweep of
about a hundred runs fits in 30 minutes of this 2-core CPU. The simulated editor and depth stand
in for the real priors (see the README's "The simulated editor").
"""
from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence

from gs_regional.bench.launching import DONUT, ROOT, run

# Kept in every record; missing keys are stored as None.
METRIC_KEYS = (
    "psnr_region_vs_true_edit", "psnr_region_source_vs_true_edit", "psnr_outside_vs_true_edit",
    "psnr_outside_source_vs_true_edit", "psnr_vs_true_edit", "psnr_source_vs_true_edit",
    "ssim_region_vs_true_edit", "ssim_region_source_vs_true_edit", "psnr_unedited", "ssim_unedited",
    "mask_iou", "mask_precision", "mask_recall", "view_agreement", "edit_coverage", "gaussians_before", "gaussians_added",
    "gaussians_pruned", "gaussians_after", "true_gaussians_added", "ply_bytes", "source_ply_bytes",
    "unet_evals", "seconds", "seconds_total", "warnings", "stopped", "footprint_fraction",
)

# Edits: name -> (config, overrides). The synthetic ones use the demo's config with data.edit.
EDITS = {
    "recolor": ("configs/demo.yaml", ["data.edit=recolor", "system.prompt=make his head red"]),
    "add": ("configs/demo.yaml", ["data.edit=add"]),
    "global": ("configs/demo.yaml", ["data.edit=global", "system.prompt=make it look like an old sepia photograph"]),
    "empty": ("configs/demo.yaml", ["data.edit=empty", "system.prompt=put a hat on the cat"]),
    "donut_recolor": ("configs/donut_recolor.yaml", [f"data.ply={DONUT}"]),
    "donut_add": ("configs/donut_add.yaml", [f"data.ply={DONUT}"]),
}
IN2N_CONFIG = {"donut_recolor": "configs/in2n.yaml", "donut_add": "configs/in2n.yaml"}
METHOD_COLORS = {
    "regional-edit": "tab:blue", "in2n": "tab:red", "plain-vote": "tab:orange", "no-depth-init": "tab:green",
    "constant-t": "tab:purple", "optimize-all": "tab:brown",
}


def scene_overrides(quick: bool, demo_scene: bool = False) -> List[str]:
    """The sweeps' scene size and output settings; `demo_scene` keeps the config's own cameras
    (the demo's 40 at 96²)."""
    size = [] if demo_scene else ["data.n_cameras=16", "data.width=48", "data.height=48"] if quick else \
        ["data.n_cameras=24", "data.width=64", "data.height=64"]
    return size + ["system.eval.turntable_frames=2", "checkpoint.every_n_train_steps=1000000"]


def regional_budget(cycles: int, iterations: int, m: int, t_schedule: Sequence[int] = (750, 500, 250)) -> List[str]:
    """Overrides of one regional-edit budget: cycles x iterations per cycle at the rates set for
    that length (a later override of iterations_per_cycle alone lengthens the cycle at the same
    travel: system.refine.rate_iterations), m views per cycle."""
    t = ",".join(str(x) for x in list(t_schedule)[:cycles])
    return [f"system.refine.cycles={cycles}", f"system.refine.iterations_per_cycle={iterations}",
            f"system.refine.rate_iterations={iterations}",
            f"system.refine.m={m}", f"system.refine.t_schedule=[{t}]",
            "system.localization.max_views=8"]  # densification: the edit's default, once a cycle


# The method's parts switched off one at a time (README "Ablations").
ABLATIONS = {
    "plain-vote": ["system.ablation.plain_vote=true"],  # the paper's vote
    "no-depth-init": ["system.ablation.initialize=false"],
    "constant-t": ["system.ablation.constant_t=500"],
    "optimize-all": ["system.ablation.optimize_all=true"],
}


@dataclass
class Run:
    """One launch.py run of a sweep: `edit` (EDITS), `method` (METHOD_COLORS), a `label` for its
    settings, and the overrides on top of the edit's config."""
    edit: str
    method: str
    label: str
    overrides: List[str] = field(default_factory=list)
    info: Dict[str, object] = field(default_factory=dict)  # copied into the record (e.g. severity)
    demo_scene: bool = False  # the config's own cameras instead of the sweeps' smaller scene

    @property
    def key(self) -> str:
        return f"{self.edit}/{self.method}/{self.label}"

    @property
    def config(self) -> str:
        if self.method == "in2n":
            return IN2N_CONFIG.get(self.edit, "configs/in2n.yaml")
        return EDITS[self.edit][0]

    def all_overrides(self, quick: bool) -> List[str]:
        edit_overrides = EDITS[self.edit][1]
        if self.method == "in2n" and self.edit.startswith("donut"):
            # in2n on the splat truth: the data section of the donut config (the system is in2n's)
            edit_overrides = donut_data_for_in2n(self.edit)
        return edit_overrides + scene_overrides(quick, self.demo_scene) + list(self.overrides)


def donut_data_for_in2n(edit: str) -> List[str]:
    """in2n's overrides for a donut truth: the splat-truth data module of that config."""
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(os.path.join(ROOT, EDITS[edit][0]))
    data = OmegaConf.to_container(cfg.data, resolve=False)
    data["ply"] = DONUT
    data["seed"] = 0
    out = ["data_type=splat-truth", f"system.prompt={data['prompt']}"]
    for k, v in data.items():
        out.append(f"data.{k}={json.dumps(v) if isinstance(v, (list, str)) else v}")
    return out


def available_edits(edits: Sequence[str]) -> List[str]:
    """The edits whose data is here; each missing one is named on stdout (and skipped)."""
    out = []
    for edit in edits:
        why = edit_available(edit)
        if why:
            print(why)
        else:
            out.append(edit)
    return out


def edit_available(edit: str) -> Optional[str]:
    """None when the edit's data is present, else why it is skipped."""
    if edit.startswith("donut") and not os.path.exists(DONUT):
        return f"{edit}: skipped, {DONUT} not found (set GS_REGIONAL_DATA to the folder holding donut/donut.ply)"
    return None


def record_of(r: Run, quick: bool, runs_dir: str) -> dict:
    """Run `r` (launching.run) and return its flat record: settings + the metrics of §1."""
    overrides = r.all_overrides(quick)
    name = r.key.replace("/", "_").replace(" ", "")
    t0 = time.perf_counter()
    m = run(runs_dir, name, r.config, *overrides)
    rec = {"key": r.key, "edit": r.edit, "method": r.method, "label": r.label, "config": r.config,
           "overrides": overrides, **r.info}
    rec.update({k: m.get(k) for k in METRIC_KEYS})
    rec["wall_seconds"] = round(time.perf_counter() - t0, 2)
    # The cost of the edit itself: every stage but writing the evaluation outputs.
    rec["edit_seconds"] = round(m["seconds_total"] - m["seconds"].get("output", 0.0), 3)
    rec["trial"] = m["trial"]
    return rec


def run_all(runs: Sequence[Run], quick: bool, out: str, json_name: str, header: dict) -> List[dict]:
    """Run every run in order, rewriting out/json_name after each (a long sweep shows progress and
    keeps what finished). A run that fails gets a record with `error` and no metrics. Returns the
    records."""
    os.makedirs(out, exist_ok=True)
    runs_dir = os.path.join(out, "runs")
    records = []
    for i, r in enumerate(runs):
        print(f"[{i + 1}/{len(runs)}] {r.key} {' '.join(r.overrides)}", flush=True)
        try:
            records.append(record_of(r, quick, runs_dir))
        except (SystemExit, Exception) as e:  # one failed run is reported, the sweep goes on
            print(f"error: {r.key} failed: {e}", flush=True)
            records.append({"key": r.key, "edit": r.edit, "method": r.method, "label": r.label, "config": r.config,
                            "overrides": r.all_overrides(quick), **r.info, **{k: None for k in METRIC_KEYS},
                            "error": str(e) or type(e).__name__})
        write_json(os.path.join(out, json_name), {**header, "records": records})
    return records


def arg_parser(doc: str, json_name: str) -> argparse.ArgumentParser:
    """The options every sweep script takes: --quick, --out (default outputs/<json_name's stem>),
    --replot."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a few runs at small budgets (the test's mode)")
    name = os.path.splitext(json_name)[0]
    ap.add_argument("--out", default=os.path.join(ROOT, "outputs", name),
                    help=f"folder for {json_name}, the PNGs and the runs (default outputs/{name})")
    ap.add_argument("--replot", action="store_true", help=f"no runs: redraw the charts and the table from OUT/{json_name}")
    return ap


def records_for(args: argparse.Namespace, plan: Callable[[], Sequence[Run]], json_name: str, header: dict) -> List[dict]:
    """The records of a sweep: read back from OUT/json_name with --replot, else run `plan()`."""
    if args.replot:
        return read_records(os.path.join(args.out, json_name), args.quick)
    return run_all(plan(), args.quick, args.out, json_name, header)


def read_records(path: str, quick: bool) -> List[dict]:
    """The records of a sweep's JSON (--replot), checked to be of the same mode."""
    with open(path) as f:
        payload = json.load(f)
    if payload.get("quick") != quick:
        raise SystemExit(f"{path} was written {'with' if payload.get('quick') else 'without'} --quick; replot it the same way")
    return payload["records"]


def write_json(path: str, payload: dict) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(payload, f, indent=1)
    os.replace(tmp, path)


def pyplot():
    """matplotlib's pyplot without a display."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def pareto_front(points: Sequence[tuple]) -> List[tuple]:
    """The (cost, quality) points no other point beats on both (lower cost, higher quality),
    sorted by cost."""
    front, best = [], float("-inf")
    for c, q in sorted(points, key=lambda p: (p[0], -p[1])):
        if q > best:
            front.append((c, q))
            best = q
    return front


def fmt(x) -> str:
    """A PSNR (or any float) for the tables; n/a when missing."""
    return "n/a" if x is None else f"{x:.2f}"


def print_table(records: Sequence[dict], columns: Sequence[str], lead: Sequence[str], cells: Callable[[dict], Sequence[str]]) -> None:
    """A markdown table of the records: `lead` keys name each run; a failed run shows its error."""
    print("\n| " + " | ".join(columns) + " |")
    print("| " + " | ".join("---" for _ in columns) + " |")
    for r in records:
        head = [str(r[k]) for k in lead]
        rest = [f"failed: {r['error']}"] + [""] * (len(columns) - len(lead) - 1) if r.get("error") else list(cells(r))
        print("| " + " | ".join(head + rest) + " |")
