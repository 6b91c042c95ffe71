"""Depth Anything (transformers `AutoModelForDepthEstimation`) as a relative-disparity estimator.

Preprocessing follows the checkpoint's image-processor config (loaded with
`AutoImageProcessor.from_pretrained`) but is done in torch on the whole batch: resize to the
processor's size keeping the aspect ratio and rounding to its multiple (14 for the DINOv2 patch),
normalise with its mean/std. The prediction is resized back to the input H×W.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import torch

from gs_regional.data.cameras import Camera
from gs_regional.depth.base import DepthEstimator
from gs_regional.guidance.base import check_images
from gs_regional.utils.pretrained import (
    PretrainedLoadError,
    batches,
    check_local_folder,
    load_pretrained,
    resize,
    resolve_device,
    resolve_dtype,
)
from gs_regional.registry import register

# Model families whose prediction is metric depth rather than relative disparity.
_METRIC_DEPTH_TYPES = {"glpn", "zoedepth", "depth_pro"}
_PIL_RESAMPLE = {0: "nearest", 2: "bilinear", 3: "bicubic"}  # others (lanczos, box, ...) -> bicubic


def _get(size, key):
    """Read a field of a processor size (a transformers SizeDict or a plain dict)."""
    return size.get(key) if isinstance(size, dict) else getattr(size, key, None)


def dpt_resize_size(h: int, w: int, out_h: int, out_w: int, keep_aspect_ratio: bool, multiple: int) -> Tuple[int, int]:
    """The output size of transformers' DPT/Depth Anything resize (get_resize_output_image_size)."""

    def constrain(val: float) -> int:
        x = round(val / multiple) * multiple
        if x < multiple:  # never round a side down to nothing
            x = math.ceil(val / multiple) * multiple
        return int(max(x, multiple))

    scale_h, scale_w = out_h / h, out_w / w
    if keep_aspect_ratio:  # scale as little as possible
        if abs(1 - scale_w) < abs(1 - scale_h):
            scale_h = scale_w
        else:
            scale_w = scale_h
    return constrain(scale_h * h), constrain(scale_w * w)


@register("depth-anything")
class DepthAnything(DepthEstimator):
    @dataclass
    class Config:
        pretrained: str = "depth-anything/Depth-Anything-V2-Small-hf"  # hub id or local folder
        dtype: str = "auto"  # auto = float16 on CUDA, float32 on CPU
        device: str = "auto"
        max_batch_size: int = 4
        local_files_only: bool = False

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where)
        from transformers import AutoConfig, AutoImageProcessor, AutoModelForDepthEstimation
        from transformers.models.auto.modeling_auto import MODEL_FOR_DEPTH_ESTIMATION_MAPPING_NAMES

        c = self.cfg
        if c.max_batch_size < 1:
            raise ValueError(f"max_batch_size must be >= 1, got {c.max_batch_size}")
        self.device = resolve_device(c.device)
        self.dtype = resolve_dtype(c.dtype, self.device)
        p, kw = c.pretrained, dict(local_files_only=c.local_files_only)
        check_local_folder(p, {"": ("config.json",)}, "DepthAnything")
        config = load_pretrained("the depth model config", p, c.local_files_only, lambda: AutoConfig.from_pretrained(p, **kw))
        model_type = getattr(config, "model_type", None)
        if model_type not in MODEL_FOR_DEPTH_ESTIMATION_MAPPING_NAMES:
            raise PretrainedLoadError(
                f"DepthAnything: '{p}' holds a '{model_type}' model ({', '.join(config.architectures or []) or '?'}), "
                f"not a depth-estimation model; expected one of {', '.join(MODEL_FOR_DEPTH_ESTIMATION_MAPPING_NAMES)}"
            )
        check_local_folder(p, {"": ("preprocessor_config.json",)}, "DepthAnything (image processor)")
        self.model = load_pretrained(
            "the depth model", p, c.local_files_only,
            lambda: AutoModelForDepthEstimation.from_pretrained(p, dtype=self.dtype, **kw),
        )
        self.model.requires_grad_(False).eval().to(self.device)
        proc = load_pretrained(
            "the depth image processor", p, c.local_files_only, lambda: AutoImageProcessor.from_pretrained(p, **kw)
        )
        self.metric = model_type in _METRIC_DEPTH_TYPES or getattr(config, "depth_estimation_type", "") == "metric"
        # Preprocessing parameters, read from the processor config.
        self.do_resize = bool(getattr(proc, "do_resize", True))
        size = getattr(proc, "size", None)
        self.size = (_get(size, "height"), _get(size, "width")) if size is not None else (None, None)
        if self.do_resize and None in self.size:
            raise PretrainedLoadError(f"DepthAnything: the image processor of '{p}' has no height/width size: {size}")
        self.keep_aspect_ratio = bool(getattr(proc, "keep_aspect_ratio", False))
        patch = getattr(config, "patch_size", 1) or 1
        self.multiple = int(getattr(proc, "ensure_multiple_of", None) or patch)
        self.mode = _PIL_RESAMPLE.get(int(getattr(proc, "resample", 3) or 3), "bicubic")
        self.do_normalize = bool(getattr(proc, "do_normalize", True))
        self.mean = torch.tensor(list(proc.image_mean), dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(list(proc.image_std), dtype=torch.float32, device=self.device).view(1, 3, 1, 1)

    def input_size(self, h: int, w: int) -> Tuple[int, int]:
        """The size the model sees for an h×w image."""
        if not self.do_resize:
            return dpt_resize_size(h, w, h, w, False, self.multiple)
        return dpt_resize_size(h, w, self.size[0], self.size[1], self.keep_aspect_ratio, self.multiple)

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """(B, H, W, 3) in [0, 1] -> the model's normalised (B, 3, h, w) pixel values, float32."""
        x = images.permute(0, 3, 1, 2).float().to(self.device)
        x = resize(x, self.input_size(*images.shape[1:3]), self.mode).clamp(0, 1)
        if self.do_normalize:
            x = (x - self.mean) / self.std
        return x

    def disparity(self, images: torch.Tensor, cameras: Optional[Sequence[Camera]] = None) -> torch.Tensor:
        """Relative disparity (B, H, W) at the input resolution (larger = nearer), float32.

        Metric-depth models (depth_estimation_type "metric", ZoeDepth, GLPN, DepthPro) are
        inverted to disparity. The prediction is resized back bilinearly (no overshoot)."""
        images = check_images(images)
        b_all, h, w = images.shape[:3]
        x = self.preprocess(images)
        out = []
        with torch.no_grad():
            for s in batches(b_all, self.cfg.max_batch_size):
                pred = self.model(pixel_values=x[s].to(self.dtype)).predicted_depth.float()
                if pred.dim() == 4:  # some heads keep a channel axis
                    pred = pred[:, 0]
                out.append(resize(pred[:, None], (h, w), "bilinear")[:, 0])
        disp = torch.cat(out)
        if self.metric:
            disp = 1.0 / disp.clamp_min(1e-6)
        return disp.to(images.device)
