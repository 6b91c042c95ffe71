"""Photos (reading, resizing, undistortion) and SfM points in the cameras' frame."""
import struct
import zlib

import imageio.v3 as iio
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from trial_helpers import shared_path
from gs_regional.api import load_cameras
from gs_regional.data.cameras import Camera
from gs_regional.data.images import ImageLoadError, load_image, read_image, undistort_image
from gs_regional.data.points import load_points
from test_cameras import POINTS_RGB, POINTS_XYZ, make_transforms, write_colmap

DIST = (-0.15, 0.05, 0.004, -0.003)
W, H = 96, 80


def camera(distortion=DIST, path=None):
    return Camera(torch.eye(4), fx=80.0, fy=84.0, cx=48.3, cy=39.6, width=W, height=H,
                  image_name="x.png", image_path=path, distortion=distortion)


def pattern(u, v):
    """A smooth test image (period >= 12 px, so bilinear sampling is accurate), (..., 3)."""
    return np.stack([
        0.5 + 0.25 * np.sin(2 * np.pi * u / 13) + 0.2 * np.cos(2 * np.pi * v / 15),
        0.5 + 0.3 * np.sin(2 * np.pi * (u + v) / 17),
        0.5 + 0.3 * np.cos(2 * np.pi * (u - 0.5 * v) / 19),
    ], -1)


def undistort_points_iterative(xd, yd, d, iters=50):
    """Inverse of the OpenCV forward model by fixed-point iteration (cv::undistortPoints),
    written here independently of the library, to *make* a distorted photo."""
    k1, k2, p1, p2 = d
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x, y = (xd - dx) / radial, (yd - dy) / radial
    return x, y


def distorted_photo(cam):
    """What a lens with `cam.distortion` records of the pinhole scene `pattern`."""
    v, u = np.meshgrid(np.arange(cam.height) + 0.5, np.arange(cam.width) + 0.5, indexing="ij")
    x, y = undistort_points_iterative((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, cam.distortion)
    return pattern(x * cam.fx + cam.cx, y * cam.fy + cam.cy), pattern(u, v)


def interior_error(a, b, margin=8):
    d = np.abs(np.asarray(a) - np.asarray(b))[margin:-margin, margin:-margin]
    return d.mean(), d.max()


def test_undistort_recovers_pinhole_image():
    cam = camera()
    photo, truth = distorted_photo(cam)
    out = undistort_image(torch.from_numpy(photo).float(), cam).numpy()
    mean, mx = interior_error(out, truth)
    assert mean < 0.005 and mx < 0.03, (mean, mx)
    # The test can fail: the photo itself, or undistorting with the wrong sign, is far off.
    assert interior_error(photo, truth)[0] > 0.02
    wrong = undistort_image(torch.from_numpy(photo).float(), camera(tuple(-d for d in DIST))).numpy()
    assert interior_error(wrong, truth)[0] > 0.02


def test_zero_distortion_is_identity():
    img = torch.rand(H, W, 3)
    assert torch.equal(undistort_image(img, camera(None)), img)
    assert torch.equal(undistort_image(img, camera((0.0, 0.0, 0.0, 0.0))), img)
    # A negligible distortion goes through grid_sample: pixel centres map onto themselves.
    out = undistort_image(img, camera((1e-12, 0.0, 0.0, 0.0)))
    assert torch.allclose(out, img, atol=1e-5)


def write_png16(path, rgb16):
    """A 16-bit RGB PNG, written by hand (Pillow cannot write them)."""
    h, w, _ = rgb16.shape
    raw = b"".join(b"\x00" + rgb16[i].astype(">u2").tobytes() for i in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0))
                + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def test_load_image_undistorts_16bit_and_scales(tmp_path):
    cam = camera(path=str(tmp_path / "x.png"))
    photo, truth = distorted_photo(cam)
    write_png16(cam.image_path, np.round(np.clip(photo, 0, 1) * 65535).astype(np.uint16))
    out = load_image(cam)
    assert out.dtype == torch.float32 and out.shape == (H, W, 3)
    mean, mx = interior_error(out.numpy(), truth)
    assert mean < 0.005 and mx < 0.03, (mean, mx)
    # At half size: the same as shrinking the true pinhole image.
    half = load_image(cam.scaled(0.5))
    assert half.shape == (H // 2, W // 2, 3)
    ref = F.interpolate(torch.from_numpy(truth).float().permute(2, 0, 1)[None], size=(H // 2, W // 2),
                        mode="bilinear", antialias=True)[0].permute(1, 2, 0)
    assert interior_error(half.numpy(), ref.numpy(), margin=4)[0] < 0.01
    assert load_image(cam.scaled(0.5), scale_to_camera=False).shape == (H, W, 3)


def test_read_image_formats(tmp_path):
    rgb = (np.arange(4 * 5 * 3).reshape(4, 5, 3) * 3).astype(np.uint8)
    iio.imwrite(tmp_path / "rgb.png", rgb)
    assert torch.allclose(read_image(str(tmp_path / "rgb.png")), torch.from_numpy(rgb / 255.0).float())
    grey = (np.arange(20).reshape(4, 5) * 10).astype(np.uint8)
    iio.imwrite(tmp_path / "grey.png", grey)
    g = read_image(str(tmp_path / "grey.png"))
    assert g.shape == (4, 5, 3) and torch.allclose(g[..., 1], torch.from_numpy(grey / 255.0).float())
    grey16 = (np.arange(20).reshape(4, 5) * 3000).astype(np.uint16)
    iio.imwrite(tmp_path / "grey16.png", grey16)
    g16 = read_image(str(tmp_path / "grey16.png"))
    assert torch.allclose(g16[..., 2], torch.from_numpy(grey16 / 65535.0).float())
    rgba = np.concatenate([rgb, np.full((4, 5, 1), 0, np.uint8)], -1)
    rgba[0, 0, 3] = 255
    iio.imwrite(tmp_path / "rgba.png", rgba)
    a = read_image(str(tmp_path / "rgba.png"))
    assert a.shape == (4, 5, 3) and a[1:].abs().max() == 0  # transparent -> black
    assert torch.allclose(a[0, 0], torch.from_numpy(rgb[0, 0] / 255.0).float())
    with pytest.raises(ImageLoadError, match="not found.*nothere.png"):
        read_image(str(tmp_path / "nothere.png"))
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(ImageLoadError, match="broken.png"):
        read_image(str(tmp_path / "broken.png"))
    wrong = camera(None, str(tmp_path / "rgb.png"))  # 5x4 photo for a 96x80 camera
    with pytest.raises(ImageLoadError, match="rgb.png.*aspect"):
        load_image(wrong)


def test_face_images_downscale():
    import warnings

    scene = shared_path("face")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cam = load_cameras(str(scene))[0]
    small = load_image(cam.scaled(0.25))
    assert small.shape == (128, 128, 3) and 0 <= small.min() and small.max() <= 1
    full = load_image(cam)
    assert full.shape == (512, 512, 3)
    # Antialiased shrink ~ 4x4 box average of the full-size undistorted photo.
    box = F.avg_pool2d(full.permute(2, 0, 1)[None], 4)[0].permute(1, 2, 0)
    assert (small - box).abs().mean() < 0.02


# ----------------------------------------------------------------------------- points


@pytest.mark.parametrize("binary", [True, False])
def test_colmap_points(tmp_path, binary):
    write_colmap(str(tmp_path / "sparse/0"), binary=binary)
    xyz, rgb = load_points(str(tmp_path))
    assert xyz.dtype == np.float32 and rgb.dtype == np.float32
    np.testing.assert_allclose(xyz, POINTS_XYZ, atol=1e-6)
    np.testing.assert_allclose(rgb, POINTS_RGB / 255.0, atol=1e-6)


def write_ply(path, xyz, rgb):
    from plyfile import PlyData, PlyElement

    v = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, k in enumerate("xyz"):
        v[k] = xyz[:, i]
    for i, k in enumerate(("red", "green", "blue")):
        v[k] = rgb[:, i]
    PlyData([PlyElement.describe(v, "vertex")], text=True).write(str(path))


# nerfstudio's applied_transform for COLMAP data: X_file = A @ X_colmap.
A = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]])


def make_nerfstudio_scene(folder, ply_frame):
    """Cameras looking at a cloud in the file frame, plus the cloud in
    `ply_frame` ('file': as nerfstudio writes it now, 'colmap': the original frame)."""
    make_transforms(folder, per_frame=False, n=4, extra={"applied_transform": A.tolist(), "ply_file_path": "pc.ply"})
    rng = np.random.default_rng(0)
    # Off the origin, so that the two frames differ for the cameras (centred clouds look alike).
    x_file = rng.normal(scale=0.2, size=(200, 3)) + [1.0, 0.0, 1.5]
    x_colmap = (x_file - A[:, 3]) @ A[:, :3]  # A[:, :3] is orthogonal: its inverse is its transpose
    rgb = rng.integers(0, 256, size=(200, 3)).astype(np.uint8)
    write_ply(folder / "pc.ply", x_file if ply_frame == "file" else x_colmap, rgb)
    return x_file, x_colmap, rgb


@pytest.mark.parametrize("ply_frame", ["file", "colmap"])
def test_nerfstudio_points_follow_cameras_frame(tmp_path, ply_frame):
    x_file, _, rgb = make_nerfstudio_scene(tmp_path, ply_frame)
    xyz, rgb_loaded = load_points(str(tmp_path))
    np.testing.assert_allclose(xyz, x_file, atol=1e-5)
    np.testing.assert_allclose(rgb_loaded, rgb / 255.0, atol=1e-6)


def test_nerfstudio_colmap_points_get_applied_transform(tmp_path):
    write_colmap(str(tmp_path / "colmap/sparse/0"), binary=True)
    make_transforms(tmp_path, per_frame=False, extra={"applied_transform": A.tolist(), "applied_scale": 2.0})
    xyz, _ = load_points(str(tmp_path))
    np.testing.assert_allclose(xyz, 2.0 * (POINTS_XYZ @ A[:, :3].T + A[:, 3]), atol=1e-5)


def test_points_absent_or_broken(tmp_path):
    assert load_points(str(tmp_path)) is None  # an empty folder has no points
    with pytest.raises(ValueError, match="does not exist.*nope"):
        load_points(str(tmp_path / "nope"))
    make_transforms(tmp_path, per_frame=False)
    assert load_points(str(tmp_path)) is None
    (tmp_path / "sparse_pc.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nend_header\n")
    with pytest.raises(ValueError, match="sparse_pc.ply"):
        load_points(str(tmp_path))


def test_face_points_match_ply():
    from plyfile import PlyData

    scene = shared_path("face")
    xyz, rgb = load_points(str(scene))
    v = PlyData.read(str(scene / "sparse_pc.ply"))["vertex"]
    # nerfstudio wrote this ply in the transforms.json frame already: it is used as it is.
    np.testing.assert_array_equal(xyz[:, 0], np.asarray(v["x"], np.float32))
    np.testing.assert_allclose(rgb[:, 0], np.asarray(v["red"]) / 255.0)
