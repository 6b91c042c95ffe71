"""Running a truth suite: each case of the draw (or the ones picked) resolved on its scene and run
as a full launch.py run, its record written to OUT/truth_suite.json after each."""
from __future__ import annotations

import json
import os
import statistics
import time
from typing import List, Optional, Sequence

from gs_regional.bench import sweeps
from gs_regional.bench.launching import SHARED_DATA, run
from gs_regional.bench.truth.cases import COMMON, JSON_NAME, METRIC_KEYS, draw, gain, run_seed, settings
from gs_regional.bench.truth.scenes import Subject, resolve, subjects_for

# The figures a case with --repeats reports as the median over its runs (each run's own in `repeats`).
REPEAT_KEYS = ("gain", "psnr_region_vs_true_edit", "psnr_outside_vs_true_edit", "psnr_far_outside_vs_true_edit",
               "outside_error_near_footprint", "psnr_vs_true_edit",
               "psnr_unedited", "mask_iou", "mask_iou_seen", "gaussians_added", "source_deleted", "unet_evals",
               "seconds_total")
REPEAT_SEED_STEP = 1  # run j of a case uses its run seed + j (run 0 is the draw's own run)


def run_case(case: dict, subject: Optional[Subject], s: dict, runs_dir: str, repeats: int = 1) -> dict:
    """Resolve and run one case; its record (an `error` instead of metrics when it failed).

    With `repeats` > 1 the case runs that many times, the run seed shifted by REPEAT_SEED_STEP each
    time (the editor's draws, the views, the densification samples change; the scene and the truth
    do not): the record holds run 0's metrics with the REPEAT_KEYS replaced by their median over the
    runs, `stopped` set when any run stopped, and each run's REPEAT_KEYS in `repeats`. One run of a
    case differs from another seed's by several dB outside the footprint (docs/results.md), so a
    per-case difference between two codes means little below that spread."""
    rec = dict(case)
    try:
        config, overrides, facts = resolve(case, subject, s)
    except Exception as e:  # a draw that cannot be placed is reported, the suite goes on
        return {**rec, **{k: None for k in METRIC_KEYS}, "error": f"resolve: {e}"}
    tail = [f"tag={case['kind']}"] + s["budget"] + COMMON
    rec.update(facts, config=config, overrides=overrides + [f"seed={case['run_seed']}"] + tail)
    base = run_seed(rec)  # a `seed=` override of the whole suite replaces the case's own
    name = f"{case['id']}_{case['scene'].replace(':', '')}"
    t0 = time.perf_counter()
    runs = []
    for j in range(repeats):
        seed = base + j * REPEAT_SEED_STEP
        try:
            m = run(runs_dir, name + (f"_r{j}" if j else ""), config, *overrides, *tail, f"seed={seed}")
        except (SystemExit, Exception) as e:
            return {**rec, **{k: None for k in METRIC_KEYS}, "error": (str(e) or type(e).__name__) + (f" (run {j}, seed {seed})" if j else ""),
                    "wall_seconds": round(time.perf_counter() - t0, 2)}
        m["gain"] = gain(m)
        runs.append((seed, m))
    m = runs[0][1]
    rec.update({k: m.get(k) for k in METRIC_KEYS})
    rec["gain"] = m["gain"]
    rec["trial"] = m["trial"]
    if repeats > 1:
        rec["repeats"] = [{"run_seed": seed, "stopped": r.get("stopped"), "trial": r["trial"],
                           **{k: r.get(k) for k in REPEAT_KEYS}} for seed, r in runs]
        for k in REPEAT_KEYS:
            vals = [r.get(k) for _, r in runs]
            rec[k] = statistics.median(vals) if all(v is not None for v in vals) else None
        stops = [r["stopped"] for _, r in runs if r.get("stopped")]
        rec["stopped"] = f"{stops[0]} ({len(stops)} of {repeats} runs)" if stops else None
    rec["wall_seconds"] = round(time.perf_counter() - t0, 2)
    return rec


def resolve_only(seed: int, n_cases: int, quick: bool, out: str, size: Optional[int] = None, parts: int = 0,
                 only: Sequence[str] = ()) -> int:
    """Place every drawn case (those named in `only`, when given) on its scene and print what would run."""
    s = settings(quick, size)
    cases = select_cases(draw(seed, n_cases, quick, parts), only, (), seed)
    subjects, missing = subjects_for(cases, out, s)
    for why in missing:
        print(f"LEFT OUT: {why}")
    for case in cases:
        if not case["native"] and case["scene"] not in subjects:
            continue
        try:
            config, overrides, facts = resolve(case, subjects.get(case["scene"]), s)
            print(case["id"], case["kind"], case["scene"], json.dumps(facts))
        except Exception as e:
            print(case["id"], case["kind"], case["scene"], f"FAILED: {e}")
    return 0


def select_cases(cases: Sequence[dict], only: Sequence[str] = (), kinds: Sequence[str] = (), seed: int = 0) -> List[dict]:
    """The cases named in `only` (all when empty) of the `kinds` given ("recolor", "add"; all
    when empty), in the draw's order: a subset of a draw re-runs exactly as in the whole draw."""
    unknown = sorted(set(only) - {c["id"] for c in cases})
    if unknown:
        raise SystemExit(f"--only: no case {', '.join(unknown)} in draw {seed} (its cases: "
                         f"{cases[0]['id']}..{cases[-1]['id']})")
    return [c for c in cases if (not only or c["id"] in only) and (not kinds or c["kind"].split("_")[0] in kinds)]


def run_suite(seed: int, n_cases: int, quick: bool, out: str, overrides: Sequence[str] = (),
              only: Sequence[str] = (), kinds: Sequence[str] = (), size: Optional[int] = None,
              repeats: int = 1, parts: int = 0) -> dict:
    """Run the draw's cases (those named in `only`, of the `kinds` given, when given; `parts`
    whole-part cases after the n_cases) and write the JSON after each."""
    s = settings(quick, size)
    s["budget"] = s["budget"] + list(overrides)  # every case's launch.py overrides
    cases = select_cases(draw(seed, n_cases, quick, parts), only, kinds, seed)
    os.makedirs(out, exist_ok=True)
    t0 = time.perf_counter()
    subjects, missing = subjects_for(cases, out, s)
    if missing:
        print("\n" + "!" * 100)
        for why in missing:
            print(f"!! LEFT OUT: {why}: its cases do not run (set GS_REGIONAL_DATA to the folder holding "
                  "donut/ and face/)")
        print("!" * 100 + "\n", flush=True)
    payload = {"seed": seed, "quick": quick, "n_cases": n_cases, "parts": parts, "only": list(only), "kinds": list(kinds), "repeats": repeats,
               "settings": {**s, "common": COMMON},
               "shared_data": SHARED_DATA, "left_out": missing, "records": []}
    runs_dir = os.path.join(out, "runs")
    todo = [c for c in cases if c["native"] or c["scene"] in subjects]
    skipped = [c for c in cases if c not in todo]
    for i, case in enumerate(todo):
        print(f"[{i + 1}/{len(todo)}] {case['id']} {case['kind']} on {case['scene']}"
              f"{' (its own edit)' if case['native'] else ''}", flush=True)
        rec = run_case(case, subjects.get(case["scene"]), s, runs_dir, repeats)
        rec.setdefault("gain", gain(rec))
        if rec.get("error"):
            print(f"error: {case['id']} failed: {rec['error']}", flush=True)
        else:
            over = f" (median of {repeats} runs)" if repeats > 1 else ""
            print(f"    {rec['prompt']!r}: gain {sweeps.fmt(rec['gain'])} dB, outside "
                  f"{sweeps.fmt(rec['psnr_outside_vs_true_edit'])} dB, IoU {sweeps.fmt(rec['mask_iou'])}{over}, "
                  f"{rec['wall_seconds']:.1f} s", flush=True)
        payload["records"].append(rec)
        sweeps.write_json(os.path.join(out, JSON_NAME), payload)
    payload["skipped_cases"] = [c["id"] for c in skipped]
    payload["wall_seconds"] = round(time.perf_counter() - t0, 1)
    sweeps.write_json(os.path.join(out, JSON_NAME), payload)
    return payload
