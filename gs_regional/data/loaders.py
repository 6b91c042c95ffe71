"""Find and load the cameras of a scene, whatever format they come in.

Formats: a COLMAP model (`sparse/0/`, `sparse/`, or the model folder itself; .bin or .txt),
nerfstudio's `transforms.json`, and the `cameras.json` the original 3DGS trainer writes next to
its `point_cloud/`. All become `Camera`s (OpenCV convention), sorted by image name.
"""
from __future__ import annotations

import json
import os
import re
import warnings
from typing import List, Optional, Sequence, Tuple

import numpy as np

from gs_regional.data import colmap, nerfstudio
from gs_regional.data.cameras import Camera
from gs_regional.data.nerfstudio import TransformsError, read_json

LOOKED_FOR = (
    "sparse/0/cameras.{bin,txt}",
    "sparse/cameras.{bin,txt}",
    "transforms.json",
    "cameras.json",
    "cameras.{bin,txt} (a COLMAP model folder)",
)


class CameraLoadError(ValueError):
    """No usable cameras at a path; the message names the path and what was looked for."""


def find_camera_source(path: str) -> Tuple[str, str]:
    """(kind, location) of the cameras at `path`: kind is 'colmap' (location = model folder),
    'transforms' or 'cameras_json' (location = the JSON file)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise CameraLoadError(f"camera path does not exist: {path}")
    if os.path.isdir(path):
        for sub in ("sparse/0", "sparse"):
            d = os.path.join(path, sub)
            if colmap.is_model_dir(d):
                return "colmap", d
        for name, kind in (("transforms.json", "transforms"), ("cameras.json", "cameras_json")):
            f = os.path.join(path, name)
            if os.path.isfile(f):
                return kind, f
        if colmap.is_model_dir(path):
            return "colmap", path
        raise CameraLoadError(
            f"no cameras found in folder {path}; looked for: {', '.join(LOOKED_FOR)}"
        )
    base = os.path.basename(path)
    stem, ext = os.path.splitext(base)
    if stem in ("cameras", "images", "points3D") and ext in (".bin", ".txt"):
        return "colmap", os.path.dirname(os.path.abspath(path))
    if ext.lower() == ".json":
        data = read_json(path)
        if isinstance(data, dict) and "frames" in data:
            return "transforms", path
        if isinstance(data, list) and data and isinstance(data[0], dict) and "img_name" in data[0]:
            return "cameras_json", path
        raise CameraLoadError(
            f"{path}: not a camera file: expected a transforms.json-like object with a 'frames' list "
            f"or a 3DGS cameras.json list of {{img_name, width, height, position, rotation, fx, fy}}"
        )
    raise CameraLoadError(
        f"{path}: not a camera file or scene folder; expected one of: {', '.join(LOOKED_FOR)}"
    )


def load_cameras(path: str) -> List[Camera]:
    """Cameras from a scene folder or a camera file, sorted by image name."""
    kind, where = find_camera_source(path)
    if kind == "colmap":
        cams = colmap.load_colmap_cameras(where)
    elif kind == "transforms":
        cams = nerfstudio.load_transforms(where)
    else:
        cams = load_cameras_json(where)
    if not cams:
        raise CameraLoadError(f"{where}: contains no cameras")
    return cams


# ----------------------------------------------------------------------------- 3DGS cameras.json


def _source_images_dir(model_dir: str) -> Optional[str]:
    """The trainer's model folder has `cfg_args` (a printed Namespace) naming the source scene."""
    cfg = os.path.join(model_dir, "cfg_args")
    dirs = [os.path.join(model_dir, "images")]
    if os.path.isfile(cfg):
        with open(cfg, "r", encoding="utf-8", errors="replace") as f:
            m = re.search(r"source_path=['\"]([^'\"]+)['\"]", f.read())
        if m:
            src = m.group(1)
            if not os.path.isabs(src):
                src = os.path.join(model_dir, src)
            dirs.append(os.path.join(src, "images"))
    return next((d for d in dirs if os.path.isdir(d)), None)


def _find_named_image(images_dir: Optional[str], name: str) -> Optional[str]:
    if images_dir is None:
        return None
    p = os.path.join(images_dir, name)
    if os.path.isfile(p):
        return p
    for ext in nerfstudio.IMAGE_EXTENSIONS:  # the trainer stores names without their extension
        if os.path.isfile(p + ext):
            return p + ext
    return None


def load_cameras_json(path: str) -> List[Camera]:
    """The original 3DGS trainer's cameras.json: `rotation` is camera-to-world, `position` the
    camera centre (COLMAP/OpenCV axes); the principal point is the image centre."""
    data = read_json(path)
    if not isinstance(data, list):
        raise TransformsError(f"{path}: expected a list of cameras")
    images_dir = _source_images_dir(os.path.dirname(os.path.abspath(path)))
    cams = []
    for i, entry in enumerate(data):
        where = f"{path}: entry [{i}]"
        if not isinstance(entry, dict):
            raise TransformsError(f"{where} is not an object")
        for key in ("img_name", "width", "height", "position", "rotation", "fx", "fy"):
            if key not in entry:
                raise TransformsError(f"{where} has no '{key}'")
        try:
            R = np.asarray(entry["rotation"], np.float64).reshape(3, 3)
            pos = np.asarray(entry["position"], np.float64).reshape(3)
            w, h = int(entry["width"]), int(entry["height"])
            fx, fy = float(entry["fx"]), float(entry["fy"])
        except (TypeError, ValueError) as e:
            raise TransformsError(f"{where}: bad rotation/position/size/focal ({e})") from None
        w2c = np.eye(4)
        w2c[:3, :3] = R.T
        w2c[:3, 3] = -R.T @ pos
        name = str(entry["img_name"])
        cams.append(
            Camera(world_to_camera=w2c, fx=fx, fy=fy, cx=w / 2.0, cy=h / 2.0, width=w, height=h,
                   image_name=name, image_path=_find_named_image(images_dir, name))
        )
    return sorted(cams, key=lambda c: c.image_name)


def save_cameras_json(cameras: Sequence[Camera], path: str) -> None:
    """Write cameras in the 3DGS trainer's cameras.json layout (what splat viewers read).

    That layout has no principal point or distortion; a camera with an off-centre principal
    point is written anyway, with a warning.
    """
    entries = []
    off_centre = []
    for i, cam in enumerate(cameras):
        if abs(cam.cx - cam.width / 2) > 0.5 or abs(cam.cy - cam.height / 2) > 0.5:
            off_centre.append(cam.image_name)
        c2w = cam.camera_to_world.double().numpy()
        name = os.path.splitext(cam.image_name)[0] if cam.image_name else f"{i:05d}"
        entries.append({
            "id": i, "img_name": name, "width": cam.width, "height": cam.height,
            "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(),
            "fy": cam.fy, "fx": cam.fx,
        })
    if off_centre:
        warnings.warn(f"{path}: cameras.json cannot store a principal point; "
                      f"{len(off_centre)} camera(s) have an off-centre one (e.g. {off_centre[0]})")
    with open(path, "w", encoding="utf-8") as f:
        json.dump(entries, f)
