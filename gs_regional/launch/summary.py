"""The few lines printed at the end of a run: what ran, how long each stage took, the Gaussian
counts, the key metrics and where the outputs are (read back from the trial's `save/` folder, so
a resumed run reports the whole run). The last line is `results: <trial dir>`."""
from __future__ import annotations

import json
import logging
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

log = logging.getLogger(__name__)

# (label, file names or glob patterns under save/; the newest match is shown).
OUTPUTS: Tuple[Tuple[str, Tuple[str, ...]], ...] = (
    ("edited scene", ("edited.ply",)),
    ("fitted scene", ("reconstructed.ply",)),
    ("exported scene", ("export_step*[0-9].ply",)),
    ("for web viewers", ("edited.splat", "export_step*[0-9].splat")),
    ("compressed PLY", ("edited.compressed.ply", "export_step*[0-9].compressed.ply")),
    ("edited region", ("edited_region.ply", "export_step*[0-9]_region.ply")),
    ("before/after", ("before_after.png",)),
    ("errors vs truth", ("errors_vs_truth.png",)),
    ("test views", ("test_views.png",)),
    ("turntable", ("turntable.mp4", "turntable.gif")),
    ("metrics.json", ("metrics.json",)),
)

# (label, key in metrics.json, format) of the metrics worth a glance, in this order.
KEY_METRICS: Tuple[Tuple[str, str, str], ...] = (
    ("mask IoU", "mask_iou", "{:.3f}"),
    ("PSNR vs true edit", "psnr_vs_true_edit", "{:.2f} dB"),
    ("unedited scene vs true edit", "psnr_source_vs_true_edit", "{:.2f} dB"),
    ("PSNR of the unedited region", "psnr_unedited", "{:.2f} dB"),
    ("CLIP direction similarity", "clip_direction_similarity", "{:.3f}"),
    ("UNet evaluations", "unet_evals", "{:,}"),
    ("PSNR on test views", "psnr_test", "{:.2f} dB"),
    ("SSIM on test views", "ssim_test", "{:.4f}"),
)
MAX_OTHER_METRICS = 6  # shown when a system reports none of KEY_METRICS


@dataclass
class RunInfo:
    trial: Path
    mode: str
    config_path: str
    system_type: str
    data_type: str
    resume: Optional[str]
    steps: Optional[int]  # training steps reached (train mode)
    setup_seconds: float  # plugins, config, data and system, before Lightning runs
    wall_seconds: float
    started_at: float  # time.time() at the start, to tell this run's outputs from older ones
    setup_parts: Dict[str, float] = field(default_factory=dict)  # run.py's PhaseClock: seconds per phase


def read_metrics(trial: Path) -> Dict[str, Any]:
    path = Path(trial) / "save" / "metrics.json"
    if not path.is_file():
        return {}
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except (OSError, ValueError) as e:
        log.warning("could not read %s for the summary: %s", path, e)
        return {}
    return data if isinstance(data, dict) else {}


def find_outputs(trial: Path) -> List[Tuple[str, Path]]:
    """(label, path) of the known output files that exist in `<trial>/save`."""
    save = Path(trial) / "save"
    found = []
    for label, patterns in OUTPUTS:
        matches = [p for pattern in patterns for p in save.glob(pattern) if p.is_file()]
        if matches:
            found.append((label, max(matches, key=lambda p: p.stat().st_mtime)))
    return found


def _seconds(metrics: Dict[str, Any]) -> str:
    per_stage = metrics.get("seconds")
    if isinstance(per_stage, dict) and per_stage:
        return ", ".join(f"{stage} {float(s):.1f}" for stage, s in per_stage.items())
    if _is_number(per_stage):
        return f"fit {float(per_stage):.1f}"
    return ""


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _gaussians(m: Dict[str, Any]) -> str:
    if "gaussians_before" in m and "gaussians_after" in m:
        parts = [f"{m['gaussians_before']:,} before"]
        if "count_added_init" in m:
            parts.append(f"+{m['count_added_init']:,} from depth")
        if m.get("count_added_cycles"):
            parts.append(f"+{m['count_added_cycles']:,} from the cycles' depth and paint")
        if "count_densified" in m:
            parts.append(f"+{m['count_densified']:,} densified")
        if m.get("count_pruned"):
            parts.append(f"-{m['count_pruned']:,} pruned")
        return ", ".join(parts) + f" -> {m['gaussians_after']:,} after"
    if "n_gaussians" in m:
        return f"{m['n_gaussians']:,}"
    return ""


def _refined_as(m: Dict[str, Any]) -> str:
    """How a regional edit was refined (metrics.json `refined_as`), and why: a recolour keeps every
    Gaussian's shape and adds none but what its later cycles paint, which a user who asked for a new
    object should be told."""
    kind, init = m.get("refined_as"), m.get("init")
    if kind == "recolour":
        edge = init.get("recolour_edge") if isinstance(init, dict) else None
        shows = (f"changes only at the recoloured part's edge ({edge:,} Gaussians placed there removed)" if edge
                 else "shows no change of shape")
        painted = m.get("count_added_cycles") or 0
        text = f"a recolour: the depth of view {m.get('v_first')} {shows}" + (
            f"; the edited views recolour next to none of the selection, and the later cycles painted {painted:,} "
            "Gaussians of a new object onto it" if painted else ", no Gaussian is added")
        if _is_number(m.get("count_selected")) and _is_number(m.get("count_recolour_declined")):
            text += (f"; {m['count_recolour_declined']:,} of the {m['count_selected']:,} selected Gaussians keep their "
                     "colours (the edited views recolour them too little, or they are parts of their own)")
        return text
    if kind == "addition":
        if not isinstance(init, dict):
            why = "initialization did not run"
        elif "rejected" in init:
            why = "the depth calibration was rejected, so refinement densifies the region"
        else:
            why = f"the depth of view {m.get('v_first')} shows a change of shape"
        return f"an addition: {why}"
    return ""


def _metrics(m: Dict[str, Any]) -> List[str]:
    shown = [f"{label} {fmt.format(m[key])}" for label, key, fmt in KEY_METRICS if _is_number(m.get(key))]
    if not shown:
        others = [(k, v) for k, v in m.items() if _is_number(v) and not k.startswith("seconds")][:MAX_OTHER_METRICS]
        shown = [f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v:,}" for k, v in others]
    return shown


def format_summary(info: RunInfo) -> str:
    m = read_metrics(info.trial)
    what = f"{info.mode} {info.system_type} on {info.data_type} ({info.config_path})"
    if info.steps is not None:
        what += f", {info.steps:,} steps"
    if info.resume:
        what += f", resumed from {info.resume}"
    rows: List[Tuple[str, str]] = [("ran", what)]
    rows.append(("wall time", f"{info.wall_seconds:.1f} s (start-up {info.setup_seconds:.1f} s)"))
    if info.setup_parts:
        text = ", ".join(f"{phase} {s:.1f}" for phase, s in info.setup_parts.items())
        if _is_number(m.get("seconds_unstaged")):  # checkpoints, Lightning's loop
            text += f"; in training outside the stages {m['seconds_unstaged']:.1f}"
        rows.append(("start-up (s)", text))
    if _seconds(m):
        rows.append(("stages (s)", _seconds(m)))
    refined = _refined_as(m)
    if refined:
        rows.append(("refined as", refined))
    if _gaussians(m):
        rows.append(("Gaussians", _gaussians(m)))
    if m.get("stopped"):
        rows.append(("stopped early", str(m["stopped"])))
    metrics = _metrics(m)
    if metrics:
        rows.append(("metrics", "; ".join(metrics)))
    for label, path in find_outputs(info.trial):
        older = path.stat().st_mtime < info.started_at - 1.0  # 1 s: coarse file-system clocks
        rows.append((label, f"{path}{'  (from an earlier run)' if older else ''}"))
    if (Path(info.trial) / "save" / "edited.ply").is_file():
        rows.append(("viewer", f"python launch.py --view {info.trial}"))
    width = max(len(label) for label, _ in rows)
    lines = [f"{label:<{width}}  {text}" for label, text in rows]
    lines.append(f"results: {info.trial}")
    return "\n".join(lines)


def print_summary(info: RunInfo) -> None:
    """The run's report to the user: standard output, whatever the log level."""
    sys.stdout.write("\n" + format_summary(info) + "\n")
    sys.stdout.flush()
