"""Photos of a camera as (H, W, 3) float tensors in [0, 1], resized and undistorted to its pinhole."""
from __future__ import annotations

import os
import warnings

import numpy as np
import torch
import torch.nn.functional as F

from gs_regional.data.cameras import Camera


class ImageLoadError(ValueError):
    """A photo that cannot be used; the message names the file."""


def read_image(path: str) -> torch.Tensor:
    """Any 8/16-bit or float image file -> (H, W, 3) float32 in [0, 1].

    Grey is expanded to RGB; an alpha channel is composited on black (what the renders use
    as background by default).
    """
    import imageio.v3 as iio

    if not path or not os.path.isfile(path):
        raise ImageLoadError(f"image file not found: {path}")
    try:
        with warnings.catch_warnings():  # imageio's plugin search warns about deprecated plugins
            warnings.simplefilter("ignore", DeprecationWarning)
            arr = np.asarray(iio.imread(path))
    except Exception as e:  # imageio raises many types for unreadable files
        raise ImageLoadError(f"cannot read image {path}: {e}") from None
    if np.issubdtype(arr.dtype, np.integer):
        # Pillow hands some 16-bit PNGs over as int32 ("I" mode): wider ints hold 16-bit data.
        top = float(np.iinfo(arr.dtype).max) if arr.dtype.itemsize <= 2 else 65535.0
        img = np.clip(arr.astype(np.float32) / top, 0.0, 1.0)
    elif np.issubdtype(arr.dtype, np.floating):
        img = np.clip(arr.astype(np.float32), 0.0, 1.0)
    elif arr.dtype == bool:
        img = arr.astype(np.float32)
    else:
        raise ImageLoadError(f"{path}: unsupported pixel type {arr.dtype}")
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3:
        raise ImageLoadError(f"{path}: expected a single image, got an array of shape {arr.shape}")
    c = img.shape[2]
    if c == 1:
        img = np.repeat(img, 3, axis=2)
    elif c == 2:  # grey + alpha
        img = np.repeat(img[..., :1] * img[..., 1:], 3, axis=2)
    elif c == 4:
        img = img[..., :3] * img[..., 3:]
    elif c != 3:
        raise ImageLoadError(f"{path}: unsupported number of channels {c}")
    return torch.from_numpy(np.ascontiguousarray(img))


def resize_image(image: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(H, W, C) -> (height, width, C); antialiased when shrinking so no detail aliases."""
    if image.shape[0] == height and image.shape[1] == width:
        return image
    x = image.permute(2, 0, 1)[None]
    shrink = height < image.shape[0] or width < image.shape[1]
    x = F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False, antialias=shrink)
    return x[0].permute(1, 2, 0).clamp(0.0, 1.0).contiguous()


def distort_points(x: torch.Tensor, y: torch.Tensor, distortion) -> tuple:
    """OpenCV forward model on normalised coordinates: k1, k2 radial, p1, p2 tangential."""
    k1, k2, p1, p2 = distortion
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def undistort_image(image: torch.Tensor, camera: Camera) -> torch.Tensor:
    """The photo `image` (H, W, C) as the distortion-free pinhole view of `camera`.

    The intrinsics are rescaled to the image's size. For each output pixel centre (pixel i is
    centred at i + 0.5, COLMAP's convention) the forward model gives where that ray hits the
    distorted photo, which is sampled bilinearly: exact, no iterative inversion.
    """
    dist = camera.distortion
    if dist is None or not any(dist):
        return image
    H, W = image.shape[:2]
    sx, sy = W / camera.width, H / camera.height
    fx, fy, cx, cy = camera.fx * sx, camera.fy * sy, camera.cx * sx, camera.cy * sy
    dev = image.device
    v, u = torch.meshgrid(
        torch.arange(H, dtype=torch.float64, device=dev) + 0.5,
        torch.arange(W, dtype=torch.float64, device=dev) + 0.5,
        indexing="ij",
    )
    xd, yd = distort_points((u - cx) / fx, (v - cy) / fy, [float(d) for d in dist])
    us, vs = fx * xd + cx, fy * yd + cy
    # grid_sample with align_corners=False: -1 and +1 are the outer edges of the image.
    grid = torch.stack([2 * us / W - 1, 2 * vs / H - 1], dim=-1).to(image.dtype)
    out = F.grid_sample(
        image.permute(2, 0, 1)[None], grid[None], mode="bilinear", padding_mode="border", align_corners=False
    )
    return out[0].permute(1, 2, 0).contiguous()


def load_image(camera: Camera, scale_to_camera: bool = True) -> torch.Tensor:
    """The photo of `camera` as (H, W, 3) float32 in [0, 1], undistorted when the camera has
    distortion, at the camera's width/height (or the file's size if `scale_to_camera` is False).

    Undistortion happens at the file's resolution and the result is then shrunk with an
    antialiased filter, so a camera `.scaled(0.25)` gets a clean small image.
    """
    if not camera.image_path:
        raise ImageLoadError(f"camera '{camera.image_name}' has no image file")
    img = read_image(camera.image_path)
    H, W = img.shape[:2]
    # A photo whose aspect ratio differs from the camera's is the wrong photo (or a crop).
    aspect_err = abs((W / camera.width) / (H / camera.height) - 1.0)
    if aspect_err > 0.01 + 1.0 / min(camera.width, camera.height):
        raise ImageLoadError(
            f"{camera.image_path}: image is {W}x{H} but camera '{camera.image_name}' is "
            f"{camera.width}x{camera.height} (different aspect ratio)"
        )
    img = undistort_image(img, camera)
    if scale_to_camera:
        img = resize_image(img, camera.height, camera.width)
    return img
