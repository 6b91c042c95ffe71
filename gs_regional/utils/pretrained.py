"""Loading pretrained models (diffusers / transformers) from a hub id or a local folder, and the
small tensor helpers their wrappers share (instructpix2pix, depth-anything, CLIP metrics)."""
from __future__ import annotations

import os
from typing import Callable, Dict, Iterator, Sequence, Tuple, TypeVar

import torch
import torch.nn.functional as F

T = TypeVar("T")



class PretrainedLoadError(OSError):
    """A pretrained model (hub id or local folder) could not be loaded; the message says which part."""


_DTYPES = {
    "float32": torch.float32,
    "fp32": torch.float32,
    "float16": torch.float16,
    "fp16": torch.float16,
    "half": torch.float16,
    "bfloat16": torch.bfloat16,
    "bf16": torch.bfloat16,
}


def resolve_device(name: str) -> torch.device:
    """"auto" = CUDA when available, else CPU; anything else must be a usable torch device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"unknown device '{name}'; use 'auto', 'cpu', 'cuda' or 'cuda:N'") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device '{name}' was requested but CUDA is not available; use device=auto or cpu")
    return device


def resolve_dtype(name: str, device: torch.device) -> torch.dtype:
    """"auto" = float16 on CUDA (what the models were released for), float32 on CPU."""
    if name == "auto":
        return torch.float16 if device.type == "cuda" else torch.float32
    if name not in _DTYPES:
        raise ValueError(f"unknown dtype '{name}'; use auto, float32, float16 or bfloat16")
    return _DTYPES[name]


def check_local_folder(pretrained: str, required: Dict[str, Sequence[str]], what: str) -> bool:
    """True when `pretrained` is a local folder. There, each `required` sub-path ("" = the folder
    itself) must hold at least one of its files, checked before loading so that the error names the
    missing component rather than surfacing from deep inside from_pretrained."""
    path = os.path.expanduser(pretrained)
    if not os.path.isdir(path):
        if os.path.exists(path):
            raise PretrainedLoadError(f"{what}: '{pretrained}' is a file; expected a model folder or a hub id")
        if pretrained.startswith(("/", "./", "../", "~", ".\\")):
            raise PretrainedLoadError(f"{what}: model folder '{pretrained}' does not exist")
        return False
    for sub, files in required.items():
        folder = os.path.join(path, sub) if sub else path
        label = f"component '{sub}' (subfolder {folder})" if sub else f"folder {folder}"
        if not os.path.isdir(folder):
            raise PretrainedLoadError(f"{what}: '{pretrained}' lacks the {label}")
        if not any(os.path.isfile(os.path.join(folder, f)) for f in files):
            raise PretrainedLoadError(f"{what}: {label} of '{pretrained}' has none of {', '.join(files)}")
    return True


def load_pretrained(what: str, pretrained: str, local_files_only: bool, fn: Callable[[], T]) -> T:
    """Run one from_pretrained call and turn any failure into an error that names the model and the
    part, with a hint when a hub id could not be found offline."""
    try:
        return fn()
    except Exception as e:  # noqa: BLE001 - re-raised with context
        hint = ""
        if not os.path.isdir(os.path.expanduser(pretrained)):
            try:
                from huggingface_hub import constants

                offline = bool(constants.HF_HUB_OFFLINE)
            except Exception:  # noqa: BLE001
                offline = False
            hint = f" ('{pretrained}' is not a local folder, so it was looked up as a Hugging Face hub id"
            if offline or local_files_only:
                hint += "; offline mode is on (HF_HUB_OFFLINE or local_files_only) and it is not in the local cache"
            hint += "; download it first or point `pretrained` at a local folder)"
        raise PretrainedLoadError(f"cannot load {what} from '{pretrained}': {e}{hint}") from e


def to_nchw(images: torch.Tensor, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    return images.permute(0, 3, 1, 2).to(device=device, dtype=torch.float32).contiguous().to(dtype)


def resize(x: torch.Tensor, size: Tuple[int, int], mode: str = "bilinear") -> torch.Tensor:
    """Resize (B, C, H, W); antialiased when shrinking (as PIL does), a no-op at the same size."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    shrink = size[0] < x.shape[-2] or size[1] < x.shape[-1]
    if mode in ("bilinear", "bicubic"):
        return F.interpolate(x, size=size, mode=mode, align_corners=False, antialias=shrink)
    return F.interpolate(x, size=size, mode=mode)


def batches(n: int, size: int) -> Iterator[slice]:
    for i in range(0, n, size):
        yield slice(i, min(i + size, n))
