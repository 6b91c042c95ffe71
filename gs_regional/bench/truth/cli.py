"""A truth suite that cannot be memorized: known edits drawn at random from a seed it prints.

    python scripts/truth_suite.py [--seed N] [--cases 24] [--parts K] [--quick] [--out outputs/truth_suite] [key=value ...]
    make truth-suite [SEED=N]

Each run draws `--cases` (default 24) known edits from a fresh random seed, printed first (`--seed N`
redraws the same cases), and runs each one as a full launch.py run (gs_regional/bench/launching.py
`run`: `regional-edit` with the `simulated-editor` and `simulated-depth` at their default failure modes),
read back from its save/metrics.json.

Scenes (every case a `splat-truth` edit of a trained splat, gs_regional/sim/splat_truth.py, unless
said otherwise):
  synthetic:<k>  the procedural scene `make_scene(k)` (figure, ground and backdrop; y up, facing +z)
                 written as a PLY with its own 24 cameras (cameras.json), for 6 scene seeds k drawn
                 at random; a quarter of its large recolours and larger additions are instead the
                 scene's own edits (`synthetic-scene`: the head turned red, the moustache).
  donut          ../shared/data/donut/donut.ply (z up; an orbit of 24 cameras).
  face           a splat fitted to ../shared/data/face with configs/reconstruct.yaml (64², 24 cameras,
                 400 steps), once: cached as OUT/face_fit/ and reused while its settings match
                 (delete the folder to refit); edited from 24 of its own cameras at 64².
The shared data is ../shared/data beside the checkout or $GS_REGIONAL_DATA; scenes whose data is
missing are named on stdout and their cases left out, the others run.

Kinds (24 cases: 4 on the donut, 4 on the face, one of each kind; 16 on the synthetic scenes, 4 of
each kind), sizes in radii of the scene's subject (the figure, the donut, the head):
  recolor_small  the Gaussians within 0.12-0.25 of a point on the subject's visible surface
  recolor_large  the donut's top 30-60 % (the icing side); elsewhere a ball of 0.45-0.7 radii
  add_small      a sphere of radius 0.06-0.10 (100-200 Gaussians) resting on the subject (seen from up)
  add_large      a sphere of radius 0.15-0.25 (300-600 Gaussians)
An addition's selected region (what the editor's relevance lights up and localization should find:
the part the object sits on) is the splat's Gaussians within 1.2-8 sphere radii of it (log-uniform;
widened by 1.25x steps while it holds fewer Gaussians than the object, as where a ball barely
touches a sparse surface), so from about the object's own size up to tens of times its Gaussian
count (`region_to_added` in each record). Colours, anchors and run seeds are random too; the prompt names the part.

Whole parts (--parts K, opt-in: K cases c25... after the 24, from a random stream of their own, so that
the 24 are drawn as without it; kinds alternate):
  recolor_part   a whole part recoloured ("make the <part> <colour>")
  add_part       a sphere of radius 0.06-0.25 (100-600 Gaussians) resting on a whole part, the part its region
On a synthetic scene (half of them) the part is one of the figure's named parts (body, head, nose, eyes,
arms) or the ground or the backdrop (sim.scene.part_masks); on the donut and the face (a quarter each) a
segment of the splat (sim.splat_truth.segment_parts: connected regions of similar colour and position), of
a size drawn log-uniformly between the smallest (30 Gaussians) and the largest segment, among those the
cameras see (less than 90 % hidden) as a region of their own (at least half of the segment's rendered
weight where it is most of the pixel: a colour class threaded through another part's Gaussians is no part).
Each record holds part_gaussians, side_view_fraction (of the views seeing the part, those under 20
degrees over its centre), hidden_fraction, view_fraction and shown_fraction (that share); the report
lists these cases apart ("whole parts") and holds every whole-part recolour to >= +8 dB.

Per case it records the footprint PSNR against the truth and what doing nothing scores there
(gain = the difference), the PSNR outside the footprint, of the unedited region, mask IoU,
Gaussians added against the truth's, source Gaussians deleted, UNet evaluations and seconds.
Writes OUT/truth_suite.json (seed, settings, one record per case), OUT/truth_suite.png (per-case
gain and outside-footprint PSNR, each sorted, with the targets drawn), and prints the distribution
and which cases miss which target:
  every case gain > 0 dB and >= +4 dB; median gain >= +8 dB (additions >= +8 dB, recolours >= +12
  dB); every whole-part recolour >= +8 dB; outside the footprint >= 45 dB every case, median >= 55
  dB; unedited region >= 50 dB; median mask IoU >= 0.9 (from exact 2D masks >= 0.95), every
  case's recall >= 0.9; no stopped run (every case has a real edit: a stop is a false safe stop); no source Gaussian
  deleted; Gaussians added <= 2x the truth's (a recolour: fewer than 1 % of its region).

Budget (the default, full): 24 cameras at 64², localization on 8 views, 3 refinement cycles x 60
iterations with 6 views each, 2 turntable frames, no checkpoints: 24 cases in about 17 min on one
core of a 2-core CPU (--threads 1: a donut case about 2 min, a face case 45 s, a synthetic one
22 s), inside 30 min; two halves side by side (--only) take about half that.
--quick (a test runs it; about 15 s): 3 cases on synthetic scenes only, 16 cameras at 48², one
refinement cycle of 10 iterations.
--replot redraws the chart and the distribution from OUT/truth_suite.json without running.
--only c03,c17 and --kind recolor|add re-run part of a draw, each case as in the whole draw (into
outputs/truth_suite/part unless --out is given). --localize-only (the override
system.stop_after=localize) ends every run after localization: a draw's mask IoU in about 2
minutes. --size 128 runs the draw at 128² views instead of 64² (the face photos scaled alike).
--repeats R runs each case R times (run seeds +0..+R-1: the editor's draws, the views, the
densification samples; the scene and the truth stay) and reports each case's median run with its
range: one run of a case differs from the next seed's by several dB outside the footprint
(docs/results.md), more than most changes between two codes. --compare BEFORE sets a run (or
--replot) against another run of the draw case by case, a difference inside both runs' ranges
marked `~`, and names the cases whose (median) run is worse by more than 1 dB.
"""
from __future__ import annotations

import argparse
import json
import os
import random

from gs_regional.bench.launching import ROOT
from gs_regional.bench.truth.cases import LOCALIZE_ONLY, JSON_NAME, PNG_NAME, draw
from gs_regional.bench.truth.compare import compare_report, load_payload
from gs_regional.bench.truth.report import chart, print_report
from gs_regional.bench.truth.run import resolve_only, run_suite

# The override of a run that ends after localization (and writes its metrics.json).


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=None, help="the draw's seed (default: a fresh one, printed)")
    ap.add_argument("--cases", type=int, default=None, help="cases to draw (default 24; 3 with --quick)")
    ap.add_argument("--parts", type=int, default=0, metavar="K",
                    help="also draw K whole-part cases after the others (c25...; their own random stream: the "
                         "first cases stay as drawn without it)")
    ap.add_argument("--quick", action="store_true", help="3 cases on synthetic scenes at tiny budgets (the test's mode)")
    ap.add_argument("--out", default=None,
                    help=f"folder for {JSON_NAME}, {PNG_NAME}, the scenes, the face fit and the runs (default "
                         "outputs/truth_suite; with --only or --kind outputs/truth_suite/part, so that a whole "
                         "draw's results are not overwritten)")
    ap.add_argument("--size", type=int, default=None, metavar="PX",
                    help="the views' side in pixels (default 64; 48 with --quick): the same draw at another resolution")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: the cores this process may use)")
    ap.add_argument("--replot", action="store_true", help=f"no runs: the chart and the distribution of OUT/{JSON_NAME}")
    ap.add_argument("--draw-only", action="store_true", help="print the drawn cases and stop")
    ap.add_argument("--resolve-only", action="store_true",
                    help="prepare the scenes and place every drawn case on its splat (anchors, truth counts), no runs")
    ap.add_argument("--strict", action="store_true", help="exit 1 when a target is missed")
    ap.add_argument("--repeats", type=int, default=1, metavar="R",
                    help="run each case R times with run seeds +0..+R-1 and report each case's median run and the "
                         "range (default 1; R times the time)")
    ap.add_argument("--compare", default=None, metavar="BEFORE",
                    help="after the run (or with --replot), print each case's gain and outside PSNR against "
                         "another run of the draw (its truth_suite.json or folder), e.g. the code before a change")
    # One value each, so that the overrides after them stay overrides.
    ap.add_argument("--only", default="", metavar="IDS", help="run only these cases of the draw, e.g. c03,c17")
    ap.add_argument("--kind", default=None, choices=["recolor", "add"],
                    help="run only the recolours or the additions of the draw")
    ap.add_argument("--localize-only", action="store_true",
                    help=f"end every run after localization ({LOCALIZE_ONLY}): the draw's mask IoUs in minutes")
    ap.add_argument("overrides", nargs="*", help="launch.py overrides (key=value) for every case, e.g. an ablation: "
                    "system.ablation.localize_with_truth=true")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats {args.repeats}: need at least 1 run a case")
    only, kinds = [i.strip() for i in args.only.split(",") if i.strip()], [args.kind] if args.kind else []
    if args.out is None:
        args.out = os.path.join(ROOT, "outputs", "truth_suite", *(["part"] if only or kinds else []))
    if args.replot:
        payload = load_payload(args.out, "--replot")
    else:
        seed = args.seed if args.seed is not None else random.SystemRandom().randrange(1_000_000)
        n = args.cases or (3 if args.quick else 24)
        print(f"truth suite seed: {seed} ({n} cases{f' + {args.parts} whole parts' if args.parts else ''}"
              f"{', quick' if args.quick else ''}; rerun this draw with --seed {seed})", flush=True)
        if args.draw_only:
            for c in draw(seed, n, args.quick, args.parts):
                print(json.dumps(c))
            return 0
        import torch

        if args.resolve_only:
            return resolve_only(seed, n, args.quick, args.out, args.size, args.parts, only)
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        torch.set_num_threads(max(1, min(args.threads or cores, cores)))
        overrides = list(args.overrides) + ([LOCALIZE_ONLY] if args.localize_only else [])
        payload = run_suite(seed, n, args.quick, args.out, overrides, only, kinds, args.size, args.repeats, args.parts)
    chart(payload, os.path.join(args.out, PNG_NAME))
    result = print_report(payload)
    if args.compare:
        compare_report(load_payload(args.compare), payload, (args.compare, args.out))
    if "wall_seconds" in payload:
        print(f"\nwall time {payload['wall_seconds']:.0f} s; {os.path.join(args.out, JSON_NAME)}, "
              f"{os.path.join(args.out, PNG_NAME)}")
    return 1 if args.strict and any(met is False for _, met, _, _ in result) else 0
