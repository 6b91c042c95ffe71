"""Time and memory of a renderer on random scenes.

    python scripts/bench_renderer.py                       # torch-rasterizer, CPU, full table
    python scripts/bench_renderer.py --counts 10000 --sizes 128 --threads 1
    python scripts/bench_renderer.py --device cuda --renderer gsplat-rasterizer

Each (count, size) runs in a fresh subprocess so that its peak memory (CPU: the growth of the
process's max RSS over the state after the scene was built; CUDA: torch.cuda.max_memory_allocated)
is its own. Scenes: Gaussians spread through the view frustum at depths 2-8 with small anisotropic
scales (0.005-0.05, i.e. about 0.3-5 px at 512^2), random rotations, opacities and SH degree 3.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time

import torch


def make_scene(n: int, size: int, device: str, seed: int = 0):
    from gs_regional.data.cameras import Camera
    from gs_regional.geometry.gaussian_model import GaussianModel

    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g)
    z = 2.0 + 6.0 * u(n)
    half = 0.55  # a little beyond the image edge (tan of the half field of view is 0.556)
    means = torch.stack([(2 * u(n) - 1) * half * z, (2 * u(n) - 1) * half * z, z], dim=-1)
    model = GaussianModel(n=n, sh_degree=3)
    model.means.data = means
    model.quats.data = torch.randn(n, 4, generator=g)
    model.log_scales.data = math.log(0.005) + math.log(10.0) * u(n, 3)
    model.opacity_logits.data = 1.5 * torch.randn(n, generator=g)
    model.sh_dc.data = torch.randn(n, 3, generator=g) * 0.5
    model.sh_rest.data = torch.randn(n, 15, 3, generator=g) * 0.05
    model = model.to(device)
    f = 0.9 * size
    cam = Camera(torch.eye(4), f, f, size / 2, size / 2, size, size).to(device)
    return model, cam


def _max_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB


def run_one(renderer_type: str, n: int, size: int, device: str, repeats: int) -> dict:
    from gs_regional.registry import find

    model, cam = make_scene(n, size, device)
    renderer = find(renderer_type, "renderers")()
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    else:
        base = _max_rss_bytes()

    def forward():
        with torch.no_grad():
            renderer.render(model, cam)
        sync()

    def forward_backward():
        out = renderer.render(model, cam)
        (out["rgb"].sum() + out["depth"].mean()).backward()
        model.zero_grad(set_to_none=True)
        sync()

    times = {}
    for name, fn in (("forward", forward), ("fwd+bwd", forward_backward)):
        fn()  # warm-up
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        times[name] = (statistics.median(ts), min(ts))
    if device.startswith("cuda"):
        peak = torch.cuda.max_memory_allocated() - base
    else:
        peak = _max_rss_bytes() - base
    with torch.no_grad():
        out = renderer.render(model, cam)
    return {
        "n": n,
        "size": size,
        "forward_s": times["forward"][0],
        "fwd_bwd_s": times["fwd+bwd"][0],
        "forward_best_s": times["forward"][1],
        "fwd_bwd_best_s": times["fwd+bwd"][1],
        "peak_mb": peak / 2**20,
        "visible": int(out["visible"].sum()),
        "coverage": float(out["alpha"].mean()),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--renderer", default="torch-rasterizer")
    p.add_argument("--device", default="cpu")
    p.add_argument("--counts", type=int, nargs="+", default=[10_000, 50_000, 100_000])
    p.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512], help="square image sides")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per case (median and best reported)")
    p.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.worker:
        print(json.dumps(run_one(args.renderer, args.counts[0], args.sizes[0], args.device, args.repeats)))
        return 0
    print(
        f"renderer {args.renderer} on {args.device}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, {os.cpu_count()} CPUs, "
        f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}"
    )
    print(
        f"{'gaussians':>9} {'size':>5} {'visible':>8} {'cover':>6} {'forward s':>10} {'(best)':>7} "
        f"{'fwd+bwd s':>10} {'(best)':>7} {'peak MB':>8}"
    )
    for n in args.counts:
        for size in args.sizes:
            cmd = [
                sys.executable, "-m", "gs_regional.bench.renderer", "--worker", "--renderer", args.renderer,
                "--device", args.device, "--counts", str(n), "--sizes", str(size),
                "--repeats", str(args.repeats), "--threads", str(args.threads),
            ]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                tail = proc.stderr.strip().splitlines()[-1:] or ["(no output)"]
                print(f"{n:>9} {size:>5}  failed: {tail[0]}")
                continue
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            print(
                f"{r['n']:>9} {r['size']:>5} {r['visible']:>8} {r['coverage']:>6.2f} "
                f"{r['forward_s']:>10.3f} {r['forward_best_s']:>7.3f} {r['fwd_bwd_s']:>10.3f} "
                f"{r['fwd_bwd_best_s']:>7.3f} {r['peak_mb']:>8.0f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":  # a worker (--worker): one (count, size) in a process of its own
    sys.exit(main())
