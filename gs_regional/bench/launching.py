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
