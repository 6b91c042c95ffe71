"""Two runs of a draw set against each other case by case (--compare)."""
from __future__ import annotations

import json
import os
import statistics
from typing import Dict, List, Sequence, Tuple

from gs_regional.bench import sweeps
from gs_regional.bench.truth.cases import JSON_NAME, run_seed, spread
from gs_regional.bench.truth.report import MET_WORDS, targets
from gs_regional.metrics.region import NEAR_FOOTPRINT_PX

# The cases whose (median) run is worse than this many dB are named: a longer refinement is held to
# none worse outside the footprint, and none with less gain.
WORSE_DB = 1.0


def load_payload(path: str, option: str = "--compare") -> dict:
    """A suite's JSON, given as the file or the folder holding it (`option` names it in the error)."""
    path = path if path.endswith(".json") else os.path.join(path, JSON_NAME)
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError) as e:
        raise SystemExit(f"{option}: cannot read the truth suite's JSON {path}: {e}")


def paired_differences(before: Dict[str, dict], after: Dict[str, dict], ids: Sequence[str], key: str) -> List[float]:
    """after - before of `key` over the runs of the same case at the same run seed (--repeats, or
    single runs: `run_seed`), leaving out runs that stopped at either."""
    out = []
    for i in ids:
        runs = lambda r: r.get("repeats") or [{**r, "run_seed": run_seed(r)}]  # noqa: E731
        x = {u.get("run_seed"): u for u in runs(before[i])}
        for v in runs(after[i]):
            u = x.get(v.get("run_seed"))
            if u is not None and not u.get("stopped") and not v.get("stopped") \
                    and u.get(key) is not None and v.get(key) is not None:
                out.append(v[key] - u[key])
    return out


def compare_report(before: dict, after: dict, names: Tuple[str, str] = ("before", "after")) -> List[dict]:
    """Print, for the cases both runs hold, the gain and the outside PSNR before -> after, and the
    two distributions; returns one row per shared case. A difference inside both runs' seed
    spreads (--repeats) is marked `~`: one seed's run says nothing about it."""
    if before.get("seed") != after.get("seed"):
        print(f"note: the runs are of different draws ({before.get('seed')} and {after.get('seed')}): "
              "cases of the same id are different edits")
    b = {r["id"]: r for r in before["records"] if not r.get("error")}
    a = {r["id"]: r for r in after["records"] if not r.get("error")}
    shared = [i for i in a if i in b]
    print(f"\n{names[0]} -> {names[1]}, {len(shared)} cases in both")
    print("| case | kind | gain dB | outside dB | UNet |")
    print("| --- | --- | --- | --- | --- |")
    rows = []
    inside_spread = set()  # (case, key): a difference inside both runs' seed ranges
    for i in shared:
        x, y = b[i], a[i]
        row = {"id": i}
        cells = []
        for key in ("gain", "psnr_outside_vs_true_edit"):
            u, v = x.get(key), y.get(key)
            if u is None or v is None:
                cells.append(f"{sweeps.fmt(u)} -> {sweeps.fmt(v)}")
                continue
            su, sv = spread(x, key), spread(y, key)
            noise = su is not None and sv is not None and su[0] <= sv[1] and sv[0] <= su[1]
            row[key] = v - u
            if noise:
                inside_spread.add((i, key))
            cells.append(f"{u:.2f} -> {v:.2f} ({v - u:+.2f}{' ~' if noise else ''})")
        rows.append(row)
        print(f"| {i} | {y['kind']} | {cells[0]} | {cells[1]} | {x.get('unet_evals')} -> {y.get('unet_evals')} |")
    print("\n| figure | " + " | ".join(names) + " |")
    print("| --- | --- | --- |")
    for name, f in (("gain min / median (dB)", lambda rs: [r["gain"] for r in rs]),
                    ("outside min / median (dB)", lambda rs: [r["psnr_outside_vs_true_edit"] for r in rs]),
                    ("outside, beyond its edge, min / median (dB)",
                     lambda rs: [r.get("psnr_far_outside_vs_true_edit") for r in rs]),
                    ("UNet evaluations min / median", lambda rs: [r["unet_evals"] for r in rs])):
        cols = []
        for rs in ([b[i] for i in shared], [a[i] for i in shared]):
            vals = [v for v in f(rs) if v is not None]
            cols.append(f"{min(vals):.2f} / {statistics.median(vals):.2f}" if vals else "-")
        print(f"| {name} | " + " | ".join(cols) + " |")
    for key, label in (("gain", "gain"), ("psnr_outside_vs_true_edit", "outside"),
                       ("psnr_far_outside_vs_true_edit", f"outside beyond {NEAR_FOOTPRINT_PX} px of the footprint")):
        d = paired_differences(b, a, shared, key)
        if d:
            print(f"paired runs (the same run seed at both, neither stopped), {label}: {len(d)} runs, better in "
                  f"{sum(v > 0 for v in d)}, worse by more than 0.3 dB in {sum(v < -0.3 for v in d)}, median "
                  f"difference {statistics.median(d):+.2f} dB")
    for key, label in (("gain", "gain"), ("psnr_outside_vs_true_edit", "outside")) if rows else ():
        worse = [r["id"] for r in rows if r.get(key, 0.0) < -WORSE_DB]
        noisy = [i for i in worse if (i, key) in inside_spread]
        print(f"cases worse by more than {WORSE_DB:g} dB, {label}: {len(worse)} of {len(rows)}"
              + (f" ({', '.join(worse)}; inside both runs' seed ranges: {', '.join(noisy) or 'none'})" if worse else ""))
    for rs, name in (([b[i] for i in shared], names[0]), ([a[i] for i in shared], names[1])):
        met = targets(rs)
        print(f"{name}: " + "; ".join(f"{MET_WORDS[ok]} {t.split(',')[0]} ({fig})" for t, ok, fig, _ in met if ok is not None))
    if shared and not (before.get("repeats", 1) > 1 and after.get("repeats", 1) > 1):
        print("(single runs: a case's run at another seed differs by several dB outside the footprint; "
              "compare --repeats runs to tell a change from noise)")
    return rows
