"""Depth Anything (transformers `AutoModelForDepthEstimation`) as a relative-disparity estimator.

Preprocessing follows the checkpoint's image-processor config (loaded with
`AutoImageProcessor.from_pretrained`) but is done in torch on the whole batch: resize to the
processor's size keeping the aspect ratio and rounding to its multiple (14 for the DINOv2 patch),
normalise with its mean/std. The prediction is resized back to the input H×W.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import torch

from gs_regional.data.cameras import Camera
from gs_regional.depth.base import DepthEstimator
from gs_regional.registry import register
from gs_regional.utils.image import resize, to_nchw
from gs_regional.utils.pretrained import (
    Pretrained,
    PretrainedLoadError,
    batches,
    processor_normalization,
    processor_resample,
    processor_size,
)

# Model families whose prediction is metric depth rather than relative disparity.
_METRIC_DEPTH_TYPES = {"glpn", "zoedepth", "depth_pro"}


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
        from transformers import AutoImageProcessor, AutoModelForDepthEstimation
        from transformers.models.auto.modeling_auto import MODEL_FOR_DEPTH_ESTIMATION_MAPPING_NAMES

        c = self.cfg
        source = self.check_source(c)
        self.device, self.dtype = source.device, source.dtype
        config = source.load_config(MODEL_FOR_DEPTH_ESTIMATION_MAPPING_NAMES, "depth-estimation")
        source.require({"": ("preprocessor_config.json",)}, "image processor")
        self.model = source.load_frozen("the depth model", AutoModelForDepthEstimation.from_pretrained, dtype=self.dtype)
        proc = source.load("the depth image processor", AutoImageProcessor.from_pretrained)
        self.metric = config.model_type in _METRIC_DEPTH_TYPES or getattr(config, "depth_estimation_type", "") == "metric"
        # Preprocessing parameters, read from the processor config.
        self.do_resize = bool(getattr(proc, "do_resize", True))
        size = getattr(proc, "size", None)
        self.size = (processor_size(size, "height"), processor_size(size, "width"))
        if self.do_resize and None in self.size:
            raise PretrainedLoadError(f"DepthAnything: the image processor of '{c.pretrained}' has no height/width size: {size}")
        self.keep_aspect_ratio = bool(getattr(proc, "keep_aspect_ratio", False))
        patch = getattr(config, "patch_size", 1) or 1
        self.multiple = int(getattr(proc, "ensure_multiple_of", None) or patch)
        self.mode = processor_resample(proc)
        self.do_normalize = bool(getattr(proc, "do_normalize", True))
        self.mean, self.std = processor_normalization(proc, self.device)

    @classmethod
    def check_source(cls, c: "DepthAnything.Config") -> Pretrained:
        """The checks that need no weights (a parsed config): the device, and the folder with its
        config (or the hub id in the cache or on the hub)."""
        source = Pretrained("DepthAnything", c.pretrained, c.device, c.dtype, c.local_files_only, c.max_batch_size,
                            key="system.depth.pretrained")
        source.require({"": ("config.json",)})
        return source

    def input_size(self, h: int, w: int) -> Tuple[int, int]:
        """The size the model sees for an h×w image."""
        if not self.do_resize:
            return dpt_resize_size(h, w, h, w, False, self.multiple)
        return dpt_resize_size(h, w, self.size[0], self.size[1], self.keep_aspect_ratio, self.multiple)

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """(B, H, W, 3) in [0, 1] -> the model's normalised (B, 3, h, w) pixel values, float32."""
        x = to_nchw(images).to(self.device)
        x = resize(x, self.input_size(*images.shape[1:3]), self.mode).clamp(0, 1)
        if self.do_normalize:
            x = (x - self.mean) / self.std
        return x

    def _disparity(self, images: torch.Tensor, cameras: Optional[List[Camera]]) -> torch.Tensor:
        """Relative disparity (B, H, W) at the input resolution (larger = nearer), float32.

        Metric-depth models (depth_estimation_type "metric", ZoeDepth, GLPN, DepthPro) are
        inverted to disparity. The prediction is resized back bilinearly (no overshoot)."""
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
