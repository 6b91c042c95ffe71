"""Data-parallel editing (gs_regional/systems/parallel.py): the diffusion stages of one edit on 1,
2, ... processes, through the REAL code path.

    python scripts/bench_parallel.py --models tiny --out DIR                 # here: 1 and 2 CPU processes
    python scripts/bench_parallel.py --models real-size --out DIR            # a GPU machine: 1..N GPUs
    python scripts/bench_parallel.py --models real-size --out DIR --processes 1 2 4

Each run is `launch.py --config configs/edit.yaml --train` with InstructPix2Pix and Depth Anything
loaded with `from_pretrained` from random-weight folders (gs_regional/testing: `tiny`, or
`real-size` = the published shapes; built once and cached as for scripts/bench_pipeline.py), on
the synthetic figure written out as a user's scene, on k processes of Lightning's launcher:
`trainer.accelerator=cpu trainer.devices=k` on the CPU, `--gpu 0,...,k-1` on GPUs. From each
run's metrics.json it takes the stage seconds
  localize     the relevance maps of the localization views (shared out) and the lift (on every process)
  refine_edit  each cycle's partial denoising of the views near its frontal one (shared out)
  refine_train the training steps (one view a step: system.refine.views_per_step=1, so every run
               trains alike and the edits compare; the other processes wait for rank 0's view)
and the UNet evaluations and VAE calls (summed over the processes: the same for every k), and
writes DIR/bench_parallel.json and a table with each stage's speed-up over one process.

The images of random weights mean nothing: the runs never stop on a doubtful localization
(min_view_agreement=0, min_edit_coverage=0). On a CPU the processes share the cores (Lightning
gives each cores / k threads): the ratio says what the split costs and saves there, not what GPUs
gain.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys
import time
from types import SimpleNamespace
from typing import Dict, List, Optional

from gs_regional.bench.launching import ROOT

SCHEMA_VERSION = 1
STAGES = ("localize", "refine_edit", "refine_train")
# Per --models: the scene's resolution, localization views, views edited per cycle (m), cycles,
# training steps per cycle (short: training is not what is split) and DDIM steps of a full edit.
BUDGETS = {
    "tiny": dict(resolution=64, max_views=12, m=8, cycles=2, iterations=5, ddim_steps=20),
    "real-size": dict(resolution=512, max_views=24, m=20, cycles=3, iterations=10, ddim_steps=20),
}
T_SCHEDULE = [750, 500, 250]
SHAPE_T_SCHEDULE = [450, 350, 250]


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", choices=sorted(BUDGETS), required=True)
    ap.add_argument("--out", default=os.path.join(ROOT, "outputs", "bench_parallel"),
                    help="output folder: bench_parallel.json, the scene, the runs, logs (default outputs/bench_parallel)")
    ap.add_argument("--processes", type=int, nargs="+", default=None,
                    help="process counts to run (default: 1 2 on the CPU, 1..the GPUs on CUDA)")
    ap.add_argument("--device", choices=["cpu", "cuda"], default=None, help="default: cuda when available")
    ap.add_argument("--models-dir", default=None, help="cache of the built prior folders (default ~/.cache/gs_regional/priors)")
    ap.add_argument("--fp16", action="store_true", help="the priors in float16 (default float32)")
    ap.add_argument("--repeat", type=int, default=1, help="runs per process count (1, 2, ..., 1, 2, ...); the fastest counts")
    for key in ("resolution", "max_views", "m", "cycles", "iterations", "ddim_steps"):
        ap.add_argument(f"--{key.replace('_', '-')}", type=int, default=None)
    ap.add_argument("--gaussians", type=int, default=0, help="resample the scene to this many Gaussians")
    ap.add_argument("--prompt", default="give him a mustache")
    args = ap.parse_args(argv)
    for key, value in BUDGETS[args.models].items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if not 1 <= args.cycles <= len(T_SCHEDULE):
        ap.error(f"--cycles must be in 1..{len(T_SCHEDULE)}")
    import torch

    if args.device is None:
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    if args.device == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda: CUDA is not available")
    if args.processes is None:
        args.processes = list(range(1, torch.cuda.device_count() + 1)) if args.device == "cuda" else [1, 2]
    if args.device == "cuda" and max(args.processes) > torch.cuda.device_count():
        ap.error(f"--processes {max(args.processes)}: this machine has {torch.cuda.device_count()} GPU(s)")
    if min(args.processes) < 1 or args.repeat < 1:
        ap.error("--processes and --repeat must be >= 1")
    args.out = os.path.abspath(args.out)
    return args


def overrides(args, scene: dict, priors: Dict[str, str]) -> List[str]:
    """The runs' settings beyond configs/edit.yaml: the scene, the priors, the budget."""
    from gs_regional.bench.pipeline import common_overrides

    dtype = "float16" if args.fp16 else "float32"
    base = SimpleNamespace(fp16=args.fp16, device=args.device, prompt=args.prompt, ddim_steps=args.ddim_steps,
                           turntable_frames=2, renderer=None)
    lists = lambda xs: "[" + ",".join(map(str, xs[: args.cycles])) + "]"  # noqa: E731
    return [
        *common_overrides(base, scene, priors),
        f"system.depth.pretrained={priors['depth_anything']}", f"system.depth.dtype={dtype}",
        f"system.depth.device={args.device}", "system.depth.local_files_only=true",
        f"system.localization.max_views={args.max_views}", "system.localization.min_view_agreement=0",
        "system.localization.min_edit_coverage=0",
        f"system.refine.cycles={args.cycles}", f"system.refine.t_schedule={lists(T_SCHEDULE)}",
        f"system.refine.shape_t_schedule={lists(SHAPE_T_SCHEDULE)}", f"system.refine.m={args.m}",
        f"system.refine.iterations_per_cycle={args.iterations}", "system.refine.views_per_step=1",
        "system.eval.max_test_views=2",
    ]


def processes_args(args, k: int) -> List[str]:
    if args.device == "cuda":
        return ["--gpu", ",".join(str(i) for i in range(k))]
    return ["trainer.accelerator=cpu", f"trainer.devices={k}"]


def run_once(args, name: str, argv: List[str], env: Dict[str, str]) -> dict:
    log_path = os.path.join(args.out, "logs", f"{name}.log")
    cmd = [sys.executable, os.path.join(ROOT, "launch.py"), "--config", os.path.join(ROOT, "configs", "edit.yaml"),
           "--train", f"exp_root_dir={os.path.join(args.out, 'runs')}", f"name={name}", *argv]
    t0 = time.perf_counter()
    with open(log_path, "w") as log:
        rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=ROOT)
    wall = time.perf_counter() - t0
    if rc != 0:
        with open(log_path) as f:
            tail = f.read()[-4000:]
        raise SystemExit(f"run {name} failed (exit code {rc}); log {log_path}:\n{tail}")
    trials = sorted(glob.glob(os.path.join(args.out, "runs", name, "*")), key=os.path.getmtime)
    with open(os.path.join(trials[-1], "save", "metrics.json")) as f:
        m = json.load(f)
    return {
        "processes": m.get("world_size", 1), "wall_seconds": round(wall, 3),
        "seconds": {s: m["seconds"].get(s) for s in STAGES},
        "unet_evals": m["unet_evals"], "vae_encodes": m["vae_encodes"], "vae_decodes": m["vae_decodes"],
        "gaussians_after": m["gaussians_after"], "trial": trials[-1],
    }


def speedups(runs: Dict[int, dict]) -> Dict[int, Dict[str, Optional[float]]]:
    """Each stage's seconds on 1 process over its seconds on k (None without a 1-process run)."""
    base = runs.get(1)
    out = {}
    for k, run in runs.items():
        out[k] = {}
        for stage in (*STAGES, "diffusion"):
            t1 = None if base is None else _stage(base, stage)
            tk = _stage(run, stage)
            out[k][stage] = round(t1 / tk, 3) if t1 and tk else None
    return out


def _stage(run: dict, stage: str) -> Optional[float]:
    s = run["seconds"]
    if stage == "diffusion":  # the stages whose work is shared out
        return (s.get("localize") or 0) + (s.get("refine_edit") or 0)
    return s.get(stage)


def table(report: dict) -> str:
    lines = [f"device: {report['device']['name']}; models {report['models']} ({report['dtype']}), {report['budget']['resolution']}², "
             f"{report['budget']['max_views']} localization views, {report['budget']['m'] + 1} views x "
             f"{report['budget']['cycles']} cycles"]
    head = f"{'processes':>9}  {'localize s':>10}  {'refine_edit s':>13}  {'refine_train s':>14}  {'UNet evals':>10}  " \
           f"{'wall s':>7}  {'speed-up: localize':>18}  {'refine_edit':>11}  {'both':>5}"
    lines += [head, "-" * len(head)]
    fmt = lambda v, spec: "-" if v is None else format(v, spec)  # noqa: E731
    for k in sorted(report["runs"], key=int):
        run, up = report["runs"][k], report["speedup"][k]
        s = run["seconds"]
        lines.append(f"{k:>9}  {fmt(s['localize'], '10.2f')}  {fmt(s['refine_edit'], '13.2f')}  "
                     f"{fmt(s['refine_train'], '14.2f')}  {run['unet_evals']:>10,}  {run['wall_seconds']:>7.1f}  "
                     f"{fmt(up['localize'], '17.2f')}x  {fmt(up['refine_edit'], '10.2f')}x  {fmt(up['diffusion'], '4.2f')}x")
    if not report["same_work"]:
        lines.append("warning: the runs did not spend the same UNet evaluations / VAE calls")
    return "\n".join(lines)


def main(argv=None) -> dict:
    args = parse_args(argv)
    from gs_regional.bench.pipeline import device_description, prepare_scene
    from gs_regional.testing.real_size_models import cached_priors

    os.makedirs(os.path.join(args.out, "logs"), exist_ok=True)
    env = dict(os.environ, HF_HUB_OFFLINE="1", TRANSFORMERS_OFFLINE="1")
    priors = cached_priors(args.models, args.models_dir)
    scene = prepare_scene(SimpleNamespace(ply=None, data=None, resolution=args.resolution, gaussians=args.gaussians),
                          os.path.join(args.out, "scene"))
    common = overrides(args, scene, priors)
    best: Dict[int, dict] = {}
    for r in range(args.repeat):
        for k in args.processes:
            name = f"p{k}" + (f"-r{r}" if args.repeat > 1 else "")
            run = run_once(args, name, [*common, *processes_args(args, k)], env)
            print(f"{k} process(es): localize {run['seconds']['localize']} s, refine_edit {run['seconds']['refine_edit']} s, "
                  f"wall {run['wall_seconds']} s", flush=True)
            if k not in best or _stage(run, "diffusion") < _stage(best[k], "diffusion"):
                best[k] = run
    work = {(r["unet_evals"], r["vae_encodes"], r["vae_decodes"]) for r in best.values()}
    report = {
        "schema": SCHEMA_VERSION, "models": args.models, "dtype": "float16" if args.fp16 else "float32",
        "device": device_description(args.device),
        "budget": {k: getattr(args, k) for k in ("resolution", "max_views", "m", "cycles", "iterations", "ddim_steps")},
        "scene": scene, "priors": priors, "repeat": args.repeat,
        "runs": {str(k): v for k, v in best.items()},
        "speedup": {str(k): v for k, v in speedups(best).items()},
        "same_work": len(work) == 1,
    }
    path = os.path.join(args.out, "bench_parallel.json")
    with open(path, "w") as f:
        json.dump(report, f, indent=2)
    print()
    print(table(report))
    print(f"\nwrote {path}")
    return report


def cli(argv=None) -> int:
    """The command line (scripts/bench_parallel.py): main, exit status 0 once the report is written."""
    main(argv)
    return 0
