"""Bytes per Gaussian, write/read seconds and round-trip PSNR of each export format
(gs_regional/geometry/formats.py) on the demo's synthetic figure and on the donut.

Each scene is written in every format, read back, and rendered with the torch-rasterizer from 8
views; the PSNR compares those renders with the renders of the scene itself (the INRIA PLY is
lossless: infinite PSNR).

    python scripts/bench_export.py [--size 256] [--views 8] [--donut ../shared/data/donut/donut.ply]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

from gs_regional.api import render
from gs_regional.bench.launching import DONUT
from gs_regional.geometry.formats import FORMATS, spz_available
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.geometry.ply import read_ply
from gs_regional.metrics.image import psnr
from gs_regional.sim.scene import make_cameras, make_scene
from gs_regional.sim.splat_truth import object_frame, orbit_cameras


def scenes(args):
    model, _, _ = make_scene()
    yield "demo figure", model.to_ply_gaussians(), make_cameras(args.views, args.size, args.size)[0]
    if os.path.isfile(args.donut):
        g = read_ply(args.donut)
        donut = GaussianModel.from_gaussians(g)
        center, radius = object_frame(donut)
        up = torch.tensor([0.0, 0.0, 1.0])
        cams = orbit_cameras(center, 2.6 * radius, up, args.views, [10.0, 30.0], 360.0, args.size, args.size, 45.0)
        yield "donut", g, cams
    else:
        print(f"skipping the donut: {args.donut} not found", file=sys.stderr)


def renders(g, cameras):
    model = GaussianModel.from_gaussians(g)
    with torch.no_grad():
        return torch.stack([render(model, c)["rgb"] for c in cameras])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=256, help="render width and height")
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--donut", default=DONUT)
    args = p.parse_args(argv)
    names = [n for n in FORMATS if n != "spz" or spz_available()]
    if "spz" not in names:
        print("spz left out: gsply is not installed (pip install 'gs_regional[spz]')", file=sys.stderr)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, g, cams in scenes(args):
            reference = renders(g, cams)
            for name in names:
                suffix, write, read = FORMATS[name]
                path = Path(tmp) / f"scene{suffix}"
                t0 = time.perf_counter()
                write(path, g)
                t1 = time.perf_counter()
                back = read(path)
                t2 = time.perf_counter()
                score = psnr(renders(back, cams), reference)
                rows.append((label, g.num_gaussians, g.sh_degree, name, path.stat().st_size / g.num_gaussians,
                             t1 - t0, t2 - t1, score))
    print(f"| scene | Gaussians (SH) | format | bytes / Gaussian | write s | read s | PSNR vs scene ({args.views} views, {args.size}²) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for label, n, deg, name, bpg, tw, tr, score in rows:
        shown = "lossless" if score >= 119 else f"{score:.2f} dB"
        print(f"| {label} | {n:,} ({deg}) | {FORMATS[name][0]} | {bpg:.2f} | {tw:.3f} | {tr:.3f} | {shown} |")
    return 0
