"""COLMAP sparse models (cameras / images / points3D, in .bin or .txt) -> `Camera`s and points.

Our own parser (struct + numpy), following the formats documented by COLMAP
(src/colmap/scene/reconstruction_io.cc). COLMAP poses are world-to-camera in the OpenCV
convention already; its pixel coordinates put the centre of the top-left pixel at (0.5, 0.5),
which is the convention `Camera` uses (cx = width/2 is the image centre).
"""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from gs_regional.data.cameras import Camera
from gs_regional.utils.rotations import quat_to_rotmat

# model id -> (name, number of parameters), from COLMAP's src/colmap/sensor/models.h
CAMERA_MODELS: Dict[int, Tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
MODEL_IDS = {name: (mid, n) for mid, (name, n) in CAMERA_MODELS.items()}
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


class ColmapError(ValueError):
    """A COLMAP model that cannot be read; the message names the file."""


@dataclass
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # float64, meaning depends on `model`


@dataclass
class ColmapImage:
    id: int
    qvec: np.ndarray  # (4,) w, x, y, z: world-to-camera rotation
    tvec: np.ndarray  # (3,) world-to-camera translation
    camera_id: int
    name: str
    xys: np.ndarray  # (P, 2) keypoints
    point3D_ids: np.ndarray  # (P,) int64, -1 where not triangulated


@dataclass
class ColmapPoints:
    ids: np.ndarray  # (N,) int64
    xyz: np.ndarray  # (N, 3) float64
    rgb: np.ndarray  # (N, 3) uint8
    error: np.ndarray  # (N,) float64


# ----------------------------------------------------------------------------- binary


class _Reader:
    """Sequential reads from a bytes buffer with an error that names the file when it ends early."""

    def __init__(self, path: str) -> None:
        self.path = path
        with open(path, "rb") as f:
            self.data = f.read()
        self.pos = 0

    def take(self, fmt: str):
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise ColmapError(f"{self.path}: file ends early (truncated or not a COLMAP binary model)")
        out = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return out

    def array(self, dtype: str, count: int) -> np.ndarray:
        dt = np.dtype(dtype)
        size = dt.itemsize * count
        if count < 0 or self.pos + size > len(self.data):
            raise ColmapError(f"{self.path}: file ends early (truncated or not a COLMAP binary model)")
        out = np.frombuffer(self.data, dtype=dt, count=count, offset=self.pos)
        self.pos += size
        return out

    def cstring(self) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise ColmapError(f"{self.path}: unterminated image name (truncated file)")
        s = self.data[self.pos : end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return s

    def finish(self) -> None:
        if self.pos != len(self.data):
            raise ColmapError(
                f"{self.path}: {len(self.data) - self.pos} unexpected trailing bytes (not a COLMAP binary model?)"
            )


def _model_info(model_id: int, path: str) -> Tuple[str, int]:
    if model_id not in CAMERA_MODELS:
        raise ColmapError(f"{path}: unknown camera model id {model_id}")
    return CAMERA_MODELS[model_id]


def read_cameras_binary(path: str) -> Dict[int, ColmapCamera]:
    r = _Reader(path)
    (num,) = r.take("<Q")
    cams = {}
    for _ in range(num):
        cam_id, model_id, width, height = r.take("<iiQQ")
        name, n = _model_info(model_id, path)
        params = r.array("<f8", n).astype(np.float64)
        cams[cam_id] = ColmapCamera(cam_id, name, int(width), int(height), params)
    r.finish()
    return cams


def read_images_binary(path: str) -> Dict[int, ColmapImage]:
    r = _Reader(path)
    (num,) = r.take("<Q")
    images = {}
    # One keypoint record: x double, y double, point3D_id int64 (24 bytes).
    kp_dtype = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
    for _ in range(num):
        image_id, qw, qx, qy, qz, tx, ty, tz, cam_id = r.take("<idddddddi")
        name = r.cstring()
        (n_pts,) = r.take("<Q")
        kp = r.array(kp_dtype, n_pts)
        images[image_id] = ColmapImage(
            image_id,
            np.array([qw, qx, qy, qz]),
            np.array([tx, ty, tz]),
            cam_id,
            name,
            np.stack([kp["x"], kp["y"]], axis=1).astype(np.float64),
            kp["id"].astype(np.int64),
        )
    r.finish()
    return images


def read_points3d_binary(path: str) -> ColmapPoints:
    r = _Reader(path)
    (num,) = r.take("<Q")
    ids = np.empty(num, np.int64)
    xyz = np.empty((num, 3), np.float64)
    rgb = np.empty((num, 3), np.uint8)
    err = np.empty(num, np.float64)
    for i in range(num):
        pid, x, y, z, cr, cg, cb, e, track_len = r.take("<QdddBBBdQ")
        r.array("<i4", 2 * track_len)  # the track (image_id, point2D_idx) pairs: not needed here
        ids[i], xyz[i], rgb[i], err[i] = pid, (x, y, z), (cr, cg, cb), e
    r.finish()
    return ColmapPoints(ids, xyz, rgb, err)


# ----------------------------------------------------------------------------- text


def _text_lines(path: str) -> List[Tuple[int, str]]:
    """(line number, line) for every line that is not a comment; blank lines are kept."""
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        return [(i + 1, ln.rstrip("\r\n")) for i, ln in enumerate(f) if not ln.lstrip().startswith("#")]


def _bad_line(path: str, lineno: int, what: str) -> ColmapError:
    return ColmapError(f"{path}, line {lineno}: {what}")


def read_cameras_text(path: str) -> Dict[int, ColmapCamera]:
    cams = {}
    for lineno, line in _text_lines(path):
        tok = line.split()
        if not tok:
            continue
        # CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]
        if len(tok) < 4:
            raise _bad_line(path, lineno, "expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'")
        model = tok[1].upper()
        if model not in MODEL_IDS:
            raise _bad_line(path, lineno, f"unknown camera model '{tok[1]}'")
        n = MODEL_IDS[model][1]
        if len(tok) != 4 + n:
            raise _bad_line(path, lineno, f"camera model {model} needs {n} parameters, got {len(tok) - 4}")
        try:
            cam = ColmapCamera(int(tok[0]), model, int(tok[2]), int(tok[3]), np.array(tok[4:], np.float64))
        except ValueError as e:
            raise _bad_line(path, lineno, f"bad number ({e})") from None
        cams[cam.id] = cam
    return cams


def read_images_text(path: str) -> Dict[int, ColmapImage]:
    lines = _text_lines(path)
    images = {}
    i = 0
    while i < len(lines):
        lineno, line = lines[i]
        if not line.strip():  # stray blank line between records
            i += 1
            continue
        # IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then one line of (X Y POINT3D_ID)*;
        # the second line is empty for an image without keypoints (and may be missing at EOF).
        tok = line.split(maxsplit=9)
        if len(tok) != 10:
            raise _bad_line(path, lineno, "expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'")
        pts_line = lines[i + 1][1] if i + 1 < len(lines) else ""
        try:
            vals = np.array(tok[1:8], np.float64)
            pts = np.array(pts_line.split(), np.float64).reshape(-1, 3)
            img = ColmapImage(
                int(tok[0]), vals[:4], vals[4:7], int(tok[8]), tok[9].strip(),
                pts[:, :2].copy(), pts[:, 2].astype(np.int64),
            )
        except ValueError as e:
            raise _bad_line(path, lineno, f"bad image record ({e})") from None
        images[img.id] = img
        i += 2
    return images


def read_points3d_text(path: str) -> ColmapPoints:
    ids, xyz, rgb, err = [], [], [], []
    for lineno, line in _text_lines(path):
        tok = line.split()
        if not tok:
            continue
        # POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)
        if len(tok) < 8:
            raise _bad_line(path, lineno, "expected 'POINT3D_ID X Y Z R G B ERROR TRACK...'")
        try:
            ids.append(int(tok[0]))
            xyz.append([float(t) for t in tok[1:4]])
            rgb.append([int(t) for t in tok[4:7]])
            err.append(float(tok[7]))
        except ValueError as e:
            raise _bad_line(path, lineno, f"bad number ({e})") from None
    return ColmapPoints(
        np.array(ids, np.int64),
        np.array(xyz, np.float64).reshape(-1, 3),
        np.clip(np.array(rgb, np.int64).reshape(-1, 3), 0, 255).astype(np.uint8),
        np.array(err, np.float64),
    )


# ----------------------------------------------------------------------------- model folders


def model_file(model_dir: str, stem: str) -> Optional[str]:
    """`<model_dir>/<stem>.bin` or `.txt` (binary preferred, as COLMAP does), or None."""
    for ext in (".bin", ".txt"):
        p = os.path.join(model_dir, stem + ext)
        if os.path.isfile(p):
            return p
    return None


def is_model_dir(path: str) -> bool:
    return os.path.isdir(path) and model_file(path, "cameras") is not None


def _read(model_dir: str, stem: str, readers):
    path = model_file(model_dir, stem)
    if path is None:
        raise ColmapError(f"COLMAP model {model_dir}: neither {stem}.bin nor {stem}.txt exists")
    try:
        return readers[path.endswith(".txt")](path)
    except (ColmapError, OSError):
        raise
    except (struct.error, UnicodeDecodeError, ValueError) as e:
        raise ColmapError(f"{path}: cannot parse ({e})") from None


def read_cameras(model_dir: str) -> Dict[int, ColmapCamera]:
    return _read(model_dir, "cameras", (read_cameras_binary, read_cameras_text))


def read_images(model_dir: str) -> Dict[int, ColmapImage]:
    return _read(model_dir, "images", (read_images_binary, read_images_text))


def read_points3d(model_dir: str) -> ColmapPoints:
    return _read(model_dir, "points3D", (read_points3d_binary, read_points3d_text))


# ----------------------------------------------------------------------------- conversion


def intrinsics(cam: ColmapCamera, where: str = "") -> Tuple[float, float, float, float, Optional[tuple]]:
    """(fx, fy, cx, cy, distortion or None) of a COLMAP camera; unsupported models are an error."""
    p = cam.params
    m = cam.model
    if m == "SIMPLE_PINHOLE":
        f, cx, cy = p
        return f, f, cx, cy, None
    if m == "PINHOLE":
        fx, fy, cx, cy = p
        return fx, fy, cx, cy, None
    if m == "SIMPLE_RADIAL":
        f, cx, cy, k = p
        return f, f, cx, cy, (k, 0.0, 0.0, 0.0)
    if m == "RADIAL":  # same forward model as SIMPLE_RADIAL with a second radial term
        f, cx, cy, k1, k2 = p
        return f, f, cx, cy, (k1, k2, 0.0, 0.0)
    if m == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p
        return fx, fy, cx, cy, (k1, k2, p1, p2)
    raise ColmapError(
        f"{where or 'COLMAP model'}: camera {cam.id} uses the {m} camera model, which is not supported "
        f"(supported: {', '.join(SUPPORTED_MODELS)}); undistort the images first, e.g. "
        f"`colmap image_undistorter`, and use the resulting PINHOLE model"
    )


def _find_image(model_dir: str, name: str) -> Optional[str]:
    """`<scene>/images/<name>`, where the scene is the model folder or one of its first 3 parents."""
    d = os.path.abspath(model_dir)
    for _ in range(4):
        p = os.path.join(d, "images", name)
        if os.path.isfile(p):
            return p
        d = os.path.dirname(d)
    return None


def load_colmap_cameras(model_dir: str) -> List[Camera]:
    """Every registered image of a COLMAP model as a `Camera`, sorted by image name."""
    cams = read_cameras(model_dir)
    images = read_images(model_dir)
    where = model_file(model_dir, "cameras")
    out = []
    for img in images.values():
        if img.camera_id not in cams:
            raise ColmapError(
                f"{model_file(model_dir, 'images')}: image '{img.name}' refers to camera {img.camera_id}, "
                f"which is not in {where}"
            )
        cam = cams[img.camera_id]
        fx, fy, cx, cy, dist = intrinsics(cam, where)
        if dist is not None and not any(dist):
            dist = None
        w2c = np.eye(4)
        w2c[:3, :3] = quat_to_rotmat(torch.as_tensor(img.qvec, dtype=torch.float64)).numpy()
        w2c[:3, 3] = img.tvec
        out.append(
            Camera(
                world_to_camera=w2c, fx=fx, fy=fy, cx=cx, cy=cy, width=cam.width, height=cam.height,
                image_name=img.name, image_path=_find_image(model_dir, img.name),
                distortion=None if dist is None else tuple(float(v) for v in dist),
            )
        )
    return sorted(out, key=lambda c: c.image_name)
