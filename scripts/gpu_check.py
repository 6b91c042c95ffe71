#!/usr/bin/env python
"""First contact with a GPU: one table of what works on this CUDA machine, in under 10 minutes.

    python scripts/gpu_check.py [--out outputs/gpu_check/gpu_check.json] [--budget 570]
    make gpu-check            # the same, after installing gsplat (the `gsplat` extra) if it is missing

Without CUDA it prints one line and exits 1; nothing is checked:
    gpu-check: no CUDA device (torch.cuda.is_available() is False); nothing was checked

The checks, in order (each a function `check_*(ctx) -> results` below, run in a child process of its
own with a time limit, so that a crash, a hang or an out-of-memory error of one is recorded as its row
and the others still run; its peak CUDA memory is its own):

  priors           build (first time, on the CPU) or find the real-size random-weight folders of
                   InstructPix2Pix and Depth Anything (gs_regional/testing/real_size_models.py), cached
                   in ~/.cache/gs_regional/priors (--models-dir)
  gsplat_vs_torch  gsplat-rasterizer against torch-rasterizer on the GPU, one random SH-3 scene
                   (scripts/bench_renderer.py's, 50k Gaussians at 512²): max abs difference of rgb,
                   alpha, depth (forward) and of every parameter's gradient and means2d's under a
                   weighted rgb loss (backward; bwd_max_rel: the largest, relative to that gradient's
                   largest value); failed above tests/test_renderer.py's tolerances (1e-3 forward,
                   1e-2 relative backward), except that up to 1e-4 of the pixels may differ by up to
                   1/255 forward: a Gaussian at the alpha cut-off, see CUTOFF_MAX. The first call
                   includes gsplat's JIT build of its CUDA kernels when no prebuilt one is installed
                   (once; it needs nvcc).
  ip2p_fp16        InstructPix2Pix from the real-size folder in float16 at 512²: load time, one edit
  ip2p_bf16        of 1 DDIM step and one of 20 (each = VAE encode + steps + decode), the guided step
                   (3-branch UNet + scheduler step) = (t20 - t1) / 19, one relevance map, weights and
                   peak CUDA memory, and whether the output is finite
  bench_pipeline   scripts/bench_pipeline.py --models real-size --fp16 at 512² with the synthetic
                   scene resampled to 1,000,000 Gaussians (--gaussians), a short schedule (1 cycle of
                   100 steps, 8 localization views, m = 8; no in2n): per-stage seconds, UNet
                   evaluations, peak CUDA memory
  donut_edit       the donut (../shared/data/donut/donut.ply, or $GS_REGIONAL_DATA) edited end to end
                   with configs/donut_add.yaml through launch.main on the GPU, its simulated priors
                   replaced by the real-size random-weight IP2P and Depth Anything, at 512², renderer
                   auto, the config's schedule (3 cycles of 100 steps, 12 localization views, m = 8):
                   wall time per stage (save/metrics.json), UNet evaluations, peak CUDA memory
  two_process      with 2 or more GPUs: launch.py --config configs/demo.yaml --train --gpu 0,1
                   trainer.devices=2; a failure is reported with the last line of its output

A check that needs another (the priors) is skipped when that one did not pass. The budget (--budget,
default 570 s) bounds the whole: each check runs for at most its own limit or what is left of the
budget, and once less than 20 s is left the remaining checks are skipped, saying so.

It prints the table (markdown, for the README) and writes it as JSON (--out) with the GPU names
(torch.cuda.get_device_name), the torch, CUDA, gsplat, diffusers, transformers and lightning
versions. Per-check logs go to logs/ beside the JSON, runs to runs/. Exit status: 0 when every check
passed or was skipped, 1 without CUDA, 3 when a check failed.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib.util
import inspect
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPTS = os.path.join(ROOT, "scripts")
for _p in (ROOT, SCRIPTS):
    if _p not in sys.path:
        sys.path.insert(0, _p)

SCHEMA_VERSION = 1
NO_CUDA_LINE = "gpu-check: no CUDA device (torch.cuda.is_available() is False); nothing was checked"
DEFAULT_OUT = os.path.join("outputs", "gpu_check", "gpu_check.json")
DEFAULT_BUDGET_S = 570.0  # the whole run stays under 10 minutes with the start-up around it
MIN_CHECK_S = 20.0  # with less than this left, the remaining checks are skipped
EXIT_NO_CUDA = 1
EXIT_FAILED = 3
SHARED_DATA = os.environ.get("GS_REGIONAL_DATA") or os.path.join(os.path.dirname(ROOT), "shared", "data")
DONUT = os.path.join(SHARED_DATA, "donut", "donut.ply")
PROMPT = "put a cherry on top"
# The real-size runs on the GPU (bench_pipeline and the donut): short schedules that fit the budget.
GPU_SETTINGS = dict(device="cuda", models="real-size", resolution=512, gaussians=1_000_000, render_gaussians=50_000,
                    schedule=dict(cycles=1, t_schedule=[750], shape_t_schedule=[450], iterations=100, m=8,
                                  max_views=8, densify_every=50, turntable_frames=8, ddim_steps=20))
# --smoke-on-cpu (a developer's check of the wiring, not a measurement): tiny models, small sizes.
CPU_SMOKE_SETTINGS = dict(device="cpu", models="tiny", resolution=64, gaussians=20_000, render_gaussians=2_000,
                          schedule=dict(cycles=1, t_schedule=[750], shape_t_schedule=[750], iterations=6, m=2,
                                        max_views=4, densify_every=3, turntable_frames=2, ddim_steps=4))
# Tolerances of tests/test_renderer.py::test_gsplat_agrees_with_torch_rasterizer.
FORWARD_TOL = 1e-3  # rgb and alpha, absolute; depth, relative on pixels with alpha > 0.5
BACKWARD_TOL = 1e-2  # gradients, max abs difference relative to the largest gradient
# A Gaussian whose alpha at a pixel sits at the 1/255 cut-off can fall on either side of it in the two
# renderers (float rounding); that pixel then differs by up to its contribution, below 1/255. Seen on the
# H200: one pixel of 262,144 at 1.26e-3 (50k Gaussians, 512²), the 99.9th percentile at 1.7e-6. So a few
# pixels may pass FORWARD_TOL, none CUTOFF_MAX.
CUTOFF_MAX = 1 / 255
CUTOFF_FRACTION = 1e-4  # of the pixels, at most, beyond FORWARD_TOL


class Skip(Exception):
    """Raised by a check that cannot run here; its message is the reason in the table."""


class CheckFailed(Exception):
    """Raised by a check that ran and failed; its message is the reason, as it is."""


@dataclass
class Check:
    name: str
    func: Callable[[dict], dict]  # module-level function: it runs in a child process
    limit_s: float
    what: str
    needs: Tuple[str, ...] = ()  # checks that must have passed first
    min_gpus: int = 0  # skipped with fewer GPUs


# ------------------------------------------------------------------------------------- helpers
def last_line(text: str, limit: int = 300) -> str:
    """The last non-empty line of `text` (the error's last line), at most `limit` characters."""
    lines = [ln.strip() for ln in str(text).strip().splitlines() if ln.strip()]
    line = lines[-1] if lines else ""
    return line if len(line) <= limit else line[: limit - 3] + "..."


def _sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _gib(nbytes: Optional[float]) -> Optional[float]:
    return None if nbytes is None else round(nbytes / 2**30, 3)


def _newest_trial(root: str, name: str) -> str:
    folder = os.path.join(root, name)
    trials = sorted((os.path.join(folder, d) for d in os.listdir(folder)), key=os.path.getmtime) if os.path.isdir(folder) else []
    if not trials:
        raise CheckFailed(f"the run left no trial folder under {folder}")
    return trials[-1]


def _metrics(trial: str) -> dict:
    path = os.path.join(trial, "save", "metrics.json")
    if not os.path.isfile(path):
        raise CheckFailed(f"the run wrote no {path}")
    with open(path) as f:
        return json.load(f)


def _stage_results(metrics: dict) -> Dict[str, Any]:
    out = {f"{k}_s": v for k, v in metrics.get("seconds", {}).items()}
    for key in ("unet_evals", "gaussians_before", "gaussians_after"):
        if key in metrics:
            out[key] = metrics[key]
    return out


class _Tee:
    """A stream that writes to `stream` and keeps a copy (the last line of a failed run's output)."""

    def __init__(self, stream):
        self.stream, self.parts = stream, []

    def write(self, s):
        self.parts.append(s)
        return self.stream.write(s)

    def flush(self):
        self.stream.flush()

    def isatty(self):
        return False

    def text(self) -> str:
        return "".join(self.parts)


# -------------------------------------------------------------------------------------- checks
def check_priors(ctx: dict) -> dict:
    """Build (once) or find the random-weight prior folders of ctx['models']."""
    from gs_regional.testing.real_size_models import cached_priors

    t0 = time.perf_counter()
    folders = cached_priors(ctx["models"], ctx.get("models_dir"))
    seconds = time.perf_counter() - t0
    return {"models": ctx["models"], "seconds_to_build_or_find": round(seconds, 2), **folders, "_ctx": {"priors": folders}}


def _renderer_auto(device: str) -> str:
    """The renderer `renderer_type: auto` picks for a run on `device` (in this environment)."""
    import torch

    from gs_regional.renderers.select import resolve_renderer_type

    return resolve_renderer_type("auto", torch.device(device))[0]


def render_comparison(ctx: dict, n: Optional[int] = None, size: Optional[int] = None,
                      other: str = "gsplat-rasterizer") -> dict:
    """`other` (gsplat-rasterizer) against torch-rasterizer on one random SH-3 scene: max abs
    differences of the renders and of every gradient of a weighted rgb loss."""
    import torch

    from gs_regional.bench.renderer import make_scene
    from gs_regional.registry import find

    device = ctx["device"]
    n = n or ctx["render_gaussians"]
    size = size or min(ctx["resolution"], 512)
    model, cam = make_scene(n, size, device)
    bg = torch.tensor([0.2, 0.5, 0.9], device=device)
    weights = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(1)).to(device)
    label = other.split("-")[0] if other != "torch-rasterizer" else "other"  # "gsplat"
    renderers = {"torch": find("torch-rasterizer")(), "other": find(other)()}
    out, grads, seconds = {}, {}, {}
    for name, r in renderers.items():
        t0 = time.perf_counter()
        r.render(model, cam, background=bg)  # the first gsplat call builds its kernels if it must
        _sync(device)
        seconds[f"{name if name == 'torch' else label}_first_call_s"] = time.perf_counter() - t0
        times = []
        for _ in range(3):
            model.zero_grad(set_to_none=True)
            t0 = time.perf_counter()
            o = r.render(model, cam, background=bg)
            (o["rgb"] * weights).sum().backward()
            _sync(device)
            times.append(time.perf_counter() - t0)
        seconds[f"{name if name == 'torch' else label}_fwd_bwd_ms"] = 1000 * statistics.median(times)
        out[name] = {k: o[k].detach() for k in ("rgb", "alpha", "depth", "visible")}
        grads[name] = {p: t.grad.detach().clone() for p, t in model.named_parameters()}
        grads[name]["means2d"] = o["means2d"].grad.detach().clone()
    a, b = out["torch"], out["other"]
    solid = a["alpha"] > 0.5
    # per pixel: rgb (largest channel) and alpha absolute, depth relative where the pixel is solid
    diffs = {"rgb": (a["rgb"] - b["rgb"]).abs().amax(-1), "alpha": (a["alpha"] - b["alpha"]).abs().reshape(size, size),
             "depth": torch.where(solid, (a["depth"] - b["depth"]).abs() / a["depth"].clamp_min(1e-12), 0.0).reshape(size, size)}
    res: Dict[str, Any] = {"gaussians": n, "size": size, "visible_torch": int(a["visible"].sum()),
                           f"visible_{label}_only": int((b["visible"] & ~a["visible"]).sum()),
                           "fwd_rgb_max_abs": float(diffs["rgb"].max()), "fwd_alpha_max_abs": float(diffs["alpha"].max()),
                           "fwd_depth_max_rel": float(diffs["depth"].max()),
                           # how the difference is spread: a few pixels at a Gaussian's cut-off, or many
                           "fwd_rgb_p999_abs": float(torch.quantile(diffs["rgb"].flatten().float(), 0.999)),
                           "fwd_pixels_over_tol": int(torch.stack(list(diffs.values())).amax(0).gt(FORWARD_TOL).sum())}
    both = a["visible"] & b["visible"]
    worst, worst_name = 0.0, None
    for p, ga in grads["torch"].items():
        gb = grads["other"][p]
        if p == "means2d":  # compared where both renderers project the Gaussian
            ga, gb = ga[both], gb[both]
        diff = float((ga - gb).abs().max()) if ga.numel() else 0.0
        rel = diff / max(float(ga.abs().max()) if ga.numel() else 0.0, 1e-12)
        res[f"bwd_{p}_max_abs"] = diff
        if worst_name is None or rel > worst:
            worst, worst_name = rel, p
    # the largest of the gradients' max abs differences, relative to that gradient's largest value
    res.update({"bwd_max_rel": worst, "bwd_max_rel_of": worst_name})
    res.update({k: round(v, 4) for k, v in seconds.items()})
    problems = [] if float(grads["torch"]["means"].abs().max()) > 0 else ["no gradient reached the Gaussians' means"]
    allowed = int(CUTOFF_FRACTION * size * size)
    for k, d in diffs.items():
        worst_px, over = float(d.max()), int(d.gt(FORWARD_TOL).sum())
        what = f"forward {k}{' (relative)' if k == 'depth' else ''} {worst_px:.2e}"
        if worst_px > CUTOFF_MAX:
            problems.append(f"{what} > {CUTOFF_MAX:.2e} (more than a Gaussian at the 1/255 cut-off)")
        elif over > allowed:
            problems.append(f"{what} > {FORWARD_TOL:g} at {over} pixels (at most {allowed} may, at a Gaussian's cut-off)")
    if worst > BACKWARD_TOL:
        problems.append(f"the gradient of {worst_name} differs by {worst:.2e} of its largest value (> {BACKWARD_TOL:g})")
    if problems:
        res["_fail"] = "; ".join(problems)
    return res


def check_gsplat_vs_torch(ctx: dict) -> dict:
    import torch

    from gs_regional.renderers import gsplat_rasterizer

    if not ctx["device"].startswith("cuda") or not torch.cuda.is_available():
        raise Skip("gsplat's kernels need a CUDA device")
    if gsplat_rasterizer._gsplat is None:
        err = gsplat_rasterizer._GSPLAT_IMPORT_ERROR
        why = f"gsplat does not import ({type(err).__name__}: {last_line(str(err))})"
        if isinstance(err, ModuleNotFoundError):
            raise Skip(f"{why}; pip install 'gs_regional[gsplat]' (make gpu-check installs it)")
        raise CheckFailed(why)
    return render_comparison(ctx)


def ip2p_step(ctx: dict, dtype: str) -> dict:
    """Load IP2P from ctx's priors in `dtype` and time its guided step at ctx['resolution']²."""
    import torch

    from gs_regional.guidance.instructpix2pix import InstructPix2Pix

    device = ctx["device"]
    cuda = device.startswith("cuda")
    if dtype == "bfloat16" and cuda and not torch.cuda.is_bf16_supported():
        raise Skip(f"{torch.cuda.get_device_name()} does not support bfloat16")
    steps = int(ctx["schedule"]["ddim_steps"])
    t0 = time.perf_counter()
    guidance = InstructPix2Pix({"pretrained": ctx["priors"]["ip2p"], "dtype": dtype, "device": device,
                                "local_files_only": True, "num_inference_steps": steps})
    _sync(device)
    res: Dict[str, Any] = {"dtype": str(guidance.dtype).replace("torch.", ""), "load_s": time.perf_counter() - t0}
    if cuda:
        res["weights_gib"] = _gib(torch.cuda.memory_allocated())
        torch.cuda.reset_peak_memory_stats()
    side = int(ctx["resolution"])
    image = torch.rand(1, side, side, 3, generator=torch.Generator().manual_seed(0))

    def edit(n_steps: int):
        guidance.cfg.num_inference_steps = n_steps
        t = time.perf_counter()
        out = guidance.edit(image, image, PROMPT, seed=0)
        _sync(device)
        return time.perf_counter() - t, out

    edit(1)  # warm-up (lazy set-up, kernel selection)
    one = statistics.median(edit(1)[0] for _ in range(3))
    full, out = edit(steps)
    t0 = time.perf_counter()
    relevance = guidance.relevance(image, PROMPT, timestep=500)
    _sync(device)
    res.update({
        "edit_1_step_s": one, f"edit_{steps}_steps_s": full,
        "guided_step_s": (full - one) / max(steps - 1, 1),
        "relevance_s": time.perf_counter() - t0,
        "resolution": side, "unet_evals": guidance.unet_evals,
        "finite": bool(torch.isfinite(out).all() and torch.isfinite(relevance).all()),
        "out_dtype": str(out.dtype).replace("torch.", ""),
    })
    if cuda:
        res["peak_gib"] = _gib(torch.cuda.max_memory_allocated())
    res = {k: round(v, 4) if isinstance(v, float) else v for k, v in res.items()}
    if not res["finite"]:
        res["_fail"] = f"non-finite output in {dtype} (random weights; the released ones may behave otherwise)"
    return res


def check_ip2p_fp16(ctx: dict) -> dict:
    return ip2p_step(ctx, "float16")


def check_ip2p_bf16(ctx: dict) -> dict:
    return ip2p_step(ctx, "bfloat16")


def bench_pipeline_argv(ctx: dict) -> List[str]:
    s = ctx["schedule"]
    argv = ["--models", ctx["models"], "--out", os.path.join(ctx["work"], "bench_pipeline"), "--device", ctx["device"],
            "--resolution", str(ctx["resolution"]), "--gaussians", str(ctx["gaussians"]), "--in2n-steps", "0",
            "--cycles", str(s["cycles"]), "--t-schedule", *map(str, s["t_schedule"]),
            "--shape-t-schedule", *map(str, s["shape_t_schedule"]), "--iterations", str(s["iterations"]),
            "--m", str(s["m"]), "--max-views", str(s["max_views"]), "--densify-every", str(s["densify_every"]),
            "--turntable-frames", str(s["turntable_frames"]), "--ddim-steps", str(s["ddim_steps"])]
    if ctx["device"].startswith("cuda"):
        argv.append("--fp16")
    if ctx.get("models_dir"):
        argv += ["--models-dir", ctx["models_dir"]]
    return argv


def check_bench_pipeline(ctx: dict) -> dict:
    from gs_regional.bench import pipeline as bench_pipeline

    try:
        report = bench_pipeline.main(bench_pipeline_argv(ctx))
    except SystemExit as e:  # bench_pipeline ends a failed step with SystemExit(message with its log's tail)
        if e.code in (0, None):
            raise
        raise CheckFailed(last_line(str(e.code))) from None
    run = report["runs"]["regional-edit"]
    res = {"gaussians": report["scene"]["gaussians"], "resolution": report["scene"]["width"], "dtype": report["dtype"],
           "renderer": _renderer_auto(ctx["device"]),
           "wall_s": run["wall_seconds"], "startup_s": run["startup_seconds"],
           **{f"{k}_s": v for k, v in run["seconds"].items()}, "unet_evals": run["unet_evals"],
           "cuda_peak_gib": _gib(run["cuda_peak_bytes"]), "peak_rss_gib": _gib(run["peak_rss_bytes"]),
           "load_unet_call_s": report["load"]["seconds"]["unet_call"],
           "report": os.path.join(ctx["work"], "bench_pipeline", "bench_pipeline.json")}
    return res


def donut_argv(ctx: dict) -> List[str]:
    from gs_regional.bench import pipeline as bench_pipeline

    s, priors, side = ctx["schedule"], ctx["priors"], ctx["resolution"]
    argv = ["--config", os.path.join(ROOT, "configs", "donut_add.yaml"), "--train",
            f"exp_root_dir={os.path.join(ctx['work'], 'runs')}", "name=gpu-check-donut", f"tag={ctx['models']}",
            f"data.ply={ctx['donut']}", f"data.width={side}", f"data.height={side}", "system.renderer_type=auto",
            "system.guidance_type=instructpix2pix", f"system.guidance.pretrained={priors['ip2p']}",
            "system.guidance.local_files_only=true", f"system.guidance.num_inference_steps={s['ddim_steps']}",
            "system.depth_type=depth-anything", f"system.depth.pretrained={priors['depth_anything']}",
            "system.depth.local_files_only=true", f"system.eval.turntable_frames={s['turntable_frames']}",
            *bench_pipeline.RANDOM_WEIGHTS_NO_STOPS, "trainer.enable_progress_bar=false"]
    if ctx["device"].startswith("cuda"):
        argv[2:2] = ["--gpu", "0"]
    if ctx.get("smoke"):  # the CPU smoke run: the donut config's 3 x 100 steps would take too long
        argv += [f"system.refine.cycles={s['cycles']}", f"system.refine.t_schedule={s['t_schedule']}",
                 f"system.refine.shape_t_schedule={s['shape_t_schedule']}",
                 f"system.refine.iterations_per_cycle={s['iterations']}", f"system.refine.m={s['m']}",
                 f"system.localization.max_views={s['max_views']}", f"system.densify.every={s['densify_every']}"]
    return argv


def check_donut_edit(ctx: dict) -> dict:
    import torch

    from gs_regional.launch import main as launch_main

    if not os.path.isfile(ctx["donut"]):
        raise Skip(f"the donut is not at {ctx['donut']} (set GS_REGIONAL_DATA to the folder holding donut/donut.ply)")
    tee = _Tee(sys.stderr)
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(tee):
        rc = launch_main(donut_argv(ctx), custom_dir=os.path.join(ROOT, "custom"))
    wall = time.perf_counter() - t0
    if rc != 0:
        raise CheckFailed(f"launch.py exited {rc}: {last_line(tee.text())}")
    trial = _newest_trial(os.path.join(ctx["work"], "runs"), "gpu-check-donut")
    metrics = _metrics(trial)
    if metrics.get("stopped"):
        raise CheckFailed(f"the edit stopped early ({metrics['stopped']}): the stages after it were not timed")
    res = {"resolution": ctx["resolution"], "renderer": _renderer_auto(ctx["device"]), "wall_s": round(wall, 2),
           **_stage_results(metrics), "trial": trial}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        res["cuda_peak_gib"] = _gib(torch.cuda.max_memory_allocated())
    return res


def two_process_command(ctx: dict) -> List[str]:
    return [sys.executable, os.path.join(ROOT, "launch.py"), "--config", os.path.join(ROOT, "configs", "demo.yaml"),
            "--train", "--gpu", "0,1", "trainer.devices=2", f"exp_root_dir={os.path.join(ctx['work'], 'runs')}",
            "name=gpu-check-2proc", "trainer.enable_progress_bar=false"]


def check_two_process(ctx: dict) -> dict:
    cmd = two_process_command(ctx)
    log_path = os.path.join(ctx["work"], "logs", "two_process.launch.log")
    print("$", " ".join(cmd), f"> {log_path}", flush=True)
    t0 = time.perf_counter()
    with open(log_path, "w") as log:
        rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
    wall = time.perf_counter() - t0
    with open(log_path) as f:
        text = f.read()
    if rc != 0:
        raise CheckFailed(f"exit code {rc}: {last_line(text)}")
    trial = _newest_trial(os.path.join(ctx["work"], "runs"), "gpu-check-2proc")
    return {"wall_s": round(wall, 2), **_stage_results(_metrics(trial)), "trial": trial}


CHECKS: List[Check] = [
    Check("priors", check_priors, 240, "the real-size random-weight prior folders (built once, cached)"),
    Check("gsplat_vs_torch", check_gsplat_vs_torch, 240, "gsplat against the torch rasterizer, forward and backward"),
    Check("ip2p_fp16", check_ip2p_fp16, 120, "IP2P guided step at 512², float16, real-size weights", needs=("priors",)),
    Check("ip2p_bf16", check_ip2p_bf16, 120, "IP2P guided step at 512², bfloat16, real-size weights", needs=("priors",)),
    Check("bench_pipeline", check_bench_pipeline, 240, "bench_pipeline: the regional edit at 1M Gaussians, 512², fp16",
          needs=("priors",)),
    Check("donut_edit", check_donut_edit, 200, "the donut edited end to end with real-size random-weight priors",
          needs=("priors",)),
    Check("two_process", check_two_process, 180, "launch.py configs/demo.yaml with trainer.devices=2", min_gpus=2),
]


# -------------------------------------------------------------------------------------- runner
def _row(check: Check, status: str, seconds: float = 0.0, results: Optional[dict] = None,
         reason: Optional[str] = None, **extra) -> dict:
    return {"name": check.name, "what": check.what, "status": status, "seconds": round(seconds, 2),
            "results": results or {}, "reason": reason, **extra}


def _func_spec(func: Callable) -> str:
    return f"{os.path.abspath(inspect.getsourcefile(func))}:{func.__name__}"


def run_check(check: Check, ctx: dict, limit_s: float, log_dir: str) -> dict:
    """Run `check.func(ctx)` in a child process for at most `limit_s` seconds; its row."""
    os.makedirs(log_dir, exist_ok=True)
    result_path = os.path.join(log_dir, f"{check.name}.result.json")
    log_path = os.path.join(log_dir, f"{check.name}.log")
    ctx_path = os.path.join(log_dir, f"{check.name}.ctx.json")
    if os.path.exists(result_path):
        os.remove(result_path)
    with open(ctx_path, "w") as f:
        json.dump(ctx, f)
    cmd = [sys.executable, os.path.abspath(__file__), "--child", _func_spec(check.func), ctx_path, result_path]
    env = dict(os.environ, HF_HUB_OFFLINE="1", TRANSFORMERS_OFFLINE="1",
               PYTHONPATH=os.pathsep.join(filter(None, [ROOT, SCRIPTS, os.environ.get("PYTHONPATH")])))
    t0 = time.monotonic()
    timed_out = False
    with open(log_path, "w") as log:
        # Its own session: on time-out the whole group (the launch runs and steps it starts) is ended.
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=ROOT, env=env,
                                start_new_session=True)
        try:
            rc = proc.wait(timeout=limit_s)
        except subprocess.TimeoutExpired:
            timed_out = True
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            rc = proc.wait()
    seconds = time.monotonic() - t0
    if timed_out:
        return _row(check, "failed", seconds, reason=f"timed out after {limit_s:.0f} s; log {log_path}", log=log_path)
    result = None
    if os.path.isfile(result_path):
        with open(result_path) as f:
            result = json.load(f)
    if result is None:
        with open(log_path, errors="replace") as f:
            tail = last_line(f.read())
        return _row(check, "failed", seconds, reason=f"exit code {rc}: {tail or '(no output)'}; log {log_path}", log=log_path)
    return _row(check, result["status"], seconds, result.get("results"), result.get("reason"), log=log_path)


def run_checks(checks: Sequence[Check], ctx: dict, budget_s: float, log_dir: str,
               clock: Callable[[], float] = time.monotonic, echo: Callable[[str], None] = print) -> List[dict]:
    """Run the checks in order within `budget_s`; one row each (ok, failed or skipped with why)."""
    start = clock()
    rows: Dict[str, dict] = {}
    for check in checks:
        used = clock() - start
        left = budget_s - used
        reason = None
        if ctx.get("gpus", 0) < check.min_gpus:
            reason = f"needs {check.min_gpus} GPUs; this machine has {ctx.get('gpus', 0)}"
        for dep in check.needs:
            if reason is None and (dep not in rows or rows[dep]["status"] != "ok"):
                reason = f"needs '{dep}', which {rows[dep]['status'] if dep in rows else 'did not run'}"
        if reason is None and left < MIN_CHECK_S:
            reason = f"the {budget_s:.0f} s budget is spent ({used:.0f} s used)"
        if reason is not None:
            row = _row(check, "skipped", reason=reason)
        else:
            limit = min(check.limit_s, left)
            echo(f"gpu-check: {check.name} (at most {limit:.0f} s): {check.what}")
            row = run_check(check, ctx, limit, log_dir)
        ctx.update(row["results"].pop("_ctx", {}) if row["status"] == "ok" else {})
        row["results"].pop("_ctx", None)
        rows[check.name] = row
        echo(f"gpu-check: {check.name}: {row['status']}" + (f" ({row['reason']})" if row["reason"] else "")
             + (f" in {row['seconds']:.1f} s" if row["status"] != "skipped" else ""))
    return list(rows.values())


def child_main(spec: str, ctx_path: str, result_path: str) -> int:
    """Run one check function and write {"status", "results", "reason"} to `result_path`."""
    # Checks defined elsewhere (tests) import Skip/CheckFailed from `gpu_check`: make that this module.
    sys.modules.setdefault("gpu_check", sys.modules[__name__])
    path, name = spec.rsplit(":", 1)
    if os.path.abspath(path) == os.path.abspath(__file__):
        func = globals()[name]
    else:
        module_spec = importlib.util.spec_from_file_location(f"_gpu_check_{name}", path)
        module = importlib.util.module_from_spec(module_spec)
        module_spec.loader.exec_module(module)
        func = getattr(module, name)
    with open(ctx_path) as f:
        ctx = json.load(f)
    results: dict = {}
    reason = None
    try:
        results = dict(func(ctx) or {})
        status = "ok"
        if results.get("_fail"):
            status, reason = "failed", str(results.pop("_fail"))
    except Skip as e:
        status, reason = "skipped", str(e)
    except CheckFailed as e:
        traceback.print_exc()
        status, reason = "failed", str(e)
    except BaseException as e:  # noqa: BLE001 - recorded as the row's error
        traceback.print_exc()
        status, reason = "failed", f"{type(e).__name__}: {last_line(str(e))}" if str(e).strip() else type(e).__name__
    torch = sys.modules.get("torch")
    if torch is not None and status == "ok" and torch.cuda.is_available() and torch.cuda.is_initialized():
        results.setdefault("cuda_peak_gib", _gib(torch.cuda.max_memory_allocated()))
    with open(result_path, "w") as f:
        json.dump({"status": status, "results": results, "reason": reason}, f, default=str)
    sys.stdout.flush()
    return 0 if status != "failed" else 1


# -------------------------------------------------------------------------------------- report
def environment() -> dict:
    """GPU names and memory, versions of torch, CUDA, gsplat and the model libraries."""
    from importlib import metadata

    import torch

    def version(pkg: str) -> Optional[str]:
        try:
            return metadata.version(pkg)
        except metadata.PackageNotFoundError:
            return None

    n = torch.cuda.device_count() if torch.cuda.is_available() else 0
    gpus = [torch.cuda.get_device_name(i) for i in range(n)]
    return {
        "gpu": gpus[0] if gpus else None, "gpus": gpus,
        "gpu_memory_gib": [_gib(torch.cuda.get_device_properties(i).total_memory) for i in range(n)],
        "torch": torch.__version__, "cuda": torch.version.cuda, "gsplat": version("gsplat"),
        "diffusers": version("diffusers"), "transformers": version("transformers"), "lightning": version("lightning"),
        "python": platform.python_version(), "host": platform.node(), "cpu_cores": os.cpu_count(),
    }


def build_report(rows: List[dict], env: dict, budget_s: float, wall_s: float, settings: Optional[dict] = None) -> dict:
    counts = {s: sum(r["status"] == s for r in rows) for s in ("ok", "failed", "skipped")}
    return {"schema": SCHEMA_VERSION, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **env,
            "budget_s": budget_s, "wall_s": round(wall_s, 1), "counts": counts, "settings": settings or {}, "rows": rows}


def format_value(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return f"{v:,}"
    if isinstance(v, float):
        if v == 0:
            return "0"
        return f"{v:.2e}" if abs(v) < 1e-2 else f"{v:.3g}" if abs(v) < 1000 else f"{v:,.0f}"
    return str(v)


def format_results(results: dict) -> str:
    # Paths (trials, reports, folders) are in the JSON; the table keeps the numbers.
    return ", ".join(f"{k} {format_value(v)}" for k, v in results.items()
                     if not (isinstance(v, str) and os.sep in v))


def format_table(report: dict) -> str:
    gpus = report.get("gpus") or []
    head = (f"gpu-check on {report.get('gpu') or 'no GPU'} ({len(gpus)} GPU{'s' if len(gpus) != 1 else ''}), "
            f"torch {report.get('torch')} (CUDA {report.get('cuda') or '-'}), gsplat {report.get('gsplat') or 'not installed'}: "
            f"{report['counts']['ok']} ok, {report['counts']['failed']} failed, {report['counts']['skipped']} skipped "
            f"in {report['wall_s']:.0f} s (budget {report['budget_s']:.0f} s)")
    lines = [head, "", "| check | status | s | results | reason |", "| --- | --- | --- | --- | --- |"]
    for r in report["rows"]:
        cells = [r["name"], r["status"], f"{r['seconds']:.1f}" if r["status"] != "skipped" else "-",
                 format_results(r["results"]) or "-", (r["reason"] or "").replace("|", "/") or "-"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(report: dict, path: str) -> str:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(report, f, indent=2, default=str)
    os.replace(tmp, path)
    return path


# ---------------------------------------------------------------------------------------- main
def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=DEFAULT_OUT, help=f"the JSON report (default {DEFAULT_OUT}); logs/ and runs/ beside it")
    ap.add_argument("--budget", type=float, default=DEFAULT_BUDGET_S, help="seconds for all the checks together")
    ap.add_argument("--only", nargs="+", default=None, choices=[c.name for c in CHECKS], help="run only these checks")
    ap.add_argument("--models-dir", default=None, help="cache of the prior folders (default ~/.cache/gs_regional/priors)")
    ap.add_argument("--gaussians", type=int, default=None, help="bench_pipeline's scene size (default 1,000,000)")
    ap.add_argument("--require-cuda", action="store_true",
                    help="only say whether CUDA is there: the one line and exit 1 without it, exit 0 silently with it")
    ap.add_argument("--smoke-on-cpu", action="store_true", help=argparse.SUPPRESS)  # wiring check: tiny models, CPU
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    import torch

    if not torch.cuda.is_available() and not args.smoke_on_cpu:
        print(NO_CUDA_LINE, flush=True)
        return EXIT_NO_CUDA
    if args.require_cuda:
        return 0
    settings = json.loads(json.dumps(CPU_SMOKE_SETTINGS if args.smoke_on_cpu else GPU_SETTINGS))
    if args.gaussians:
        settings["gaussians"] = args.gaussians
    out = os.path.abspath(args.out)
    work = os.path.dirname(out)
    os.makedirs(os.path.join(work, "logs"), exist_ok=True)
    env = environment()
    ctx = {**settings, "smoke": bool(args.smoke_on_cpu), "models_dir": args.models_dir, "work": work,
           "donut": DONUT, "gpus": 0 if args.smoke_on_cpu else len(env["gpus"])}
    checks = [c for c in CHECKS if not args.only or c.name in args.only or (c.name == "priors" and
              any("priors" in d.needs for d in CHECKS if d.name in args.only))]
    print(f"gpu-check: {len(checks)} checks on {env['gpu'] or 'the CPU (smoke run: tiny models, the numbers mean nothing)'}, "
          f"budget {args.budget:.0f} s; logs in {os.path.join(work, 'logs')}", flush=True)
    t0 = time.monotonic()
    rows = run_checks(checks, ctx, args.budget, os.path.join(work, "logs"), echo=lambda s: print(s, flush=True))
    report = build_report(rows, env, args.budget, time.monotonic() - t0,
                          {k: v for k, v in ctx.items() if k not in ("priors",)})
    write_report(report, out)
    print()
    print(format_table(report))
    print(f"\nwrote {out}")
    return EXIT_FAILED if report["counts"]["failed"] else 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        sys.exit(child_main(*sys.argv[2:5]))
    sys.exit(main())
