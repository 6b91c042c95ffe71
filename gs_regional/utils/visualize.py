"""Images, image grids, mask overlays and videos for the files systems write into `save/`.

Images are (H, W, 3) (or (H, W) / (H, W, 1) grey, (H, W, 4) RGBA) torch tensors or numpy arrays,
float in [0, 1] or uint8. Every file is written atomically (temporary file + rename), so a run
killed while writing never leaves a truncated image or video behind.
"""
from __future__ import annotations

import os
import warnings
from typing import Any, List, Optional, Sequence, Tuple

import numpy as np

from gs_regional.utils.io import atomic_write

__all__ = ["to_uint8", "make_grid", "save_image", "save_video", "overlay_mask"]


def _to_numpy(img: Any, what: str = "image") -> np.ndarray:
    try:
        import torch

        if isinstance(img, torch.Tensor):
            img = img.detach().cpu()
            if img.dtype in (torch.bfloat16, torch.float16):
                img = img.float()
            return img.numpy()
    except ImportError:  # pragma: no cover - torch is a hard dependency, kept for clarity
        pass
    if isinstance(img, np.ndarray):
        return img
    try:
        return np.asarray(img)
    except Exception:
        raise TypeError(f"{what} must be a torch tensor or numpy array, got {type(img).__name__}") from None


def to_uint8(img: Any, what: str = "image") -> np.ndarray:
    """(H, W, 3) uint8 from a float image in [0, 1] (clipped; NaN -> 0), a uint8 image or a bool mask.

    Grey (H, W) / (H, W, 1) images are repeated to 3 channels; RGBA is composited over white.
    """
    a = _to_numpy(img, what)
    if a.ndim == 3 and a.shape[-1] == 1:
        a = a[..., 0]
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.ndim != 3 or a.shape[-1] not in (3, 4) or a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{what} must have shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4); got {a.shape}")
    if a.dtype == np.uint8:
        out = a
    elif a.dtype == np.bool_:
        out = a.astype(np.uint8) * 255
    elif np.issubdtype(a.dtype, np.number):
        f = np.nan_to_num(a.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
        out = (np.clip(f, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    else:
        raise TypeError(f"{what} has unsupported dtype {a.dtype}")
    if out.shape[-1] == 4:  # composite over white: PNG viewers differ on how they show alpha
        rgb, alpha = out[..., :3].astype(np.float32), out[..., 3:].astype(np.float32) / 255.0
        out = (rgb * alpha + 255.0 * (1.0 - alpha) + 0.5).astype(np.uint8)
    return np.ascontiguousarray(out)


def _draw_label(strip: np.ndarray, text: str) -> np.ndarray:
    """Write `text` in black onto a white (h, w, 3) uint8 strip with Pillow's built-in font."""
    from PIL import Image, ImageDraw

    im = Image.fromarray(strip)
    ImageDraw.Draw(im).text((2, 1), text, fill=(0, 0, 0))
    return np.asarray(im)


LABEL_HEIGHT = 14


def make_grid(
    rows: Sequence[Sequence[Any]],
    labels: Optional[Sequence[Sequence[Optional[str]]]] = None,
    margin: int = 4,
    background: int = 255,
) -> np.ndarray:
    """Tile images into one (H, W, 3) uint8 image: `rows[r][c]` goes to row r, column c.

    Cells are as tall as the tallest image of their row and as wide as the widest of their column
    (smaller images sit at the top left); `margin` pixels of `background` separate them.
    `labels`, if given, has the same nesting as `rows` (entries may be None) and is drawn as a
    caption strip above each image.
    """
    if len(rows) == 0 or any(len(r) == 0 for r in rows):
        raise ValueError("make_grid needs at least one image in every row")
    imgs = [[to_uint8(im, f"grid image [{r}][{c}]") for c, im in enumerate(row)] for r, row in enumerate(rows)]
    if labels is not None:
        if len(labels) != len(rows) or any(
            isinstance(lr, str) or len(lr) != len(r) for lr, r in zip(labels, rows)
        ):
            raise ValueError(
                "labels must have the same nesting as rows (a list of lists, one entry per image); "
                f"rows have lengths {[len(r) for r in rows]}"
            )
    ncols = max(len(r) for r in imgs)
    row_h = [max(im.shape[0] for im in row) for row in imgs]
    col_w = [max(row[c].shape[1] for row in imgs if c < len(row)) for c in range(ncols)]
    label_h = LABEL_HEIGHT if labels is not None else 0
    height = sum(row_h) + len(imgs) * label_h + (len(imgs) + 1) * margin
    width = sum(col_w) + (ncols + 1) * margin
    grid = np.full((height, width, 3), background, dtype=np.uint8)
    y = margin
    for r, row in enumerate(imgs):
        x = margin
        for c in range(ncols):
            if c < len(row):
                im = row[c]
                if labels is not None and labels[r][c]:
                    strip = np.full((label_h, col_w[c], 3), 255, dtype=np.uint8)
                    grid[y : y + label_h, x : x + col_w[c]] = _draw_label(strip, str(labels[r][c]))
                grid[y + label_h : y + label_h + im.shape[0], x : x + im.shape[1]] = im
            x += col_w[c] + margin
        y += row_h[r] + label_h + margin
    return grid


def _check_path(path: Any) -> str:
    path = os.fspath(path)
    if not os.path.splitext(path)[1]:
        raise ValueError(f"cannot tell the image format of '{path}': give it an extension such as .png")
    return path


def save_image(path: Any, img: Any) -> str:
    """Write an image (format from the extension: .png, .jpg, ...) atomically; returns the path."""
    import imageio.v3 as iio

    path = _check_path(path)
    data = to_uint8(img)
    ext = os.path.splitext(path)[1]
    with atomic_write(path) as tmp:
        iio.imwrite(tmp, data, extension=ext)
    return path


def _video_frames(frames: Sequence[Any]) -> List[np.ndarray]:
    if len(frames) == 0:
        raise ValueError("save_video needs at least one frame")
    out = [to_uint8(f, f"video frame {i}") for i, f in enumerate(frames)]
    shape = out[0].shape
    for i, f in enumerate(out):
        if f.shape != shape:
            raise ValueError(f"video frames must all have the same size; frame 0 is {shape}, frame {i} is {f.shape}")
    # H.264 in yuv420p needs even sizes: pad by one row/column of edge pixels rather than rescale.
    h, w = shape[:2]
    ph, pw = h % 2, w % 2
    if ph or pw:
        out = [np.pad(f, ((0, ph), (0, pw), (0, 0)), mode="edge") for f in out]
    return out


def _write_mp4(path: str, frames: List[np.ndarray], fps: float) -> None:
    import imageio.v2 as imageio

    writer = imageio.get_writer(
        path, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=8,
        pixelformat="yuv420p", macro_block_size=1, ffmpeg_log_level="error",
    )
    try:
        for f in frames:
            writer.append_data(f)
    finally:
        writer.close()


def _write_gif(path: str, frames: List[np.ndarray], fps: float) -> None:
    import imageio.v3 as iio

    # Pillow merges identical consecutive frames; that only changes timing, not what is shown.
    iio.imwrite(path, np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0)


def save_video(path: Any, frames: Sequence[Any], fps: float = 24) -> str:
    """Write frames as an H.264 mp4 (imageio-ffmpeg) atomically; returns the path written.

    If the mp4 writer fails (no ffmpeg binary, no codec), writes `<path without ext>.gif` instead
    with a warning that says why, and returns that path.
    """
    path = os.fspath(path)
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    data = _video_frames(frames)
    if os.path.splitext(path)[1].lower() == ".gif":
        with atomic_write(path) as tmp:
            _write_gif(tmp + ".gif", data, fps)
            os.replace(tmp + ".gif", tmp)
        return path
    try:
        with atomic_write(path) as tmp:
            # The ffmpeg writer picks the container from the extension, so the temp name keeps it.
            tmp_mp4 = tmp + os.path.splitext(path)[1]
            try:
                _write_mp4(tmp_mp4, data, fps)
                os.replace(tmp_mp4, tmp)
            finally:
                if os.path.exists(tmp_mp4):
                    os.remove(tmp_mp4)
        return path
    except Exception as e:
        gif = os.path.splitext(path)[0] + ".gif"
        warnings.warn(
            f"ffmpeg is unavailable for writing {path} ({type(e).__name__}: {e}); wrote a GIF instead: {gif}",
            RuntimeWarning,
            stacklevel=2,
        )
        with atomic_write(gif) as tmp:
            _write_gif(tmp + ".gif", data, fps)
            os.replace(tmp + ".gif", tmp)
        return gif


def overlay_mask(
    image: Any,
    mask: Any,
    color: Tuple[float, float, float] = (1.0, 0.0, 0.0),
    alpha: float = 0.5,
) -> Any:
    """Tint `image` (H, W, 3) towards `color` where `mask` (H, W) is set (soft masks blend partly).

    Returns float in [0, 1], a torch tensor if `image` is one (on its device), else a numpy array.
    """
    is_torch = False
    try:
        import torch

        is_torch = isinstance(image, torch.Tensor)
    except ImportError:  # pragma: no cover
        pass
    img = _to_numpy(image, "image")
    if img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    img = img.astype(np.float32)
    if img.ndim != 3 or img.shape[-1] != 3:
        raise ValueError(f"overlay_mask: image must be (H, W, 3), got {img.shape}")
    m = _to_numpy(mask, "mask").astype(np.float32)
    if m.ndim == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if m.shape != img.shape[:2]:
        raise ValueError(f"overlay_mask: mask must be (H, W) = {img.shape[:2]}, got {m.shape}")
    w = np.clip(m, 0.0, 1.0)[..., None] * float(alpha)
    out = np.clip(img * (1.0 - w) + np.asarray(color, dtype=np.float32) * w, 0.0, 1.0)
    if is_torch:
        return torch.from_numpy(out).to(image.device)
    return out
