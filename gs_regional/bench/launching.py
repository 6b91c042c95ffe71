"""One launch.py run of a benchmark, read back from its save/metrics.json; where the checkout and
the shared data are."""
from __future__ import annotations

import glob
import json
import os
import time
from pathlib import Path

# The checkout (configs/, custom/ and launch.py live there): the package is installed editable.
ROOT = str(Path(__file__).resolve().parents[2])
# The data of the real-splat truths (../shared/data beside the checkout, or GS_REGIONAL_DATA).
SHARED_DATA = os.environ.get("GS_REGIONAL_DATA") or os.path.join(os.path.dirname(ROOT), "shared", "data")
DONUT = os.path.join(SHARED_DATA, "donut", "donut.ply")


def run(out: str, name: str, config: str, *overrides: str) -> dict:
    """`launch.py --config ROOT/config --train` into out/name with `overrides`; its metrics.json
    with `wall_seconds` and `trial` (the trial folder) added."""
    from gs_regional.launch import main

    t0 = time.perf_counter()
    argv = ["--config", os.path.join(ROOT, config), "--train", f"exp_root_dir={out}", f"name={name}",
            "trainer.enable_progress_bar=false", *overrides]
    if main(argv, custom_dir=os.path.join(ROOT, "custom")) != 0:
        raise SystemExit(f"run {name} failed")
    trial = sorted(glob.glob(os.path.join(out, name, "*")), key=os.path.getmtime)[-1]
    with open(os.path.join(trial, "save", "metrics.json")) as f:
        m = json.load(f)
    m["wall_seconds"] = time.perf_counter() - t0
    m["trial"] = trial
    return m


def trial_truth(trial: str) -> tuple:
    """(config, scene) of a finished trial: its configs/parsed.yaml and its data module's scene set
    up again, whose `ground_truth` the trial was scored against (exits naming the trial when its
    scene has none)."""
    from gs_regional.config import load_config
    from gs_regional.registry import find, load_builtins

    load_builtins()
    cfg = load_config(os.path.join(trial, "configs", "parsed.yaml"))
    dm = find(cfg.data_type, kind="data")(cfg.data)
    dm.setup("fit")
    if dm.scene.ground_truth is None:
        raise SystemExit(f"{trial}: its scene ({cfg.data_type}) has no ground truth")
    return cfg, dm.scene
