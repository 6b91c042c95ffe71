"""CLIP metrics of an edit (DESIGN §3.4): text-image direction similarity and image-image similarity.

Embeddings are L2-normalised before differences are taken, as in the InstructPix2Pix / IN2N
evaluation code. Preprocessing follows the checkpoint's CLIP image-processor config (resize the
shortest edge, center crop, mean/std) but runs in torch on the batch.
"""
from __future__ import annotations

from typing import List, Sequence, Tuple, Union

import torch
import torch.nn.functional as F

from gs_regional.utils.image import check_images, resize, to_nchw
from gs_regional.utils.pretrained import (
    Pretrained,
    batches,
    processor_normalization,
    processor_resample,
    processor_size,
)


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
        from transformers import AutoImageProcessor, CLIPModel, CLIPTokenizer

        self.pretrained = pretrained
        source = Pretrained("ClipMetrics", pretrained, device, dtype, local_files_only, max_batch_size,
                            key="system.eval.clip_model")
        self.device, self.dtype = source.device, source.dtype
        self.max_batch_size = max_batch_size
        source.load_config({"clip"}, "CLIP")
        source.require({"": ("vocab.json", "tokenizer.json")}, "tokenizer")
        source.require({"": ("preprocessor_config.json",)}, "image processor")
        self.model = source.load_frozen("the CLIP model", CLIPModel.from_pretrained, dtype=self.dtype)
        self.tokenizer = source.load("the CLIP tokenizer", CLIPTokenizer.from_pretrained)
        proc = source.load("the CLIP image processor", AutoImageProcessor.from_pretrained)
        self.shortest_edge = processor_size(proc.size, "shortest_edge")
        self.resize_hw = (processor_size(proc.size, "height"), processor_size(proc.size, "width"))
        crop = getattr(proc, "crop_size", None)
        do_crop = getattr(proc, "do_center_crop", True)
        self.crop_hw = (processor_size(crop, "height"), processor_size(crop, "width")) if do_crop else None
        if self.crop_hw is not None and None in self.crop_hw:
            self.crop_hw = None
        self.mode = processor_resample(proc)
        self.mean, self.std = processor_normalization(proc, self.device)
        self.max_text_length = min(
            int(self.tokenizer.model_max_length), int(self.model.config.text_config.max_position_embeddings)
        )

    # ------------------------------------------------------------------ embeddings

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """(B, H, W, 3) in [0, 1] -> normalised (B, 3, h, w) pixel values for the vision tower."""
        x = to_nchw(images).to(self.device)
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
