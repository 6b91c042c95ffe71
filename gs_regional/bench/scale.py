"""Seconds and peak memory of the stages of a regional edit that grow with the number of Gaussians.

    python scripts/bench_scale.py --sizes 100000 1000000 --out DIR
    python scripts/bench_scale.py --quick --out DIR          # 10k and 30k: a check, not a measurement

Writes DIR/bench_scale.json, {stage: {N: {"seconds": s, "peak_bytes": b, "cpu_seconds": c}}}, and
prints a table with the growth exponent of every stage's wall seconds between consecutive sizes
(log(t2/t1) / log(N2/N1): 1 is linear). cpu_seconds (all threads of the process) is the steadier
number on a machine shared with other work. Stages:

  ply_save       GaussianModel.save_ply
  ply_load       GaussianModel.from_ply (the file is in the page cache: written just before)
  render_512     one render forward + backward at 512x512 (--render-size; --renderer, the
                 torch-rasterizer by default)
  knn_pool       the neighbour pooling of localization: 16 nearest neighbours of every Gaussian,
                 votes summed over them
  localize       localization without the diffusion model: rendering-weight votes from 24 views at
                 256x256 (--localize-views, --localize-size), 2 reweighting passes (a render per
                 view each), kNN pooling (neighbours found once), the evidence prior, point expansion
                 (radius 1% of the scene extent) and the selection rendered back into the 24 views
  selection_pieces  a recolour gate's connected pieces of the selection (Recolour.selection_pieces):
                 16 nearest neighbours of every Gaussian, then neighbors.components of a selection
                 of half of them (a part that large is the most passes)
  append         depth initialization's append (geometry.rows.append) of N/100 new Gaussians, with
                 Adam state
  densify_prune  one DensifyStrategy.densify_and_prune step over the whole scene (about 2% cloned
                 or split, 1% pruned)
  checkpoint     a training checkpoint as launch.py writes it (TrialCheckpointIO: atomic, fsynced,
                 the optimizer state packed to its non-zero rows) of the scene and its Adam state
                 after a step that trained 5% of the rows, as a regional edit trains its region;
                 also its file_bytes

Every (stage, N) runs in a fresh child process: its peak memory is the growth of the process's
resident set (VmHWM, reset through /proc/self/clear_refs just before the stage) over what the
process held when the stage began, or on CUDA torch.cuda.max_memory_allocated over the memory
allocated then. The scene is a synthetic splat: 48 blobby shells and a ground disk, Gaussians
flattened along the surface with scales about the local spacing, random opacities, SH degree 3.
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import multiprocessing as mp
import os
import resource
import sys
import tempfile
import time

import torch

# Imported once here: the stages run in forked children that share them.
from gs_regional.bench.launching import ROOT
from gs_regional.stages.localize import (
    expand_selection, knn_pool, localize_gaussians, neighbourhoods, render_selection, splat_selection,
)
from gs_regional.geometry import rows
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.geometry.strategy import DensifyStrategy
from gs_regional.registry import find
from gs_regional.sim.scene import look_at
from gs_regional.systems.regional_edit import LocalizeConfig

STAGES = ["ply_save", "ply_load", "render_512", "knn_pool", "localize", "selection_pieces", "append", "densify_prune",
          "checkpoint"]
DEFAULT_SIZES = [10_000, 100_000, 1_000_000]
QUICK_SIZES = [10_000, 30_000]
SCENE_EXTENT = 1.6  # radius of the synthetic scene around the origin
CAMERA_DISTANCE = 4.0


# ----------------------------------------------------------------------------------- the scene
def make_splat(n: int, seed: int = 0):
    """A GaussianModel of n Gaussians on surfaces, SH degree 3, in the camera ring's view."""
    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    nrm = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    n_disk = n // 5
    n_blobs = n - n_disk
    # shells: 48 spheres of radius 0.1-0.4 around the origin, points spread by area
    centres = (u(48, 3) * 2 - 1) * torch.tensor([0.9, 0.5, 0.9])
    radii = 0.1 + 0.3 * u(48)
    which = torch.multinomial(radii**2, n_blobs, replacement=True, generator=g)
    normal_b = nrm(n_blobs, 3)
    normal_b = normal_b / normal_b.norm(dim=1, keepdim=True)
    pts_b = centres[which] + normal_b * radii[which, None]
    # a ground disk of radius 1.5 at y = -0.7 (world +y up here, the cameras look slightly down)
    r = 1.5 * u(n_disk).sqrt()
    a = 2 * math.pi * u(n_disk)
    pts_d = torch.stack([r * torch.cos(a), torch.full_like(r, -0.7), r * torch.sin(a)], 1)
    normal_d = torch.tensor([0.0, 1.0, 0.0]).expand(n_disk, 3)
    means = torch.cat([pts_b, pts_d])
    normals = torch.cat([normal_b, normal_d])
    area = float(4 * math.pi * (radii**2).sum() + math.pi * 1.5**2)
    spacing = math.sqrt(area / n)
    # flat Gaussians: two tangent scales about the spacing, a thin one along the normal
    log_scales = math.log(spacing) + 0.3 * nrm(n, 3)
    log_scales[:, 2] += math.log(0.1)
    model = GaussianModel(n=n, sh_degree=3)
    model.means.data = means + nrm(n, 3) * 0.1 * spacing
    model.quats.data = _quat_from_z(normals, 2 * math.pi * u(n))
    model.log_scales.data = log_scales
    model.opacity_logits.data = 1.0 + 1.5 * nrm(n)
    model.sh_dc.data = nrm(n, 3) * 0.5
    model.sh_rest.data = nrm(n, 15, 3) * 0.05
    return model


def _quat_from_z(axis: torch.Tensor, spin: torch.Tensor) -> torch.Tensor:
    """Quaternions (w, x, y, z) of rotations taking local +z to `axis`, spun by `spin` about it."""
    z = torch.tensor([0.0, 0.0, 1.0])
    half = torch.cross(z.expand_as(axis), axis, dim=1)
    w = 1.0 + axis[:, 2]
    q = torch.cat([w[:, None], half], 1)
    q[w < 1e-6] = torch.tensor([0.0, 1.0, 0.0, 0.0])  # axis = -z: half a turn about x
    q = q / q.norm(dim=1, keepdim=True)
    s = torch.stack([torch.cos(spin / 2), torch.zeros_like(spin), torch.zeros_like(spin), torch.sin(spin / 2)], 1)
    return _quat_mul(q, s)


def _quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    w1, x1, y1, z1 = a.unbind(1)
    w2, x2, y2, z2 = b.unbind(1)
    return torch.stack([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ], 1)


def make_cameras(count: int, size: int, device):
    """`count` cameras on a ring around the scene, 20 degrees above it, looking at the origin."""
    cams = []
    for i in range(count):
        a = 2 * math.pi * i / count
        e = math.radians(20.0)
        centre = (CAMERA_DISTANCE * math.cos(e) * math.sin(a), CAMERA_DISTANCE * math.sin(e),
                  CAMERA_DISTANCE * math.cos(e) * math.cos(a))
        # look_at's cameras have world +y up on screen
        cams.append(look_at(centre, (0.0, 0.0, 0.0), size, size, fov_deg=50.0, name=f"ring_{i:02d}").to(device))
    return cams


# --------------------------------------------------------------------------------- one stage
def _status_kib(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field}")


class PeakMemory:
    """Peak memory of a block over what the process held when it began (see the module doc)."""

    def __init__(self, device: torch.device) -> None:
        self.cuda = device.type == "cuda"

    def __enter__(self):
        gc.collect()
        if self.cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            self.base = torch.cuda.memory_allocated()
        else:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")  # resets VmHWM to the current resident set
            self.base = _status_kib("VmRSS") * 1024
        return self

    def __exit__(self, *exc) -> None:
        if self.cuda:
            torch.cuda.synchronize()
            self.peak = torch.cuda.max_memory_allocated() - self.base
        else:
            self.peak = _status_kib("VmHWM") * 1024 - self.base


def run_stage(stage: str, n: int, device: torch.device, renderer_type: str, workdir: str, render_size: int = 512,
              localize_views: int = 24, localize_size: int = 256) -> dict:
    """Set up (untimed), then time `stage` once; returns {"seconds", "peak_bytes"}."""
    model = make_splat(n).to(device)
    renderer = find(renderer_type, "renderers")()
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    path = os.path.join(workdir, f"splat_{n}.ply")
    gen = torch.Generator().manual_seed(1)

    if stage == "ply_load":
        model.save_ply(path)
        del model
        run = lambda: GaussianModel.from_ply(path)  # noqa: E731
    elif stage == "ply_save":
        if os.path.exists(path):
            os.remove(path)
        run = lambda: model.save_ply(path)  # noqa: E731
    elif stage == "render_512":
        cam = make_cameras(1, render_size, device)[0]

        def run():
            out = renderer.render(model, cam)
            (out["rgb"].sum() + out["depth"].mean()).backward()
    elif stage in ("knn_pool", "localize"):
        lc = LocalizeConfig()
        means = model.means.detach()
        if stage == "knn_pool":
            num, den = torch.rand(n, generator=gen).to(device), torch.rand(n, generator=gen).to(device)

            def run():
                knn_pool(num, den, neighbourhoods(means, lc.knn))
        else:
            cams = make_cameras(localize_views, localize_size, device)
            # The 2D masks a relevance map would give: a ball around one shell, rendered (untimed).
            region = (means - means[0]).norm(dim=1) < 0.35
            masks = [render_selection(model, renderer, c, region) > 0.5 for c in cams]

            def run():
                with torch.no_grad():
                    lifted = localize_gaussians(
                        model, renderer, cams, masks, threshold=lc.mask_threshold, knn=lc.knn,
                        evidence_prior=lc.lift()["evidence_prior"],
                    )
                    selected = expand_selection(means, lifted["selected"], 0.01 * SCENE_EXTENT)
                    for view in lifted["views"]:  # the render-back, from the views' kept weights
                        splat_selection(view, selected)
    elif stage == "selection_pieces":
        from gs_regional.geometry.neighbors import components, knn
        from gs_regional.stages.strategies import GATE_NEIGHBOURS

        means = model.means.detach()
        selected = means[:, 0] > float(means[:, 0].median())

        def run():
            components(knn(means, GATE_NEIGHBOURS)[1], selected)
    elif stage in ("append", "densify_prune"):
        opt = torch.optim.Adam(model.optimizer_param_groups(spatial_scale=SCENE_EXTENT))
        for p in model.parameters():
            p.grad = torch.zeros_like(p)
        opt.step()  # Adam state exists, as in a run: it is resized with the rows
        if stage == "append":
            m = max(1, n // 100)
            new = make_splat(m, seed=2)
            params = {k: getattr(new, k).detach().to(device) for k in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")}

            def run():  # as the regional edit adds the Gaussians made from depth
                rows.append(model, params, optimizer=opt, mask=True, generation=1)
        else:
            with torch.no_grad():
                # ~2% of the Gaussians above the gradient threshold, ~1% below the opacity floor
                model.grad_count.fill_(10.0)
                model.grad_accum.copy_((torch.rand(n, generator=gen) < 0.02).float().to(device) * 10 * 4e-4)
                low = torch.rand(n, generator=gen).to(device) < 0.01
                model.opacity_logits[low] = -8.0

            # the whole scene, as `reconstruct` densifies it
            strategy = DensifyStrategy(grad_threshold=2e-4, max_gaussians=None, only_trainable=False)

            def run():
                strategy.densify_and_prune(model, SCENE_EXTENT, opt, generator=gen)
    elif stage == "checkpoint":
        from gs_regional.launch.checkpoints import TrialCheckpointIO

        opt = torch.optim.Adam(model.optimizer_param_groups(spatial_scale=SCENE_EXTENT))
        trained = (torch.rand(n, generator=gen) < 0.05).to(device)
        for p in model.parameters():
            p.grad = torch.zeros_like(p)
            p.grad[trained] = 1e-3
        opt.step()
        checkpoint = {"state_dict": model.state_dict(), "optimizer_states": [opt.state_dict()]}
        path = os.path.join(workdir, f"last_{n}.ckpt")
        run = lambda: TrialCheckpointIO().save_checkpoint(checkpoint, path)  # noqa: E731
    else:
        raise ValueError(f"unknown stage {stage!r}; stages: {STAGES}")

    with PeakMemory(device) as mem:
        c0, t0 = _cpu_seconds(), time.perf_counter()
        run()
        sync()
        seconds, cpu = time.perf_counter() - t0, _cpu_seconds() - c0
    result = {"seconds": round(seconds, 4), "peak_bytes": int(mem.peak), "cpu_seconds": round(cpu, 3)}
    if stage == "checkpoint":
        result["file_bytes"] = os.path.getsize(path)
    return result


def _cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)  # all threads of this process
    return r.ru_utime + r.ru_stime


# --------------------------------------------------------------------------------- the driver
def growth_exponents(results: dict) -> dict:
    """{stage: [(N1, N2, exponent)]} between consecutive measured sizes."""
    out = {}
    for stage, by_n in results.items():
        sizes = sorted(int(k) for k, v in by_n.items() if v.get("seconds"))
        out[stage] = [
            (a, b, math.log(by_n[str(b)]["seconds"] / by_n[str(a)]["seconds"]) / math.log(b / a))
            for a, b in zip(sizes, sizes[1:])
        ]
    return out


def _short(n: int) -> str:
    for unit, div in (("M", 10**6), ("k", 10**3)):
        if n >= div and n % (div // 10) == 0:
            return f"{n / div:g}{unit}"
    return str(n)


def format_table(results: dict) -> str:
    sizes = sorted({int(n) for by_n in results.values() for n in by_n})
    exps = growth_exponents(results)
    head = ["stage"] + [f"{_short(n)} s" for n in sizes] + [f"{_short(n)} CPU s" for n in sizes]
    head += [f"{_short(n)} peak MiB" for n in sizes]
    head += [f"exp {_short(a)}→{_short(b)}" for a, b in zip(sizes, sizes[1:])]
    rows = []
    for stage in results:
        cells = [stage]
        for n in sizes:
            e = results[stage].get(str(n), {})
            cells.append(f"{e['seconds']:.2f}" if e.get("seconds") is not None else ("failed" if e else "-"))
        for n in sizes:
            e = results[stage].get(str(n), {})
            cells.append(f"{e['cpu_seconds']:.2f}" if e.get("cpu_seconds") is not None else "-")
        for n in sizes:
            e = results[stage].get(str(n), {})
            cells.append(f"{e['peak_bytes'] / 2**20:.0f}" if e.get("peak_bytes") is not None else "-")
        by_pair = {(a, b): x for a, b, x in exps[stage]}
        cells += [f"{by_pair[(a, b)]:.2f}" if (a, b) in by_pair else "-" for a, b in zip(sizes, sizes[1:])]
        rows.append(cells)
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _stage_process(conn, *stage_args) -> None:
    try:
        conn.send(run_stage(*stage_args))
    except BaseException as e:  # report it to the driver, which goes on with the other stages
        conn.send({"error": f"{type(e).__name__}: {e}"})
        raise
    finally:
        conn.close()


def _run_isolated(timeout: float, *stage_args) -> dict:
    """run_stage in a fresh child process (forked where possible: torch is imported only once),
    so that each stage's peak memory is its own."""
    ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_stage_process, args=(send, *stage_args))
    proc.start()
    send.close()
    try:
        entry = recv.recv() if recv.poll(timeout) else {"error": f"timeout {timeout:.0f}s"}
    except EOFError:  # the child died without a word (killed for memory, crashed)
        proc.join()
        entry = {"error": f"the stage's process died with exit code {proc.exitcode}"}
    if proc.is_alive():
        proc.terminate()
    proc.join()
    if "error" in entry:
        print(f"{stage_args[0]} N={stage_args[1]} failed: {entry['error']}", file=sys.stderr, flush=True)
        entry = {"seconds": None, "peak_bytes": None, "error": entry["error"][:200]}
    return entry


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=None, help=f"numbers of Gaussians (default {DEFAULT_SIZES})")
    ap.add_argument("--quick", action="store_true", help=f"sizes {QUICK_SIZES}: checks the script, measures little")
    ap.add_argument("--stages", nargs="+", default=STAGES, choices=STAGES)
    ap.add_argument("--out", default=os.path.join(ROOT, "outputs", "bench_scale"),
                    help="folder for bench_scale.json (default outputs/bench_scale)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--renderer", default="torch-rasterizer")
    ap.add_argument("--render-size", type=int, default=512, help="image side of the render_512 stage")
    ap.add_argument("--localize-views", type=int, default=24)
    ap.add_argument("--localize-size", type=int, default=256, help="image side of the localization views")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds allowed per (stage, N)")
    args = ap.parse_args(argv)

    sizes = args.sizes or (QUICK_SIZES if args.quick else DEFAULT_SIZES)
    os.makedirs(args.out, exist_ok=True)
    results = {stage: {} for stage in args.stages}
    print(f"device {args.device}, renderer {args.renderer}, torch threads {torch.get_num_threads()}, sizes {sizes}, "
          f"render {args.render_size}^2, localization {args.localize_views} views at {args.localize_size}^2", flush=True)
    with tempfile.TemporaryDirectory(prefix="bench_scale_") as workdir:
        for stage in args.stages:
            for n in sizes:
                entry = _run_isolated(args.timeout, stage, n, torch.device(args.device), args.renderer, workdir,
                                      args.render_size, args.localize_views, args.localize_size)
                results[stage][str(n)] = entry
                print(f"{stage:14s} N={n:>9,}  {entry}", flush=True)
                with open(os.path.join(args.out, "bench_scale.json"), "w") as f:
                    json.dump(results, f, indent=1)
    print()
    print(format_table(results))
    failed = [(s, n) for s, by_n in results.items() for n, e in by_n.items() if e.get("seconds") is None]
    return 1 if failed else 0
