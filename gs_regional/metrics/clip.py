"""CLIP metrics of an edit (DESIGN §3.4): text-image direction similarity and image-image similarity.

Embeddings are L2-normalised before differences are taken, as in the InstructPix2Pix / IN2N
evaluation code. Preprocessing follows the checkpoint's CLIP image-processor config (resize the
shortest edge, center crop, mean/std) but runs in torch on the batch.
"""
from __future__ import annotations

from typing import List, Sequence, Tuple, Union

import torch
import torch.nn.functional as F

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

_PIL_RESAMPLE = {0: "nearest", 2: "bilinear", 3: "bicubic"}


def _get(size, key):
    if size is None:
        return None
    if isinstance(size, int):
        return size if key == "shortest_edge" else None
    return size.get(key) if isinstance(size, dict) else getattr(size, key, None)


def _features(out) -> torch.Tensor:
    """transformers 5 returns an output object (projected embeddings in .pooler_output); 4.x a tensor."""
    return out if isinstance(out, torch.Tensor) else out.pooler_output


class ClipMetrics:
    """CLIPModel + tokenizer + image-processor config from a hub id or a local folder."""

    def __init__(
        self,
        pretrained: str = "openai/clip-vit-large-patch14",
        device: str = "auto",
        dtype: str = "float32",
        max_batch_size: int = 16,
        local_files_only: bool = False,
    ) -> None:
        from transformers import AutoConfig, AutoImageProcessor, CLIPModel, CLIPTokenizer

        self.pretrained = pretrained
        self.device = resolve_device(device)
        self.dtype = resolve_dtype(dtype, self.device)
        if max_batch_size < 1:
            raise ValueError(f"max_batch_size must be >= 1, got {max_batch_size}")
        self.max_batch_size = max_batch_size
        p, kw = pretrained, dict(local_files_only=local_files_only)
        check_local_folder(
            p,
            {"": ("config.json",)},
            "ClipMetrics",
        )
        config = load_pretrained("the CLIP config", p, local_files_only, lambda: AutoConfig.from_pretrained(p, **kw))
        if getattr(config, "model_type", None) != "clip":
            raise PretrainedLoadError(
                f"ClipMetrics: '{p}' holds a '{getattr(config, 'model_type', None)}' model, not a CLIP model"
            )
        check_local_folder(p, {"": ("vocab.json", "tokenizer.json")}, "ClipMetrics (tokenizer)")
        check_local_folder(p, {"": ("preprocessor_config.json",)}, "ClipMetrics (image processor)")
        self.model = load_pretrained(
            "the CLIP model", p, local_files_only, lambda: CLIPModel.from_pretrained(p, dtype=self.dtype, **kw)
        )
        self.model.requires_grad_(False).eval().to(self.device)
        self.tokenizer = load_pretrained(
            "the CLIP tokenizer", p, local_files_only, lambda: CLIPTokenizer.from_pretrained(p, **kw)
        )
        proc = load_pretrained(
            "the CLIP image processor", p, local_files_only, lambda: AutoImageProcessor.from_pretrained(p, **kw)
        )
        self.shortest_edge = _get(proc.size, "shortest_edge")
        self.resize_hw = (_get(proc.size, "height"), _get(proc.size, "width"))
        crop = getattr(proc, "crop_size", None)
        self.crop_hw = (_get(crop, "height"), _get(crop, "width")) if getattr(proc, "do_center_crop", True) else None
        if self.crop_hw is not None and None in self.crop_hw:
            self.crop_hw = None
        self.mode = _PIL_RESAMPLE.get(int(getattr(proc, "resample", 3) or 3), "bicubic")
        self.mean = torch.tensor(list(proc.image_mean), dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(list(proc.image_std), dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.max_text_length = min(
            int(self.tokenizer.model_max_length), int(self.model.config.text_config.max_position_embeddings)
        )

    # ------------------------------------------------------------------ embeddings

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """(B, H, W, 3) in [0, 1] -> normalised (B, 3, h, w) pixel values for the vision tower."""
        x = images.permute(0, 3, 1, 2).float().to(self.device)
        h, w = x.shape[-2:]
        if self.shortest_edge:
            s = int(self.shortest_edge)
            size = (s, int(s * w / h)) if h <= w else (int(s * h / w), s)  # as transformers' resize
        elif None not in self.resize_hw:
            size = tuple(int(v) for v in self.resize_hw)
        else:
            size = (h, w)
        x = resize(x, size, self.mode).clamp(0, 1)
        if self.crop_hw is not None:
            ch, cw = (int(v) for v in self.crop_hw)
            if x.shape[-2] < ch or x.shape[-1] < cw:  # too small to crop: scale up first
                x = resize(x, (max(ch, x.shape[-2]), max(cw, x.shape[-1])), self.mode).clamp(0, 1)
            top, left = (x.shape[-2] - ch) // 2, (x.shape[-1] - cw) // 2
            x = x[..., top : top + ch, left : left + cw]
        return (x - self.mean) / self.std

    def image_embeddings(self, images: torch.Tensor) -> torch.Tensor:
        """L2-normalised image embeddings (B, D), float32."""
        images = check_images(images)
        out = []
        with torch.no_grad():
            for s in batches(images.shape[0], self.max_batch_size):
                pix = self.preprocess(images[s]).to(self.dtype)
                out.append(_features(self.model.get_image_features(pixel_values=pix)).float())
        return F.normalize(torch.cat(out), dim=-1)

    def text_embeddings(self, texts: Sequence[str]) -> torch.Tensor:
        """L2-normalised text embeddings (N, D), float32."""
        tok = self.tokenizer(
            list(texts), padding=True, truncation=True, max_length=self.max_text_length, return_tensors="pt"
        )
        with torch.no_grad():
            out = self.model.get_text_features(
                input_ids=tok.input_ids.to(self.device), attention_mask=tok.attention_mask.to(self.device)
            )
        return F.normalize(_features(out).float(), dim=-1)

    # ------------------------------------------------------------------ metrics

    @staticmethod
    def _pair(src: torch.Tensor, edited: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        src, edited = check_images(src, "src_images"), check_images(edited, "edited_images")
        if src.shape[0] != edited.shape[0]:
            raise ValueError(f"src_images ({src.shape[0]}) and edited_images ({edited.shape[0]}) differ in count")
        return src, edited

    @staticmethod
    def _texts(text: Union[str, List[str]], n: int, name: str) -> List[str]:
        if isinstance(text, str):
            return [text] * n
        text = list(text)
        if len(text) != n:
            raise ValueError(f"{name} has {len(text)} entries for {n} images")
        return text

    def direction_similarity(
        self,
        src_images: torch.Tensor,
        edited_images: torch.Tensor,
        src_text: Union[str, List[str]],
        edit_text: Union[str, List[str]],
    ) -> float:
        """Mean over the batch of cos(E_img(edited) − E_img(src), E_txt(edit_text) − E_txt(src_text)),
        in [-1, 1]."""
        src, edited = self._pair(src_images, edited_images)
        n = src.shape[0]
        img = self.image_embeddings(torch.cat([src, edited]))
        txt = self.text_embeddings(self._texts(src_text, n, "src_text") + self._texts(edit_text, n, "edit_text"))
        d_img, d_txt = img[n:] - img[:n], txt[n:] - txt[:n]
        return float(F.cosine_similarity(d_img, d_txt, dim=-1).mean().clamp(-1, 1))

    def image_similarity(self, src_images: torch.Tensor, edited_images: torch.Tensor) -> float:
        """Mean over the batch of the cosine of the two images' CLIP embeddings, in [-1, 1]."""
        src, edited = self._pair(src_images, edited_images)
        img = self.image_embeddings(torch.cat([src, edited]))
        n = src.shape[0]
        return float((img[:n] * img[n:]).sum(-1).mean().clamp(-1, 1))
