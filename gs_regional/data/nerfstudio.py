"""nerfstudio `transforms.json` -> `Camera`s (and the frame of its point cloud).

`transform_matrix` is camera-to-world in the OpenGL convention (x right, y up, z backward);
flipping the camera's y and z axes gives OpenCV. Intrinsics may be given once at the top level
or per frame (a frame's value wins). Blender/instant-ngp style files (`camera_angle_x`, no
`fl_x`) are accepted too.

Which world frame? We keep the file's own frame, for cameras and points alike:
`applied_transform` (3x4) and `applied_scale` only record how this frame was obtained from the
original COLMAP frame (`X_file = applied_scale * (A[:, :3] X_colmap + A[:, 3])`). Current
nerfstudio (`ns-process-data`, `create_ply_from_colmap`) writes `sparse_pc.ply` with that
transform already applied, so the ply needs nothing. Checked on ../shared/data/face: taken as-is,
every one of the 9,875 points lies in front of all 65 cameras, 59-91 % (mean 75 %) of them project
inside each 512x512 image (the rest is wall outside the field of view; every point is inside >= 2
views), their colours match the photos (mean |diff| 0.13 vs 0.21 at random pixels) and the splatted
points show the face, shoulders and the wall edge where the photos have them. Applying
`applied_transform` (or its inverse) once more puts ~0 % of the points in front of any camera.
Other tools (and older nerfstudio) write the ply in the original COLMAP frame instead, so
`points.py` tries both and keeps the one the cameras see (`points_to_file_frame`, `colmap_to_file`).
"""
from __future__ import annotations

import json
import math
import os
import warnings
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from gs_regional.data.cameras import Camera

PERSPECTIVE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "PERSPECTIVE")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG")


class TransformsError(ValueError):
    """A transforms.json that cannot be used; the message names the file and the key."""


def read_json(path: str) -> Any:
    try:
        with open(path, "r", encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        raise TransformsError(f"{path}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except OSError as e:
        raise TransformsError(f"cannot read {path}: {e.strerror}") from None


def _number(value: Any, path: str, key: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TransformsError(f"{path}: '{key}' must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise TransformsError(f"{path}: '{key}' is not finite ({value!r})")
    return v


def _matrix(value: Any, rows: int, path: str, key: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape not in ((rows, 4), (4, 4)) or not np.isfinite(m).all():
        raise TransformsError(f"{path}: '{key}' must be a finite {rows}x4 matrix, got {value!r}"[:300])
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    return m


def applied_transform(meta: Dict[str, Any], path: str = "transforms.json") -> Tuple[np.ndarray, float]:
    """(4x4 A, applied_scale) with X_file = scale * (A @ X_colmap); identity/1 when absent."""
    A = np.eye(4)
    if "applied_transform" in meta:
        A = _matrix(meta["applied_transform"], 3, path, "applied_transform")
    scale = _number(meta.get("applied_scale", 1.0), path, "applied_scale")
    return A, scale


def colmap_to_file(xyz: np.ndarray, meta: Dict[str, Any], path: str = "transforms.json") -> np.ndarray:
    """Points from the original COLMAP frame into the transforms.json frame."""
    A, scale = applied_transform(meta, path)
    return scale * (np.asarray(xyz, np.float64) @ A[:3, :3].T + A[:3, 3])


def _find_image(root: str, file_path: str) -> Optional[str]:
    p = os.path.normpath(os.path.join(root, file_path))
    if os.path.isfile(p):
        return p
    if not os.path.splitext(p)[1]:  # Blender-style paths come without an extension
        for ext in IMAGE_EXTENSIONS:
            if os.path.isfile(p + ext):
                return p + ext
    return None


def _image_name(file_path: str) -> str:
    """The name relative to the images folder, like COLMAP's (so both sort the same)."""
    name = os.path.normpath(file_path).replace(os.sep, "/")
    if name.startswith("images/"):
        name = name[len("images/") :]
    return name


def load_transforms(path: str) -> List[Camera]:
    """Cameras of a nerfstudio transforms.json (a file, or a folder holding one), sorted by name.

    Frames whose photo is missing are skipped with a warning; if no photo exists at all the
    cameras are kept without photos (rendering only needs the cameras).
    """
    if os.path.isdir(path):
        path = os.path.join(path, "transforms.json")
    meta = read_json(path)
    if not isinstance(meta, dict):
        raise TransformsError(f"{path}: expected a JSON object with a 'frames' list")
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise TransformsError(f"{path}: missing key 'frames' (a list of frames)")
    if not frames:
        raise TransformsError(f"{path}: 'frames' is empty")
    root = os.path.dirname(os.path.abspath(path))

    cams: List[Camera] = []
    missing: List[str] = []
    for i, frame in enumerate(frames):
        where = f"frames[{i}]"
        if not isinstance(frame, dict):
            raise TransformsError(f"{path}: {where} is not an object")
        if "file_path" not in frame:
            raise TransformsError(f"{path}: {where} has no 'file_path'")
        if "transform_matrix" not in frame:
            raise TransformsError(f"{path}: {where} has no 'transform_matrix'")
        file_path = str(frame["file_path"])
        image_path = _find_image(root, file_path)
        if image_path is None:
            missing.append(file_path)
        cams.append(_frame_camera(meta, frame, path, where, file_path, image_path))

    if missing and len(missing) < len(frames):
        shown = ", ".join(missing[:10]) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
        warnings.warn(f"{path}: skipping {len(missing)} frame(s) whose image file is missing: {shown}")
        cams = [c for c in cams if c.image_path is not None]
    elif missing:
        warnings.warn(f"{path}: none of the {len(frames)} image files exist; cameras are loaded without photos")
    return sorted(cams, key=lambda c: c.image_name)


def _frame_camera(meta, frame, path, where, file_path, image_path) -> Camera:
    def get(key: str, default: Any = None) -> Any:
        if key in frame:
            return _number(frame[key], path, f"{where}.{key}")
        if key in meta:
            return _number(meta[key], path, key)
        return default

    model = str(frame.get("camera_model", meta.get("camera_model", "OPENCV"))).upper()
    if model not in PERSPECTIVE_MODELS:
        raise TransformsError(
            f"{path}: camera_model '{model}' is not supported (supported: {', '.join(PERSPECTIVE_MODELS)})"
        )

    w, h = get("w"), get("h")
    if w is None or h is None:
        if image_path is None:
            raise TransformsError(f"{path}: {where} has no 'w'/'h' (neither per frame nor top level) "
                                  f"and its image is missing, so the size is unknown")
        import imageio.v3 as iio

        shape = iio.improps(image_path).shape
        h, w = (h or shape[0]), (w or shape[1])

    fx, fy = get("fl_x"), get("fl_y")
    if fx is None:
        angle = get("camera_angle_x")
        if angle is None:
            raise TransformsError(f"{path}: {where} has no 'fl_x' (neither per frame nor top level) "
                                  f"and no 'camera_angle_x'")
        fx = 0.5 * w / math.tan(0.5 * angle)
    if fy is None:
        angle_y = get("camera_angle_y")
        fy = 0.5 * h / math.tan(0.5 * angle_y) if angle_y is not None else fx

    for key in ("k3", "k4"):
        if get(key, 0.0) != 0.0:
            raise TransformsError(f"{path}: {where} has a non-zero '{key}'; only k1, k2, p1, p2 are supported")
    dist = tuple(get(k, 0.0) for k in ("k1", "k2", "p1", "p2"))

    c2w = _matrix(frame["transform_matrix"], 3, path, f"{where}.transform_matrix")
    c2w[:3, 1:3] *= -1.0  # OpenGL camera axes (y up, z back) -> OpenCV (y down, z forward)
    try:
        w2c = np.linalg.inv(c2w)
    except np.linalg.LinAlgError:
        raise TransformsError(f"{path}: {where}.transform_matrix is singular") from None

    return Camera(
        world_to_camera=w2c, fx=fx, fy=fy, cx=get("cx", w / 2.0), cy=get("cy", h / 2.0),
        width=int(round(w)), height=int(round(h)), image_name=_image_name(file_path),
        image_path=image_path, distortion=dist if any(dist) else None,
    )


def ply_path(path: str) -> Optional[str]:
    """The point cloud a transforms.json names (`ply_file_path`), else `sparse_pc.ply` beside it."""
    if os.path.isdir(path):
        path = os.path.join(path, "transforms.json")
    meta = read_json(path)
    root = os.path.dirname(os.path.abspath(path))
    if isinstance(meta, dict) and meta.get("ply_file_path"):
        p = os.path.join(root, str(meta["ply_file_path"]))
        if not os.path.isfile(p):
            raise TransformsError(f"{path}: 'ply_file_path' points to {p}, which does not exist")
        return p
    p = os.path.join(root, "sparse_pc.ply")
    return p if os.path.isfile(p) else None
