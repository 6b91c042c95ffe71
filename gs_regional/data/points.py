"""SfM points of a scene, in the same world frame as `load_cameras` of that folder."""
from __future__ import annotations

import os
import warnings
from typing import List, Optional, Tuple

import numpy as np

from gs_regional.data import colmap, nerfstudio
from gs_regional.data.cameras import Camera
from gs_regional.data.loaders import CameraLoadError, find_camera_source, load_cameras

Points = Tuple[np.ndarray, np.ndarray]  # xyz float32 (N, 3), rgb float32 (N, 3) in [0, 1]


class PointsError(ValueError):
    """A point cloud that cannot be read; the message names the file."""


def read_ply_points(path: str) -> Points:
    """xyz and colours of a point-cloud PLY (red/green/blue as uint8, uint16 or float; grey if absent)."""
    from plyfile import PlyData

    try:
        ply = PlyData.read(path)
    except Exception as e:  # plyfile raises several kinds for a bad header/body
        raise PointsError(f"cannot read point cloud {path}: {e}") from None
    if "vertex" not in [el.name for el in ply.elements]:
        raise PointsError(f"{path}: no 'vertex' element")
    v = ply["vertex"].data
    names = v.dtype.names
    if not all(k in names for k in ("x", "y", "z")):
        raise PointsError(f"{path}: vertices have no x/y/z properties (have: {', '.join(names)})")
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    if all(k in names for k in ("red", "green", "blue")):
        raw = np.stack([v["red"], v["green"], v["blue"]], axis=1)
        if np.issubdtype(raw.dtype, np.integer):
            rgb = raw.astype(np.float32) / float(np.iinfo(raw.dtype).max)
        else:
            rgb = np.clip(raw.astype(np.float32), 0.0, 1.0)
    else:
        rgb = np.full_like(xyz, 0.5)
    return xyz, rgb


def _colmap_points(model_dir: str) -> Optional[Points]:
    if colmap.model_file(model_dir, "points3D") is not None:
        pts = colmap.read_points3d(model_dir)
        return pts.xyz.astype(np.float32), pts.rgb.astype(np.float32) / 255.0
    # The 3DGS trainer converts points3D.bin to points3D.ply in the same folder.
    ply = os.path.join(model_dir, "points3D.ply")
    return read_ply_points(ply) if os.path.isfile(ply) else None


def visible_fraction(xyz: np.ndarray, cameras: List[Camera], max_cameras: int = 16) -> float:
    """Mean fraction of points in front of a camera and inside its image (pinhole), over cameras."""
    if len(xyz) == 0 or not cameras:
        return 0.0
    step = max(1, len(cameras) // max_cameras)
    fracs = []
    for cam in cameras[::step]:
        w2c = cam.world_to_camera.double().numpy()
        pc = xyz.astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam.fx * pc[:, 0] / z + cam.cx
            v = cam.fy * pc[:, 1] / z + cam.cy
        inside = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        fracs.append(inside.mean())
    return float(np.mean(fracs))


def points_to_file_frame(xyz: np.ndarray, meta: dict, cameras: List[Camera], path: str) -> np.ndarray:
    """A transforms.json's ply is either already in the file's frame (nerfstudio today) or in the
    original COLMAP frame (older exports). Keep whichever the cameras actually see; as-is wins ties.
    See the module docstring of `nerfstudio.py` for the check on the face scene."""
    if "applied_transform" not in meta and "applied_scale" not in meta:
        return xyz
    moved = nerfstudio.colmap_to_file(xyz, meta, path).astype(np.float32)
    return moved if visible_fraction(moved, cameras) > 1.5 * visible_fraction(xyz, cameras) else xyz


def load_points(scene_path: str) -> Optional[Points]:
    """(xyz float32 (N,3), rgb float32 (N,3) in [0,1]) of a scene, or None if it has no points.

    The points come from the same source as the cameras (`find_camera_source`), so the two share
    a world frame: COLMAP points3D.{bin,txt}; a transforms.json's `ply_file_path`/`sparse_pc.ply`
    (or, failing that, nerfstudio's `colmap/sparse/0` moved by `applied_transform`); beside a
    3DGS cameras.json, the trainer's `input.ply`. A `points3d.ply` in the folder (NeRF-synthetic
    scenes for 3DGS) is used when nothing else is there. A .ply file path is read as it is.
    """
    scene_path = os.fspath(scene_path)
    if os.path.isfile(scene_path) and scene_path.lower().endswith(".ply"):
        return read_ply_points(scene_path)
    if not os.path.exists(scene_path):
        raise PointsError(f"scene path does not exist: {scene_path}")
    folder = scene_path if os.path.isdir(scene_path) else os.path.dirname(os.path.abspath(scene_path))
    try:
        kind, where = find_camera_source(scene_path)
    except CameraLoadError:  # no cameras here: only a stand-alone points3d.ply can be meant
        kind, where = "none", ""

    pts: Optional[Points] = None
    if kind == "colmap":
        pts = _colmap_points(where)
    elif kind == "transforms":
        meta = nerfstudio.read_json(where)
        root = os.path.dirname(os.path.abspath(where))
        ply = nerfstudio.ply_path(where)
        if ply is not None:
            xyz, rgb = read_ply_points(ply)
            with warnings.catch_warnings():  # load_cameras already warned about missing photos
                warnings.simplefilter("ignore")
                cams = load_cameras(where)
            pts = points_to_file_frame(xyz, meta, cams, where), rgb
        else:
            for sub in ("colmap/sparse/0", "sparse/0", "sparse"):
                d = os.path.join(root, sub)
                if os.path.isdir(d) and colmap.model_file(d, "points3D") is not None:
                    xyz, rgb = _colmap_points(d)
                    pts = nerfstudio.colmap_to_file(xyz, meta, where).astype(np.float32), rgb
                    break
    elif kind == "cameras_json":  # 3DGS trainer model folder
        ply = os.path.join(os.path.dirname(os.path.abspath(where)), "input.ply")
        if os.path.isfile(ply):
            pts = read_ply_points(ply)

    if pts is None:
        ply = os.path.join(folder, "points3d.ply")
        if os.path.isfile(ply):
            pts = read_ply_points(ply)
    return pts
