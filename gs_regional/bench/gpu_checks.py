"""The GPU checks: what works on a CUDA machine, each check a function `check_*(ctx) -> results`
that the tests of tests/gpu/ run (marked `cuda`; `make gpu-check` runs them and summarises the
results each records with gpu_report.py). A check that cannot run here raises Skip, one that ran
and failed raises CheckFailed or returns its results with `_fail` (the reason).

  priors           build (first time, on the CPU) or find the real-size random-weight folders of
                   InstructPix2Pix and Depth Anything (gs_regional/testing/real_size_models.py), cached
                   in ~/.cache/gs_regional/priors (--models-dir)
  gsplat_vs_torch  gsplat-rasterizer against torch-rasterizer on the GPU, one random SH-3 scene
                   (renderer.py's, 50k Gaussians at 512²): max abs difference of rgb, alpha, depth
                   (forward) and of every parameter's gradient and means2d's under a weighted rgb loss
                   (backward; bwd_max_rel: the largest, relative to that gradient's largest value);
                   failed above tests/test_renderer.py's tolerances (1e-3 forward, 1e-2 relative
                   backward), except that up to 1e-4 of the pixels may differ by up to 1/255 forward:
                   a Gaussian at the alpha cut-off, see CUTOFF_MAX. The first call includes gsplat's
                   JIT build of its CUDA kernels when no prebuilt one is installed (once; it needs nvcc).
  ip2p_fp16        InstructPix2Pix from the real-size folder in float16 at 512²: load time, one edit
  ip2p_bf16        of 1 DDIM step and one of 20 (each = VAE encode + steps + decode), the guided step
                   (3-branch UNet + scheduler step) = (t20 - t1) / 19, one relevance map, weights and
                   peak CUDA memory, and whether the output is finite
  bench_pipeline   pipeline.py --models real-size --fp16 at 512² with the synthetic scene resampled
                   to 1,000,000 Gaussians (--gaussians), a short schedule (1 cycle of 100 steps, 8
                   localization views, m = 8; no in2n): per-stage seconds, UNet evaluations, peak
                   CUDA memory
  paper_budget     the paper's budget (pipeline.py BUDGETS["real-size"]: 3 cycles of 500 steps, m = 20,
                   24 localization views, 20 DDIM steps) with --fp16 at 512², the synthetic scene
                   resampled to 100,000 and to 1,000,000 Gaussians (no in2n, no load step): per run
                   every stage, start-up split by phase, the UNet's seconds and share of the wall
                   time, the views per UNet call batch_size auto chose, the wait for the priors, peak
                   CUDA memory and RSS; written as paper_budget.json beside the table's JSON
  donut_edit       the donut (../shared/data/donut/donut.ply, or $GS_REGIONAL_DATA) edited end to end
                   with configs/donut_add.yaml through launch.main on the GPU, its simulated priors
                   replaced by the real-size random-weight IP2P and Depth Anything, at 512², renderer
                   auto, the config's schedule (3 cycles of 100 steps, 12 localization views, m = 8):
                   wall time per stage (save/metrics.json), UNet evaluations, peak CUDA memory
  two_process      with 2 or more GPUs: launch.py --config configs/demo.yaml --train --gpu 0,1
                   trainer.devices=2; a failure is reported with the last line of its output

A check that needs the priors is skipped when they did not build. The budget (default 570 s)
bounds the whole: each check runs for at most its own limit (CHECKS) or what is left of the budget,
and once less than 20 s is left the remaining checks are skipped, saying so.
"""
from __future__ import annotations

import contextlib
import json
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Any, Dict, List, Mapping, Optional

from gs_regional.bench.launching import DONUT, ROOT

NO_CUDA_LINE = "gpu-check: no CUDA device (torch.cuda.is_available() is False); nothing was checked"
NO_CUDA_REASON = "no CUDA device (torch.cuda.is_available() is False): a GPU check (make gpu-check)"
NOT_ASKED_REASON = "a GPU check: make gpu-check runs it (or pytest -m cuda)"
DEFAULT_BUDGET_S = 570.0  # the whole run stays under 10 minutes with the start-up around it
MIN_CHECK_S = 20.0  # with less than this left, the remaining checks are skipped

PROMPT = "put a cherry on top"
# The real-size runs on the GPU (bench_pipeline and the donut): short schedules that fit the budget.
GPU_SETTINGS = dict(device="cuda", models="real-size", resolution=512, gaussians=1_000_000, render_gaussians=50_000,
                    schedule=dict(cycles=1, t_schedule=[750], shape_t_schedule=[450], iterations=100, m=8,
                                  max_views=8, densify_every=50, turntable_frames=8, ddim_steps=20),
                    paper_gaussians=[100_000, 1_000_000])
# --smoke-on-cpu (a developer's check of the wiring, not a measurement): tiny models, small sizes.
CPU_SMOKE_SETTINGS = dict(device="cpu", models="tiny", resolution=64, gaussians=20_000, render_gaussians=2_000,
                          schedule=dict(cycles=1, t_schedule=[750], shape_t_schedule=[750], iterations=6, m=2,
                                        max_views=4, densify_every=3, turntable_frames=2, ddim_steps=4),
                          paper_gaussians=[2_000, 4_000])
# Tolerances of tests/test_renderer.py::test_gsplat_agrees_with_torch_rasterizer.
FORWARD_TOL = 1e-3  # rgb and alpha, absolute; depth, relative on pixels with alpha > 0.5
BACKWARD_TOL = 1e-2  # gradients, max abs difference relative to the largest gradient
# A Gaussian whose alpha at a pixel sits at the 1/255 cut-off can fall on either side of it in the two
# renderers (float rounding); that pixel then differs by up to its contribution, below 1/255 (with 50k
# Gaussians at 512², gsplat differs at one pixel of 262,144 by 1.26e-3; its 99.9th percentile is 1.7e-6).
# So a few pixels may pass FORWARD_TOL, none CUTOFF_MAX.
CUTOFF_MAX = 1 / 255
CUTOFF_FRACTION = 1e-4  # of the pixels, at most, beyond FORWARD_TOL


class Skip(Exception):
    """Raised by a check that cannot run here; its message is the reason in the table."""


class CheckFailed(Exception):
    """Raised by a check that ran and failed; its message is the reason, as it is."""


@dataclass(frozen=True)
class Check:
    what: str
    limit_s: float  # seconds at most (or what is left of the budget, the smaller)


# The checks, in the order tests/gpu/test_gpu.py runs them (its test_<name>).
CHECKS: Dict[str, Check] = {
    "priors": Check("the real-size random-weight prior folders (built once, cached)", 240),
    "gsplat_vs_torch": Check("gsplat against the torch rasterizer, forward and backward", 240),
    "ip2p_fp16": Check("IP2P guided step at 512², float16, real-size weights", 120),
    "ip2p_bf16": Check("IP2P guided step at 512², bfloat16, real-size weights", 120),
    "bench_pipeline": Check("bench_pipeline: the regional edit at 1M Gaussians, 512², fp16", 240),
    "paper_budget": Check("the paper's budget at 100k and 1M Gaussians, 512², fp16: the stage breakdown", 300),
    "donut_edit": Check("the donut edited end to end with real-size random-weight priors", 200),
    "two_process": Check("launch.py configs/demo.yaml with trainer.devices=2", 180),
}

# The settings of a run come from the environment (scripts/gpu_check.py sets them).
ENV_WORK, ENV_MODELS_DIR, ENV_GAUSSIANS = "GPU_CHECK_WORK", "GPU_CHECK_MODELS_DIR", "GPU_CHECK_GAUSSIANS"
ENV_SMOKE, ENV_BUDGET, ENV_RUN = "GPU_CHECK_SMOKE_ON_CPU", "GPU_CHECK_BUDGET", "GPU_CHECK"


def context(environ: Mapping[str, str] = os.environ, gpus: Optional[int] = None) -> dict:
    """What the checks read: the settings (GPU_SETTINGS, or CPU_SMOKE_SETTINGS for a smoke run on
    the CPU), the work folder (runs/ and logs/ go there), the prior cache, the donut, the budget."""
    smoke = environ.get(ENV_SMOKE) == "1"
    settings = json.loads(json.dumps(CPU_SMOKE_SETTINGS if smoke else GPU_SETTINGS))
    if environ.get(ENV_GAUSSIANS):
        settings["gaussians"] = int(environ[ENV_GAUSSIANS])
    if gpus is None:
        import torch

        gpus = torch.cuda.device_count() if torch.cuda.is_available() else 0
    work = os.path.abspath(environ.get(ENV_WORK) or os.path.join(ROOT, "outputs", "gpu_check"))
    os.makedirs(os.path.join(work, "logs"), exist_ok=True)
    return {**settings, "smoke": smoke, "models_dir": environ.get(ENV_MODELS_DIR) or None, "work": work,
            "donut": DONUT, "gpus": 0 if smoke else gpus,
            "budget_s": float(environ.get(ENV_BUDGET) or DEFAULT_BUDGET_S)}



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
    return {"models": ctx["models"], "seconds_to_build_or_find": round(seconds, 2), **folders}


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


def _schedule_argv(s: dict) -> List[str]:
    return ["--cycles", str(s["cycles"]), "--t-schedule", *map(str, s["t_schedule"]),
            "--shape-t-schedule", *map(str, s["shape_t_schedule"]), "--iterations", str(s["iterations"]),
            "--m", str(s["m"]), "--max-views", str(s["max_views"]), "--densify-every", str(s["densify_every"]),
            "--turntable-frames", str(s["turntable_frames"]), "--ddim-steps", str(s["ddim_steps"])]


def _pipeline_argv(ctx: dict, out: str, gaussians: int) -> List[str]:
    argv = ["--models", ctx["models"], "--out", out, "--device", ctx["device"], "--resolution", str(ctx["resolution"]),
            "--gaussians", str(gaussians), "--in2n-steps", "0"]
    if ctx["device"].startswith("cuda"):
        argv.append("--fp16")
    if ctx.get("models_dir"):
        argv += ["--models-dir", ctx["models_dir"]]
    return argv


def bench_pipeline_argv(ctx: dict) -> List[str]:
    return [*_pipeline_argv(ctx, os.path.join(ctx["work"], "bench_pipeline"), ctx["gaussians"]),
            *_schedule_argv(ctx["schedule"])]


def paper_budget_argv(ctx: dict, gaussians: int) -> List[str]:
    """pipeline.py at the paper's budget (its real-size BUDGETS, unset options take them) with
    `gaussians`, without the load step; the CPU smoke run takes ctx's short schedule instead."""
    argv = [*_pipeline_argv(ctx, os.path.join(ctx["work"], "paper_budget", str(gaussians)), gaussians), "--no-load"]
    if ctx.get("smoke"):
        argv += _schedule_argv(ctx["schedule"])
    return argv


def _count_label(n: int) -> str:
    return f"{n / 1e6:g}M" if n >= 1_000_000 else f"{n / 1e3:g}k"


def check_paper_budget(ctx: dict) -> dict:
    """The regional edit at the paper's budget at each of ctx['paper_gaussians'], one process
    each; the whole breakdown goes to WORK/paper_budget.json, the table row keeps the headlines."""
    from gs_regional.bench import pipeline as bench_pipeline

    runs, report = {}, None
    for n in ctx["paper_gaussians"]:
        try:
            report = bench_pipeline.main(paper_budget_argv(ctx, n))
        except SystemExit as e:
            if e.code in (0, None):
                raise
            raise CheckFailed(f"{n:,} Gaussians: {last_line(str(e.code))}") from None
        run = report["runs"]["regional-edit"]
        runs[_count_label(n)] = {
            "gaussians": report["scene"]["gaussians"], "wall_s": run["wall_seconds"], "startup_s": run["startup_seconds"],
            "startup_parts_s": run["startup_parts"], "stages_s": run["seconds"], "stages_total_s": run["seconds_total"],
            "unet_evals": run["unet_evals"],
            "unet_s": run["unet_seconds"], "unet_share": run["unet_share"], "batch_size": run["batch_size"],
            "prior_wait_s": run["prior_wait_seconds"], "vae_encodes": run["vae_encodes"], "vae_decodes": run["vae_decodes"],
            "cuda_peak_gib": _gib(run["cuda_peak_bytes"]), "peak_rss_gib": _gib(run["peak_rss_bytes"]),
            "gaussians_after": run["gaussians_after"], "report": os.path.join(ctx["work"], "paper_budget", str(n),
                                                                              "bench_pipeline.json")}
    breakdown = {"schema": 1, "models": report["models"], "dtype": report["dtype"], "device": report["device"],
                 "resolution": report["scene"]["width"], "renderer": _renderer_auto(ctx["device"]),
                 "schedule": report["schedule"], "runs": runs}
    path = os.path.join(ctx["work"], "paper_budget.json")
    with open(path, "w") as f:
        json.dump(breakdown, f, indent=2)
    res: Dict[str, Any] = {}
    for label, r in runs.items():
        res.update({f"{label}_wall_s": r["wall_s"], f"{label}_startup_s": r["startup_s"],
                    f"{label}_startup_parts": ", ".join(f"{k} {v:.1f}" for k, v in r["startup_parts_s"].items()),
                    f"{label}_unet_share": r["unet_share"],
                    f"{label}_batch": ",".join(str(b) for b in r["batch_size"].values()) or "-",
                    f"{label}_cuda_peak_gib": r["cuda_peak_gib"]})
    res["breakdown"] = path
    return res


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
