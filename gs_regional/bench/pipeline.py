"""The whole regional edit and the in2n baseline on one scene, through the REAL code path:
`launch.py` with configs/edit.yaml, InstructPix2Pix (`instructpix2pix`) and Depth Anything
(`depth-anything`) loaded with `from_pretrained` from local folders.

    python scripts/bench_pipeline.py --models tiny|real-size [--out outputs/bench_pipeline] [options]

No weights can be downloaded here, so the folders hold random weights (built once and cached
under ~/.cache/gs_regional/priors, see gs_regional/testing/real_size_models.py):
  tiny       the tiny models of gs_regional/testing/ (a CPU smoke run of minutes);
  real-size  the published shapes (SD 1.5 UNet with 8 input channels, the SD VAE, CLIP ViT-L/14
             text encoder; Depth-Anything-V2-Small), for a GPU. The timings and memory are real,
             the images meaningless.

The scene is the synthetic figure (written out as cameras.json + an INRIA PLY, so the runs read
it exactly as a user's scene) or --ply with --data; --gaussians N resamples it to N Gaussians.
Every scene is written with SH degree 3, as trained scenes have. Unset budget options take the
budget of --models (BUDGETS: real-size = the paper's schedule, tiny = the CPU demo's).

Steps, each in its own process (so that peak CPU RSS and peak CUDA memory are per step):
  load           construct both priors from their folders, one UNet call and one depth call
  regional-edit  launch.py --config configs/edit.yaml --train ...
  in2n           the same data/guidance sections with system_type in2n
It writes DIR/bench_pipeline.json and prints a table: per-stage seconds (the names of the runs'
metrics.json: localize, initialize, refine_edit, refine_train, ... ), start-up (the wall time the
stages do not cover; a line per run splits it: plugins, scene, system, trainer, lightning, unstaged
= checkpoints and Lightning's loop in training, process = interpreter, imports, exit), UNet
evaluations, the UNet's seconds and share of the wall time, the views per UNet call the guidance
chose (batch_size auto), VAE encodes/decodes, peak CPU RSS and peak CUDA memory, with the device
named. --no-load skips the load step.
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import os
import platform
import runpy
import subprocess
import sys
import time
from typing import Dict, List, Optional

from gs_regional.bench.launching import ROOT

SCHEMA_VERSION = 1
# Budgets: real-size = the paper's schedule (configs/edit.yaml: 3 cycles from t 750/500/250, an edit
# that changes the shape from 450/350/250, m = 20,
# 500 steps per cycle, 24 localization views) against in2n's 1500 steps; tiny = the CPU demo's
# (configs/demo.yaml, configs/in2n.yaml), minutes on a CPU.
BUDGETS = {
    "real-size": dict(resolution=512, cycles=3, t_schedule=[750, 500, 250], shape_t_schedule=[450, 350, 250], m=20, iterations=500, max_views=24,
                      in2n_steps=1500, turntable_frames=48, densify_every=100),
    "tiny": dict(resolution=64, cycles=3, t_schedule=[750, 500, 250], shape_t_schedule=[450, 350, 250], m=8, iterations=100, max_views=12,
                 in2n_steps=300, turntable_frames=12, densify_every=50),
}
# Random weights edit nothing consistently, so the safe stops (views disagree, edit outside the region)
# end a regional edit with the real-size folders after localization: they are off here, so that
# every stage runs and is timed. A run that stops anyway is an error, not a timing.
RANDOM_WEIGHTS_NO_STOPS = ["system.localization.min_view_agreement=0", "system.localization.min_edit_coverage=0"]


# ----------------------------------------------------------------------------------- child steps
def _cuda_stats() -> Dict[str, object]:
    import torch

    if not torch.cuda.is_available() or not torch.cuda.is_initialized():
        return {"cuda_peak_bytes": None}
    return {"cuda_peak_bytes": int(torch.cuda.max_memory_allocated()),
            "cuda_peak_reserved_bytes": int(torch.cuda.max_memory_reserved())}


def child_launch(result_path: str, launch_argv: List[str]) -> int:
    """Run launch.py in this process (as `python launch.py ...` would), then record CUDA peaks."""
    sys.argv = [os.path.join(ROOT, "launch.py"), *launch_argv]
    try:
        runpy.run_path(sys.argv[0], run_name="__main__")
        rc = 0
    except SystemExit as e:
        rc = int(e.code or 0) if not isinstance(e.code, str) else 1
    with open(result_path, "w") as f:
        json.dump({"rc": rc, **_cuda_stats()}, f)
    return rc


def child_load(result_path: str, ip2p: str, depth: str, device: str, dtype: str, resolution: int) -> int:
    """Time constructing both priors from their folders and one call of each at `resolution`²."""
    import torch

    from gs_regional.depth.depth_anything import DepthAnything
    from gs_regional.guidance.instructpix2pix import InstructPix2Pix

    def sync():
        if torch.cuda.is_available() and torch.cuda.is_initialized():
            torch.cuda.synchronize()

    seconds = {}
    t0 = time.perf_counter()
    guidance = InstructPix2Pix({"pretrained": ip2p, "device": device, "dtype": dtype, "local_files_only": True})
    sync()
    seconds["load_ip2p"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    estimator = DepthAnything({"pretrained": depth, "device": device, "dtype": dtype, "local_files_only": True})
    sync()
    seconds["load_depth"] = time.perf_counter() - t0
    image = torch.rand(1, resolution, resolution, 3, generator=torch.Generator().manual_seed(0))
    # One bare UNet evaluation on latents of a resolution² image (the first call includes lazy
    # set-up, so it runs twice), then one relevance map through the guidance's public interface
    # (a VAE encode and 2 UNet evaluations in one batch) and one depth prediction.
    unet, f = guidance.unet, guidance.vae_scale_factor
    gen = torch.Generator().manual_seed(0)
    latents = torch.randn(1, unet.config.in_channels, resolution // f, resolution // f, generator=gen)
    emb = torch.randn(1, guidance.max_text_length, unet.config.cross_attention_dim, generator=gen)
    latents, emb = latents.to(guidance.device, guidance.dtype), emb.to(guidance.device, guidance.dtype)
    with torch.no_grad():
        for label in ("unet_call_first", "unet_call"):
            t0 = time.perf_counter()
            eps = unet(latents, torch.tensor(500, device=guidance.device), encoder_hidden_states=emb).sample
            sync()
            seconds[label] = time.perf_counter() - t0
    t0 = time.perf_counter()
    guidance.relevance(image, "give him a mustache", timestep=500)
    sync()
    seconds["relevance_call"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    disp = estimator.disparity(image)
    sync()
    seconds["depth_call"] = time.perf_counter() - t0
    out = {
        "rc": 0,
        "seconds": {k: round(v, 4) for k, v in seconds.items()},
        "unet_output_shape": list(eps.shape),
        "disparity_shape": list(disp.shape),
        "parameters": {
            "unet": sum(p.numel() for p in guidance.unet.parameters()),
            "vae": sum(p.numel() for p in guidance.vae.parameters()),
            "text_encoder": sum(p.numel() for p in guidance.text_encoder.parameters()),
            "depth": sum(p.numel() for p in estimator.model.parameters()),
        },
        "dtype": str(guidance.dtype).replace("torch.", ""),
        "device": str(guidance.device),
        **_cuda_stats(),
    }
    with open(result_path, "w") as f:
        json.dump(out, f)
    return 0


def run_child(args: List[str], result_path: str, log_path: str, env: Dict[str, str]) -> dict:
    """Run this module as a child step; returns its result JSON plus wall seconds and peak RSS
    (from wait4, so the peak of that process alone)."""
    t0 = time.perf_counter()
    with open(log_path, "w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "gs_regional.bench.pipeline", *args], stdout=log,
                                stderr=subprocess.STDOUT, env=env, cwd=ROOT)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    result = {}
    if os.path.isfile(result_path):
        with open(result_path) as f:
            result = json.load(f)
    if proc.returncode != 0 or result.get("rc", 1) != 0:
        with open(log_path) as f:
            tail = f.read()[-4000:]
        raise SystemExit(f"step failed (exit code {proc.returncode}); log {log_path}:\n{tail}")
    result["wall_seconds"] = round(wall, 3)
    result["peak_rss_bytes"] = int(usage.ru_maxrss) * 1024  # Linux reports KiB
    return result


# ----------------------------------------------------------------------------------- the scene
def resample_gaussians(model, n: int, seed: int = 0):
    """`model` with exactly `n` Gaussians. Fewer: a seeded random subset. More: every Gaussian
    kept, and extra copies of randomly chosen ones placed by sampling from their own Gaussian
    (as a 3DGS split does); all scales shrink by sqrt(n_source / n) so that the surface stays
    covered about as densely as before. Vectorised (1M Gaussians in seconds)."""
    import torch

    from gs_regional.geometry.gaussian_model import GaussianModel
    from gs_regional.utils.rotations import quat_to_rotmat

    src = model.num_gaussians
    gen = torch.Generator().manual_seed(seed)
    p = {name: getattr(model, name).detach() for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")}
    if n <= src:
        idx = torch.randperm(src, generator=gen)[:n].sort().values
        return GaussianModel.from_tensors(**{k: v[idx] for k, v in p.items()})
    extra = torch.randint(src, (n - src,), generator=gen)
    idx = torch.cat([torch.arange(src), extra])
    out = {k: v[idx].clone() for k, v in p.items()}
    local = torch.randn(n - src, 3, generator=gen) * p["log_scales"][extra].exp()
    out["means"][src:] += (quat_to_rotmat(p["quats"][extra]) @ local[:, :, None])[:, :, 0]
    out["log_scales"] += 0.5 * math.log(src / n)
    return GaussianModel.from_tensors(**out)


def with_sh_degree(model, degree: int):
    """The same Gaussians with (zero) SH coefficients up to `degree` if they have fewer."""
    import torch

    from gs_regional.geometry.gaussian_model import GaussianModel

    k1 = (degree + 1) ** 2 - 1
    rest = model.sh_rest.detach()
    if rest.shape[1] >= k1:
        return model
    rest = torch.cat([rest, rest.new_zeros(rest.shape[0], k1 - rest.shape[1], 3)], dim=1)
    return GaussianModel.from_tensors(model.means.detach(), model.quats.detach(), model.log_scales.detach(),
                                      model.opacity_logits.detach(), model.sh_dc.detach(), rest)


def prepare_scene(args, folder: str) -> dict:
    """Write the scene the runs read: (cameras file, PLY, data.downscale) and a description."""
    from gs_regional.api import load_cameras
    from gs_regional.data.loaders import save_cameras_json
    from gs_regional.sim.scene import make_cameras, make_scene
    from gs_regional.geometry.gaussian_model import GaussianModel

    os.makedirs(folder, exist_ok=True)
    if args.ply:
        model = GaussianModel.from_ply(args.ply)
        cameras = load_cameras(args.data)
        source, data_source = args.ply, args.data
        side = max(max(c.width, c.height) for c in cameras)
        downscale = side / args.resolution
        width, height = round(cameras[0].width / downscale), round(cameras[0].height / downscale)
    else:
        model, _, _ = make_scene(seed=0)
        cameras, _ = make_cameras(n=40, width=args.resolution, height=args.resolution, seed=0)
        data_source = os.path.join(folder, "cameras.json")
        save_cameras_json(cameras, data_source)
        source, downscale, width, height = "synthetic", 1.0, args.resolution, args.resolution
    n_source = model.num_gaussians
    if args.gaussians:
        model = resample_gaussians(model, args.gaussians, seed=0)
    model = with_sh_degree(model, 3)
    ply = os.path.join(folder, "point_cloud.ply")
    model.save_ply(ply)
    return {"source": source, "gaussians_source": n_source, "gaussians": model.num_gaussians, "sh_degree": model.sh_degree,
            "cameras": len(cameras), "width": width, "height": height, "data_source": data_source, "ply": ply,
            "downscale": downscale}


# ----------------------------------------------------------------------------------- the runs
def in2n_config(out_path: str) -> str:
    """configs/edit.yaml's data and guidance sections with the in2n system (as configs/in2n.yaml
    says to do for real scenes)."""
    from omegaconf import OmegaConf

    edit = OmegaConf.load(os.path.join(ROOT, "configs", "edit.yaml"))
    keep = ("prompt", "seed", "geometry_type", "geometry", "renderer_type", "renderer", "guidance_type", "guidance",
            "lr", "lambda_l1", "lambda_lpips", "eval")
    system = {k: v for k, v in edit.system.items() if k in keep}
    cfg = OmegaConf.merge(edit, {"name": "in2n", "system_type": "in2n"})
    cfg.system = OmegaConf.create(system)
    OmegaConf.save(cfg, out_path)
    return out_path


def common_overrides(args, scene: dict, priors: Dict[str, str]) -> List[str]:
    dtype = "float16" if args.fp16 else "float32"
    device = args.device
    ov = [
        f"data.source={scene['data_source']}", f"data.downscale={scene['downscale']}",
        f"system.geometry.ply={scene['ply']}", f"system.prompt={args.prompt}",
        f"system.guidance.pretrained={priors['ip2p']}", f"system.guidance.dtype={dtype}",
        f"system.guidance.device={device}", "system.guidance.local_files_only=true",
        f"system.guidance.num_inference_steps={args.ddim_steps}",
        f"system.eval.turntable_frames={args.turntable_frames}",
        "trainer.enable_progress_bar=false",
    ]
    if args.renderer:
        ov.append(f"system.renderer_type={args.renderer}")
    return ov


def launch_args(args, config: str, name: str, overrides: List[str]) -> List[str]:
    argv = ["--config", config, "--train", f"exp_root_dir={os.path.join(args.out, 'runs')}", f"name={name}", *overrides]
    if args.device.startswith("cuda"):
        index = args.device.split(":")[1] if ":" in args.device else "0"
        argv[3:3] = ["--gpu", index]
    return argv


def trial_metrics(args, name: str) -> dict:
    trials = sorted(glob.glob(os.path.join(args.out, "runs", name, "*")), key=os.path.getmtime)
    if not trials:
        raise SystemExit(f"run {name} left no trial dir under {args.out}/runs")
    with open(os.path.join(trials[-1], "save", "metrics.json")) as f:
        m = json.load(f)
    m["trial"] = trials[-1]
    return m


# ----------------------------------------------------------------------------------- report
def unet_profile(metrics: dict, wall_seconds: float) -> dict:
    """From a run's metrics.json: the UNet's wall seconds and their share of the run's wall time,
    the views per UNet call the guidance used at each resolution ("WxH": batch), and how long the
    first stage waited for the priors still loading."""
    unet_s = float(metrics.get("unet_seconds", 0.0))
    return {"unet_seconds": round(unet_s, 3), "unet_share": round(min(unet_s / wall_seconds, 1.0), 4) if wall_seconds > 0 else 0.0,
            "batch_size": dict(metrics.get("guidance_batch_size", {})),
            "prior_wait_seconds": metrics.get("prior_wait_seconds")}


def startup_parts(metrics: dict, wall_seconds: float) -> dict:
    """The start-up (the child's wall time outside the stages) split by phase: launch's
    `seconds_setup` (plugins, scene, system, trainer, lightning), `seconds_unstaged` (in training
    outside the stages: checkpoints, Lightning's loop) and "process" (the rest: interpreter start,
    imports before launch, the summary, exit)."""
    parts = dict(metrics.get("seconds_setup", {}))
    if "seconds_unstaged" in metrics:
        parts["unstaged"] = metrics["seconds_unstaged"]
    parts["process"] = round(wall_seconds - metrics["seconds_total"] - sum(parts.values()), 3)
    return parts


def device_description(device: str) -> dict:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        if names:
            cpu = names[0]
    except OSError:
        pass
    desc = {"cpu": cpu, "cpu_cores": os.cpu_count(), "torch": torch.__version__, "device": device}
    if device.startswith("cuda"):
        index = int(device.split(":")[1]) if ":" in device else 0
        desc["gpu"] = torch.cuda.get_device_name(index)
        desc["gpu_memory_bytes"] = int(torch.cuda.get_device_properties(index).total_memory)
        desc["name"] = desc["gpu"]
    else:
        desc["name"] = f"{cpu} ({os.cpu_count()} cores)"
    return desc


def _gib(b: Optional[int]) -> str:
    return "-" if b is None else f"{b / 2**30:.2f}"


def load_line(load: dict) -> str:
    s = load["seconds"]
    return (f"load: IP2P {s['load_ip2p']:.1f} s, Depth Anything {s['load_depth']:.1f} s, one UNet call "
            f"{s['unet_call']:.3f} s (first {s['unet_call_first']:.3f} s), one relevance map {s['relevance_call']:.3f} s, "
            f"one depth call {s['depth_call']:.3f} s; peak RSS {_gib(load['peak_rss_bytes'])} GiB, "
            f"peak CUDA {_gib(load['cuda_peak_bytes'])} GiB")


def table(report: dict) -> str:
    runs = report["runs"]
    stages = []
    for r in runs.values():
        stages += [s for s in r["seconds"] if s not in stages]
    head = ["method", "wall s", "start-up s", *[f"{s} s" for s in stages], "UNet evals", "UNet s", "UNet share",
            "batch", "VAE enc", "VAE dec", "peak RSS GiB", "peak CUDA GiB"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for label, r in runs.items():
        cells = [label, f"{r['wall_seconds']:.1f}", f"{r['startup_seconds']:.1f}",
                 *[f"{r['seconds'][s]:.2f}" if s in r["seconds"] else "-" for s in stages],
                 str(r["unet_evals"]), f"{r['unet_seconds']:.2f}", f"{r['unet_share']:.0%}",
                 ", ".join(f"{b} at {hw}" for hw, b in r["batch_size"].items()) or "-",
                 str(r["vae_encodes"]), str(r["vae_decodes"]),
                 _gib(r["peak_rss_bytes"]), _gib(r["cuda_peak_bytes"])]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    for label, r in runs.items():
        lines.append(f"{label} start-up (s): " + ", ".join(f"{k} {v:.1f}" for k, v in r.get("startup_parts", {}).items()))
    if "load" in report:
        lines.append(load_line(report["load"]))
    sc = report["scene"]
    lines.append(f"{report['models']} priors ({report['dtype']}) on {report['device']['name']}; scene {sc['source']}: "
                 f"{sc['gaussians']} Gaussians, {sc['cameras']} cameras at {sc['width']}x{sc['height']}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------- main
def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", choices=["tiny", "real-size"], required=True)
    ap.add_argument("--out", default=os.path.join(ROOT, "outputs", "bench_pipeline"),
                    help="output folder: bench_pipeline.json, the scene, the runs, logs (default outputs/bench_pipeline)")
    ap.add_argument("--models-dir", default=None, help="cache of the built prior folders (default ~/.cache/gs_regional/priors)")
    ap.add_argument("--ply", default=None, help="a trained scene (INRIA PLY); needs --data")
    ap.add_argument("--data", default=None, help="its cameras: scene folder or camera file")
    ap.add_argument("--gaussians", type=int, default=0, help="resample the scene to this many Gaussians")
    ap.add_argument("--resolution", type=int, default=None, help="longest image side")
    ap.add_argument("--device", default=None, help="cpu | cuda | cuda:N (default: cuda when available)")
    ap.add_argument("--fp16", action="store_true", help="run the priors in float16 (default float32)")
    ap.add_argument("--renderer", default=None, help="system.renderer_type (default: configs/edit.yaml's)")
    ap.add_argument("--prompt", default="give him a mustache")
    ap.add_argument("--cycles", type=int, default=None)
    ap.add_argument("--t-schedule", type=int, nargs="+", default=None, help="start timestep of each cycle (a recolour)")
    ap.add_argument("--shape-t-schedule", type=int, nargs="+", default=None,
                    help="start timestep of each cycle of an edit that changes the shape")
    ap.add_argument("--m", type=int, default=None, help="views edited per cycle around the frontal one")
    ap.add_argument("--iterations", type=int, default=None, help="steps per cycle")
    ap.add_argument("--max-views", type=int, default=None, help="localization views")
    ap.add_argument("--densify-every", type=int, default=None, help="refinement steps between densifications")
    ap.add_argument("--ddim-steps", type=int, default=20, help="DDIM steps of a full edit")
    ap.add_argument("--in2n-steps", type=int, default=None, help="in2n training steps (0 skips the baseline)")
    ap.add_argument("--edit-every", type=int, default=10, help="in2n: steps between dataset edits")
    ap.add_argument("--turntable-frames", type=int, default=None)
    ap.add_argument("--load-only", action="store_true", help="only the load step (load both priors, one call each)")
    ap.add_argument("--no-load", action="store_true", help="skip the load step (the runs alone)")
    args = ap.parse_args(argv)
    if args.load_only and args.no_load:
        ap.error("--load-only and --no-load exclude each other")
    if bool(args.ply) != bool(args.data):
        ap.error("--ply and --data go together (a trained scene and its cameras)")
    for key, value in BUDGETS[args.models].items():  # unset options take the budget of --models
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.device is None:
        import torch

        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    if args.device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            ap.error(f"--device {args.device}: CUDA is not available")
    elif args.device != "cpu":
        ap.error(f"--device must be cpu, cuda or cuda:N, got {args.device}")
    args.out = os.path.abspath(args.out)
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    from gs_regional.testing.real_size_models import cached_priors

    os.makedirs(os.path.join(args.out, "logs"), exist_ok=True)
    env = dict(os.environ, HF_HUB_OFFLINE="1", TRANSFORMERS_OFFLINE="1")
    report: dict = {"schema": SCHEMA_VERSION, "models": args.models, "dtype": "float16" if args.fp16 else "float32",
                    "device": device_description(args.device)}
    t0 = time.perf_counter()
    priors = cached_priors(args.models, args.models_dir)
    report["priors"] = {**priors, "seconds_to_build_or_find": round(time.perf_counter() - t0, 3)}
    print(f"priors ({args.models}): {priors['ip2p']}, {priors['depth_anything']}")

    step = lambda name: (os.path.join(args.out, "logs", f"{name}.json"), os.path.join(args.out, "logs", f"{name}.log"))  # noqa: E731
    if not args.no_load:
        res, log = step("load")
        report["load"] = run_child(["--child-load", res, priors["ip2p"], priors["depth_anything"], args.device,
                                    report["dtype"], str(args.resolution)], res, log, env)
        print(f"load: {report['load']['seconds']}")
    if args.load_only:
        return _write(args, report)

    report["scene"] = prepare_scene(args, os.path.join(args.out, "scene"))
    print(f"scene: {report['scene']['gaussians']} Gaussians, {report['scene']['cameras']} cameras")
    common = common_overrides(args, report["scene"], priors)
    regional = [
        *common,
        f"system.depth.pretrained={priors['depth_anything']}", f"system.depth.dtype={report['dtype']}",
        f"system.depth.device={args.device}", "system.depth.local_files_only=true",
        f"system.refine.cycles={args.cycles}", f"system.refine.t_schedule=[{','.join(map(str, args.t_schedule))}]",
        f"system.refine.shape_t_schedule=[{','.join(map(str, args.shape_t_schedule))}]",
        f"system.refine.m={args.m}", f"system.refine.iterations_per_cycle={args.iterations}",
        f"system.localization.max_views={args.max_views}", f"system.densify.every={args.densify_every}",
        *RANDOM_WEIGHTS_NO_STOPS,
    ]
    report["schedule"] = {"cycles": args.cycles, "t_schedule": args.t_schedule,
                          "shape_t_schedule": args.shape_t_schedule, "m": args.m,
                          "iterations_per_cycle": args.iterations, "localization_views": args.max_views,
                          "densify_every": args.densify_every,
                          "ddim_steps": args.ddim_steps, "in2n_steps": args.in2n_steps, "in2n_edit_every": args.edit_every}
    runs = {"regional-edit": (os.path.join(ROOT, "configs", "edit.yaml"), regional)}
    if args.in2n_steps > 0:
        cfg = in2n_config(os.path.join(args.out, "in2n.yaml"))
        runs["in2n"] = (cfg, [*common, f"system.max_steps={args.in2n_steps}", f"system.edit_every={args.edit_every}"])
    report["runs"] = {}
    for name, (config, overrides) in runs.items():
        res, log = step(name)
        child = run_child(["--child-launch", res, *launch_args(args, config, name, overrides)], res, log, env)
        m = trial_metrics(args, name)
        if m.get("stopped"):
            raise SystemExit(f"{name} stopped early ({m['stopped']}; {m['trial']}): the stages after it were not timed")
        report["runs"][name] = {
            "seconds": m["seconds"], "seconds_total": m["seconds_total"], "wall_seconds": child["wall_seconds"],
            # process start, imports, loading the priors, Lightning set-up: what the stages do not time
            "startup_seconds": round(child["wall_seconds"] - m["seconds_total"], 3),
            "startup_parts": startup_parts(m, child["wall_seconds"]),
            "unet_evals": m["unet_evals"], "vae_encodes": m["vae_encodes"], "vae_decodes": m["vae_decodes"],
            **unet_profile(m, child["wall_seconds"]),
            "peak_rss_bytes": child["peak_rss_bytes"], "cuda_peak_bytes": child["cuda_peak_bytes"],
            "gaussians_before": m["gaussians_before"], "gaussians_after": m["gaussians_after"], "trial": m["trial"],
        }
        print(f"{name}: {child['wall_seconds']:.1f} s, {m['unet_evals']} UNet evaluations")
    return _write(args, report)


def _write(args, report: dict) -> dict:
    path = os.path.join(args.out, "bench_pipeline.json")
    with open(path, "w") as f:
        json.dump(report, f, indent=2)
    print()
    print(table(report) if "runs" in report else load_line(report["load"]))
    print(f"\nwrote {path}")
    return report


def cli(argv=None) -> int:
    """The command line: a child step (--child-launch, --child-load; run_child starts them) or main."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--child-launch"]:
        return child_launch(argv[1], argv[2:])
    if argv[:1] == ["--child-load"]:
        return child_load(argv[1], *argv[2:6], int(argv[6]))
    main(argv)
    return 0


if __name__ == "__main__":
    sys.exit(cli())
