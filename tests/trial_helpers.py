"""Reading what a launch.py run wrote into its trial directory (shared by the system tests)."""
import glob
import json
import os

import numpy as np
from plyfile import PlyData


def trial_of(tmp, name):
    """The newest trial dir of experiment `name` under the exp_root_dir `tmp`."""
    trials = sorted(glob.glob(os.path.join(tmp, name, "*")), key=os.path.getmtime)
    assert trials, f"no trial dir under {tmp}/{name}"
    return trials[-1]


def metrics_of(trial):
    with open(os.path.join(trial, "save", "metrics.json")) as f:
        return json.load(f)


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
