"""Launching runs the way a user does (launch.py, in this process or a fresh one) and reading what
they wrote into their trial directory (shared by the system tests)."""
import glob
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from plyfile import PlyData

ROOT = Path(__file__).resolve().parents[1]  # the checkout
DEMO = ROOT / "configs" / "demo.yaml"
SMALL_DEMO = Path(__file__).parent / "data" / "small_demo.yaml"
# The keys of the small demo that every system on the synthetic scene takes (in2n as well).
_SCENE_SECTIONS = ("use_timestamp", "data.", "system.eval.", "checkpoint.", "trainer.")


# ../shared/data beside the checkout; GS_REGIONAL_DATA points elsewhere (e.g. from a git worktree).
SHARED_DATA = Path(os.environ.get("GS_REGIONAL_DATA") or ROOT.parent / "shared" / "data")


def shared_path(*parts: str) -> Path:
    """A path under ../shared/data, or skip the test with a clear reason."""
    import pytest

    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not found: {p} (expected ../shared/data beside the checkout, or set GS_REGIONAL_DATA)")
    return p


def small_demo(scene_only=False):
    """tests/data/small_demo.yaml as key=value overrides (of configs/demo.yaml); `scene_only`: its
    scene, evaluation and trainer keys alone, for another system on the synthetic scene."""
    flat = []

    def walk(node, prefix):
        for key, value in node.items():
            if isinstance(value, dict):
                walk(value, f"{prefix}{key}.")
            else:
                flat.append((f"{prefix}{key}", value))

    walk(OmegaConf.to_container(OmegaConf.load(SMALL_DEMO)), "")
    return [f"{k}={str(v).lower() if isinstance(v, bool) else v}" for k, v in flat
            if not scene_only or k.startswith(_SCENE_SECTIONS)]


def launch_args(out, name, *overrides, config=DEMO, small=True, mode="--train"):
    """launch.py's arguments for a run of `config` named `name` under the exp_root_dir `out`, with
    the small demo's overrides first (`small`: True, "scene" for its scene keys alone, False)."""
    size = small_demo(scene_only=small == "scene") if small else []
    modes = (mode,) if isinstance(mode, str) else tuple(mode)  # ("--export", "region")
    return ["--config", str(ROOT / config), *modes, f"exp_root_dir={out}", f"name={name}", *size, *overrides]


def launch(out, name, *overrides, config=DEMO, small=True, expect=0, args=()):
    """launch.py in this process: asserts its exit code and returns the new trial dir (None when
    `expect` is not 0). `args`: more of launch.py's options (--gpu 0, --verbose, --custom-dir D)."""
    from gs_regional.launch import main

    code = main([*launch_args(out, name, *overrides, config=config, small=small), *args])
    assert code == expect, f"launch.py exited {code}, expected {expect}"
    return trial_of(out, name) if expect == 0 else None


def launch_process(out, name, *overrides, config=DEMO, small=True, expect=0, args=(), program=None, env=None,
                   timeout=600):
    """launch.py in a fresh Python process (`program`: Python source run instead of launch.py, which
    reads the same arguments); returns the finished process, its output as bytes."""
    head = [sys.executable, "-c", program] if program else [sys.executable, str(ROOT / "launch.py")]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])), **(env or {})}
    proc = subprocess.run([*head, *launch_args(out, name, *overrides, config=config, small=small), *args],
                          capture_output=True, timeout=timeout, env=env, cwd=ROOT)
    if expect is not None:
        assert proc.returncode == expect, proc.stdout.decode()[-3000:] + proc.stderr.decode()[-3000:]
    return proc


def trial_of(tmp, name):
    """The newest trial dir of experiment `name` under the exp_root_dir `tmp`."""
    trials = sorted(glob.glob(os.path.join(tmp, name, "*")), key=os.path.getmtime)
    assert trials, f"no trial dir under {tmp}/{name}"
    return Path(trials[-1])


def metrics_of(trial):
    with open(os.path.join(trial, "save", "metrics.json")) as f:
        return json.load(f)


def metrics_without_timings(trial):
    """metrics.json less its wall-clock figures (seconds, seconds_total, *_seconds): the only
    metrics two runs of one edit may differ in."""
    return {k: v for k, v in metrics_of(trial).items() if "seconds" not in k}


def run_quick(script, out, json_name):
    """`script.main(["--quick", "--out", out])` (a sweep of scripts/), then its JSON payload."""
    assert script.main(["--quick", "--out", str(out)]) == 0
    with open(os.path.join(out, json_name)) as f:
        return json.load(f)


def ply_arrays(path):
    """Every vertex property of a PLY as a numpy array."""
    v = PlyData.read(str(path))["vertex"].data
    return {name: np.asarray(v[name]) for name in v.dtype.names}


def write_scene_folder(tmp, n_cameras, size):
    """The synthetic figure written as a user's scene folder (point_cloud.ply + cameras.json, no
    known edit): the input of configs/edit.yaml. Returns (folder, ply path)."""
    from pathlib import Path

    from gs_regional.data.loaders import save_cameras_json
    from gs_regional.sim.scene import make_cameras, make_edit

    scene = Path(tmp) / "scene"
    scene.mkdir()
    ply = scene / "point_cloud.ply"
    make_edit("add").source.save_ply(str(ply))
    save_cameras_json(make_cameras(n=n_cameras, width=size, height=size)[0], str(scene / "cameras.json"))
    return scene, ply


def write_bright_photo_scene(tmp, n_cameras, size, gain=1.8):
    """Photos of the synthetic figure, brightened by `gain` until its colours saturate, written as
    a user's nerfstudio scene (transforms.json + PNGs, no splat): what configs/reconstruct.yaml
    fits. Saturated photos are what makes a fitted splat with view-dependent colour render above 1
    here and there. Returns the folder."""
    import json
    from pathlib import Path

    import imageio.v3 as iio
    import torch

    from gs_regional.registry import find
    from gs_regional.sim.scene import make_cameras, make_edit

    folder = Path(tmp) / "bright_scene"
    (folder / "images").mkdir(parents=True)
    source = make_edit("add").source
    renderer = find("torch-rasterizer")()
    bg = torch.tensor([1.0, 1.0, 1.0])
    frames = []
    cameras = make_cameras(n=n_cameras, width=size, height=size)[0]
    for cam in cameras:
        rgb = (renderer.render(source, cam, background=bg)["rgb"].detach() * gain).clamp(0, 1)
        name = f"images/{cam.image_name}.png"
        iio.imwrite(folder / name, (rgb * 255).round().to(torch.uint8).numpy())
        c2w = cam.camera_to_world.double().clone()
        c2w[:3, 1:3] *= -1  # OpenCV camera axes -> nerfstudio's OpenGL ones
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
    first = cameras[0]
    meta = {"camera_model": "OPENCV", "fl_x": first.fx, "fl_y": first.fy, "cx": first.cx, "cy": first.cy,
            "w": size, "h": size, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder
