"""The targets of a truth suite, its printed report (the cases, the distribution, which case misses
which target) and its chart."""
from __future__ import annotations

import statistics
from typing import Dict, List, Optional, Sequence, Tuple

from gs_regional.bench import sweeps
from gs_regional.bench.truth.cases import KINDS, LOCALIZE_ONLY, PART_KINDS, gain, spread
from gs_regional.metrics.region import NEAR_FOOTPRINT_PX


def _ratio_added(r: dict) -> Optional[float]:
    if r.get("gaussians_added") is None:
        return None
    if r["kind"].startswith("add"):
        return r["gaussians_added"] / max(r.get("true_added") or r.get("true_gaussians_added") or 1, 1)
    return r["gaussians_added"] / max(r.get("region_gaussians") or 1, 1)


def refined_otherwise(r: dict) -> str:
    """" (refined as a recolour)" for an addition whose depth showed no change of shape (none of its
    object is added: its Gaussians only recolour), " (refined as an addition)" for a recolour whose
    depth showed one; "" when the edit was refined as its kind."""
    refined = r.get("refined_as")
    if refined == "recolour" and r["kind"].startswith("add"):
        return " (refined as a recolour)"
    if refined == "addition" and r["kind"].startswith("recolor"):
        return " (refined as an addition)"
    return ""


MET_WORDS = {True: "ok", False: "FAIL", None: "n/a"}

# What a draw holds the edit to (docs/results.md, "Truth suite"): gains in dB over doing nothing in
# the true footprint, and PSNR outside it.
MIN_GAIN = 4.0
MEDIAN_GAIN = 8.0
MEDIAN_GAIN_ADDITIONS = 8.0
MEDIAN_GAIN_RECOLOURS = 12.0
MIN_GAIN_WHOLE_PART_RECOLOUR = 8.0
MIN_OUTSIDE = 45.0
MEDIAN_OUTSIDE = 55.0
MIN_UNEDITED = 50.0  # PSNR of the region no edit should touch, against the source


def localize_only(payload: dict) -> bool:
    """Whether every run of `payload` ended after localization (--localize-only)."""
    return LOCALIZE_ONLY in (payload.get("settings") or {}).get("budget", [])


def targets(records: Sequence[dict], localization_only: bool = False) -> List[Tuple[str, Optional[bool], str, List[str]]]:
    """(target, met, the figure, failing case ids) of each target; met is None where no case is of
    the kind it is about. `localization_only`: the localization's targets alone (runs that ended
    after localization have no edit to judge)."""
    ok = [r for r in records if not r.get("error")]
    failed_runs = [r["id"] for r in records if r.get("error")]

    def per_case(name, test):
        bad = [r["id"] for r in ok if not test(r)] + failed_runs
        return (name, not bad, f"{len(ok) - len(bad) + len(failed_runs)}/{len(records)} cases", bad)

    def median_of(name, values, limit):
        vals = [v for v in values if v is not None]
        if not vals:  # e.g. the recolours' target of a run of the additions alone
            return (name, None, "no such case", [])
        med = statistics.median(vals)
        return (name, med >= limit, f"median {sweeps.fmt(med)}", [])

    g = lambda r: r["gain"] if r.get("gain") is not None else float("-inf")  # noqa: E731
    recolours = [r for r in ok if r["kind"].startswith("recolor")]
    additions = [r for r in ok if r["kind"].startswith("add")]
    part_recolours = [r for r in records if r["kind"] == "recolor_part"]

    def whole_part_recolours(name, limit):  # None when the run holds no whole-part recolour
        if not part_recolours:
            return (name, None, "no such case", [])
        bad = [r["id"] for r in part_recolours if r.get("error") or g(r) < limit]
        return (name, not bad, f"{len(part_recolours) - len(bad)}/{len(part_recolours)} cases", bad)

    localization = [
        median_of("median mask IoU >= 0.9", [r["mask_iou"] for r in ok], 0.9),
        median_of("median mask IoU from exact 2D masks >= 0.95", [r.get("mask_iou_exact_masks") for r in ok], 0.95),
        per_case("mask recall >= 0.9, every case", lambda r: (r.get("mask_recall") or 0) >= 0.9),
    ]
    if localization_only:
        return localization
    return [
        per_case("gain > 0 dB, every case", lambda r: g(r) > 0),
        per_case(f"gain >= +{MIN_GAIN:g} dB, every case", lambda r: g(r) >= MIN_GAIN),
        median_of(f"median gain >= +{MEDIAN_GAIN:g} dB", [r["gain"] for r in ok], MEDIAN_GAIN),
        median_of(f"median gain of the additions >= +{MEDIAN_GAIN_ADDITIONS:g} dB", [r["gain"] for r in additions],
                  MEDIAN_GAIN_ADDITIONS),
        median_of(f"median gain of the recolours >= +{MEDIAN_GAIN_RECOLOURS:g} dB", [r["gain"] for r in recolours],
                  MEDIAN_GAIN_RECOLOURS),
        whole_part_recolours(f"gain >= +{MIN_GAIN_WHOLE_PART_RECOLOUR:g} dB, every whole-part recolour",
                             MIN_GAIN_WHOLE_PART_RECOLOUR),
        per_case(f"outside-footprint PSNR >= {MIN_OUTSIDE:g} dB, every case",
                 lambda r: (r["psnr_outside_vs_true_edit"] or 0) >= MIN_OUTSIDE),
        median_of(f"median outside-footprint PSNR >= {MEDIAN_OUTSIDE:g} dB", [r["psnr_outside_vs_true_edit"] for r in ok],
                  MEDIAN_OUTSIDE),
        per_case(f"unedited PSNR >= {MIN_UNEDITED:g} dB, every case", lambda r: (r["psnr_unedited"] or 0) >= MIN_UNEDITED),
        *localization,
        per_case("no stopped run", lambda r: not r.get("stopped")),
        per_case("no source Gaussian deleted", lambda r: r.get("source_deleted") == 0),
        per_case("Gaussians added <= 2x the truth's (a recolour: < 1 % of its region)",
                 lambda r: _ratio_added(r) is not None and (_ratio_added(r) <= 2.0 if r["kind"].startswith("add")
                                                            else _ratio_added(r) < 0.01)),
    ]


DISTRIBUTION = (
    ("gain (dB)", gain),
    ("footprint PSNR vs truth (dB)", lambda r: r.get("psnr_region_vs_true_edit")),
    ("footprint PSNR doing nothing (dB)", lambda r: r.get("psnr_region_source_vs_true_edit")),
    ("outside-footprint PSNR (dB)", lambda r: r.get("psnr_outside_vs_true_edit")),
    (f"outside it, over {NEAR_FOOTPRINT_PX} px from it (dB)", lambda r: r.get("psnr_far_outside_vs_true_edit")),
    (f"outside error within {NEAR_FOOTPRINT_PX} px of it (share)", lambda r: r.get("outside_error_near_footprint")),
    ("unedited PSNR (dB)", lambda r: r.get("psnr_unedited")),
    ("mask IoU", lambda r: r.get("mask_iou")),
    ("mask IoU (seen)", lambda r: r.get("mask_iou_seen")),
    ("mask precision", lambda r: r.get("mask_precision")),
    ("mask recall", lambda r: r.get("mask_recall")),
    ("mask IoU from exact 2D masks", lambda r: r.get("mask_iou_exact_masks")),
    ("mask recall from exact 2D masks", lambda r: r.get("mask_recall_exact_masks")),
    ("added / truth's added (adds)", lambda r: _ratio_added(r) if r["kind"].startswith("add") else None),
    ("added / region (recolours)", lambda r: _ratio_added(r) if r["kind"].startswith("recolor") else None),
    ("region / true added (adds)", lambda r: r.get("region_to_added") if r["kind"].startswith("add") else None),
    ("true object's coverage drawn (adds)", lambda r: r.get("added_cover")),
    ("added coverage beside it (adds)", lambda r: r.get("added_cover_outside")),
    ("recolour's error removed (recolours)", lambda r: r.get("recolour_done")),
    ("source Gaussians deleted", lambda r: r.get("source_deleted")),
    ("UNet evaluations", lambda r: r.get("unet_evals")),
    ("seconds (all stages)", lambda r: r.get("seconds_total")),
    ("wall seconds", lambda r: r.get("wall_seconds")),
)


def seed_spreads(records: Sequence[dict]) -> Dict[str, List[float]]:
    """Per figure (gain, outside), each repeated case's max - min over its runs."""
    out = {}
    for name, key in (("gain", "gain"), ("outside", "psnr_outside_vs_true_edit")):
        v = [sp[1] - sp[0] for sp in (spread(r, key) for r in records if not r.get("error")) if sp]
        if v:
            out[name] = v
    return out


# The whole-part cases' own figures: the part and how the cameras see it.
PART_DISTRIBUTION = (
    ("part size (Gaussians)", lambda r: r.get("part_gaussians")),
    ("views seeing it from the side or below", lambda r: r.get("side_view_fraction")),
    ("part hidden by others (fraction)", lambda r: r.get("hidden_fraction")),
    ("part's weight where it is most of the pixel (fraction)", lambda r: r.get("shown_fraction")),
    ("part's share of the image", lambda r: r.get("view_fraction")),
)


def _distribution_rows(records: Sequence[dict], rows) -> None:
    for name, f in rows:
        vals = [f(r) for r in records if not r.get("error")]
        vals = [float(v) for v in vals if v is not None]
        if vals:
            print(f"| {name} | {len(vals)} | {min(vals):.3g} | {statistics.median(vals):.3g} | {max(vals):.3g} |")


def print_report(payload: dict) -> List[Tuple[str, bool, str, List[str]]]:
    records = payload["records"]
    print(f"\ntruth suite: seed {payload['seed']} ({len(records)} cases"
          f"{', quick' if payload.get('quick') else ''}; rerun this draw with --seed {payload['seed']})")
    if payload.get("left_out"):
        print("LEFT OUT: " + "; ".join(payload["left_out"]))
    only = localize_only(payload)
    if only:  # the localization of each case, from the relevance maps and from exact 2D masks
        print("\nlocalization only (relevance maps | exact 2D masks):\n| case | kind | scene | IoU | precision | recall "
              "| IoU | precision | recall |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for r in records:
            if not r.get("error"):
                print(f"| {r['id']} | {r['kind']} | {r['scene']} | " + " | ".join(
                    sweeps.fmt(r.get(f"mask_{m}{src}")) for src in ("", "_exact_masks")
                    for m in ("iou", "precision", "recall")) + " |")
    else:
        print("\n| case | kind | scene | prompt | gain dB | outside dB | unedited dB | IoU | added (truth) | s |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in records if not only else []:
        scene = f"{r['scene']}{' (own edit)' if r.get('native') else ''}"
        head = f"| {r['id']} | {r['kind']}{refined_otherwise(r)} | {scene} | {r.get('prompt', '')} |"
        if r.get("error"):
            print(f"{head} failed: {r['error']} | | | | | |")
            continue
        truth = r.get("true_added") if r["kind"].startswith("add") else f"region {r.get('region_gaussians')}"
        stop = f" STOPPED ({r['stopped']})" if r.get("stopped") else ""
        rng = lambda key: "" if spread(r, key) is None else " ({} to {})".format(*map(sweeps.fmt, spread(r, key)))  # noqa: E731
        print(f"{head} {sweeps.fmt(r['gain'])}{rng('gain')}{stop} | {sweeps.fmt(r['psnr_outside_vs_true_edit'])}"
              f"{rng('psnr_outside_vs_true_edit')} | "
              f"{sweeps.fmt(r['psnr_unedited'])} | {sweeps.fmt(r['mask_iou'])} | {r['gaussians_added']} ({truth}) | "
              f"{sweeps.fmt(r.get('wall_seconds'))} |")
    parts = [r for r in records if r["kind"] in PART_KINDS]
    drawn = [r for r in records if r["kind"] not in PART_KINDS]
    if parts and not only:
        print("\nwhole parts:\n| case | kind | scene | part | part size | side/below views | hidden | shown | image share "
              "| gain dB | outside dB | IoU | recolour's error left: unselected / declined / trained |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for r in parts:
            left = " / ".join(sweeps.fmt(r.get(f"recolour_left_{k}")) for k in ("unselected", "declined", "taken"))
            print(f"| {r['id']} | {r['kind']} | {r['scene']} | {r.get('part_key', r.get('part'))} | {r.get('part_gaussians')} | "
                  f"{sweeps.fmt(r.get('side_view_fraction'))} | {sweeps.fmt(r.get('hidden_fraction'))} | "
                  f"{sweeps.fmt(r.get('shown_fraction'))} | {sweeps.fmt(r.get('view_fraction'))} | {sweeps.fmt(r.get('gain'))} | "
                  f"{sweeps.fmt(r.get('psnr_outside_vs_true_edit'))} | {sweeps.fmt(r.get('mask_iou'))} | "
                  f"{left if r['kind'] == 'recolor_part' else ''} |")
    print("\n| metric | n | min | median | max |")
    print("| --- | --- | --- | --- | --- |")
    _distribution_rows(drawn, DISTRIBUTION)
    if parts:  # the whole-part cases apart
        print("| **whole parts** | | | | |")
        _distribution_rows(parts, DISTRIBUTION + PART_DISTRIBUTION)
    spreads = seed_spreads(records)
    if spreads:
        print(f"\n{payload.get('repeats')} runs a case (run seeds +0..+{payload.get('repeats', 1) - 1}): each figure above is "
              "their median, the range in brackets; " + "; ".join(
                  f"{name} spread (max - min) median {statistics.median(v):.2f}, max {max(v):.2f} dB"
                  for name, v in spreads.items()))
    result = targets(records, only)
    print("\ntargets" + (" (on each case's median run)" if spreads else "") + ":")
    for name, met, figure, bad in result:
        print(f"  [{MET_WORDS[met]}] {name}: {figure}" + (f"; missed by {', '.join(bad)}" if bad else ""))
    return result


def chart(payload: dict, path: str) -> None:
    """Per-case gain and outside-footprint PSNR, each sorted, coloured by kind, targets drawn."""
    plt = sweeps.pyplot()
    records = [r for r in payload["records"] if not r.get("error")]
    colors = dict(zip(KINDS + PART_KINDS, ("tab:orange", "tab:red", "tab:blue", "tab:purple", "tab:brown", "tab:cyan")))
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8))
    panels = ((axes[0], "gain", "gain in the footprint vs doing nothing (dB)",
               ((MIN_GAIN, f"every case >= +{MIN_GAIN:g}"), (MEDIAN_GAIN, f"median >= +{MEDIAN_GAIN:g}"),
                (MEDIAN_GAIN_RECOLOURS, f"median of the recolours >= +{MEDIAN_GAIN_RECOLOURS:g}"))),
              (axes[1], "psnr_outside_vs_true_edit", "PSNR outside the footprint (dB)",
               ((MIN_OUTSIDE, f"every case >= {MIN_OUTSIDE:g}"), (MEDIAN_OUTSIDE, f"median >= {MEDIAN_OUTSIDE:g}"))))
    for ax, key, label, lines in panels:
        rows = sorted((r for r in records if r.get(key) is not None), key=lambda r: r[key])
        xs = range(len(rows))
        ax.bar(xs, [r[key] for r in rows], color=[colors[r["kind"]] for r in rows],
               edgecolor=["black" if r.get("stopped") else "none" for r in rows])
        ranges = [spread(r, key) for r in rows]
        if any(ranges):  # --repeats: each bar is a case's median run, the whisker its runs' range
            ax.errorbar(list(xs), [r[key] for r in rows], fmt="none", ecolor="black", elinewidth=0.8, capsize=2,
                        yerr=[[r[key] - (sp or (r[key],))[0] for r, sp in zip(rows, ranges)],
                              [(sp or (0, r[key]))[1] - r[key] for r, sp in zip(rows, ranges)]])
        stopped = [(x, r[key]) for x, r in zip(xs, rows) if r.get("stopped")]
        if stopped:  # a stop leaves the source: gain 0, invisible as a bar
            ax.scatter(*zip(*stopped), marker="x", color="black", zorder=4, s=40)
        ax.set_xticks(list(xs))
        ax.set_xticklabels([r["id"] for r in rows], rotation=90, fontsize=7)
        for y, text in lines:
            ax.axhline(y, color="black", ls="--" if "median" in text else "-", lw=1)
            ax.text(0, y, f" target: {text}", va="bottom", fontsize=8)
        if rows:
            med = statistics.median(r[key] for r in rows)
            ax.axhline(med, color="tab:green", lw=1.5, alpha=0.8)
            ax.text(len(rows) - 1, med, f"median {med:.1f}", va="bottom", ha="right", color="tab:green", fontsize=8)
        if key != "gain" and rows:  # PSNRs: from a little below the lowest target or value
            ax.set_ylim(min(40.0, rows[0][key] - 3), max(55.0, rows[-1][key] + 3))
        ax.set_ylabel(label)
        ax.set_xlabel("case (sorted)")
        ax.grid(axis="y", alpha=0.3)
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in colors.values()]
    handles.append(plt.Line2D([], [], marker="x", color="black", ls=""))
    axes[0].legend(handles, list(colors) + ["stopped (source kept)"], fontsize=8, loc="upper left",
                   bbox_to_anchor=(0, 0.9))
    runs = payload.get("repeats", 1)
    fig.suptitle(f"truth suite, seed {payload['seed']}: {len(records)} known edits (simulated editor and depth)"
                 + (f"; each bar the median of {runs} runs (run seeds), the whisker their range" if runs > 1 else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
