"""Loading pretrained models (diffusers / transformers) from a hub id or a local folder, and the
small helpers their wrappers share (instructpix2pix, depth-anything, CLIP metrics)."""
from __future__ import annotations

import os
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Collection, Dict, Iterator, Optional, Sequence, Tuple, TypeVar

import torch

T = TypeVar("T")
M = TypeVar("M", bound=torch.nn.Module)


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


HUB_PROBE_TIMEOUT_S = 10.0  # one request to the hub; no retries


def _hub_offline() -> bool:
    try:
        from huggingface_hub import constants

        return bool(constants.HF_HUB_OFFLINE)
    except Exception:  # noqa: BLE001
        return False


def probe_hub(repo_id: str) -> None:
    """One request to the Hugging Face hub for `repo_id` (raises on any failure, no retries)."""
    from huggingface_hub import HfApi

    HfApi().model_info(repo_id, timeout=HUB_PROBE_TIMEOUT_S)


def locate_hub_model(what: str, pretrained: str, local_files_only: bool, key: str) -> bool:
    """For a hub id (not a local folder): True when the model is in the local Hugging Face cache
    (then load it from there, without asking the network). Otherwise, unless the hub answers one
    request, fail at once with one line that names the model and says how to provide it, instead
    of retrying every file's download for minutes."""
    try:
        from huggingface_hub import snapshot_download

        snapshot_download(pretrained, local_files_only=True)
        return True
    except Exception:  # noqa: BLE001 - not cached (or not a valid id): ask the hub once below
        pass
    how = (f"give a local copy with {key}=/path/to/folder, or download it where the network is reachable "
           f"(huggingface-cli download {pretrained})")
    if local_files_only or _hub_offline():
        raise PretrainedLoadError(
            f"{what}: '{pretrained}' is not a local folder, so it was looked up as a Hugging Face hub id: it is not in "
            f"the local cache and offline mode is on (HF_HUB_OFFLINE or local_files_only); {how}"
        )
    try:
        probe_hub(pretrained)
    except Exception as e:  # noqa: BLE001 - unreachable hub, unknown repo, refused access
        reason = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
        raise PretrainedLoadError(
            f"{what}: '{pretrained}' is not a local folder, so it was looked up as a Hugging Face hub id: it is not in "
            f"the local cache and the hub did not answer ({type(e).__name__}: {reason}); {how}"
        ) from None
    return False


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


def batches(n: int, size: int) -> Iterator[slice]:
    for i in range(0, n, size):
        yield slice(i, min(i + size, n))


class Pretrained:
    """One pretrained model (hub id or local folder) and where it runs.

    The preamble every wrapper needs, in one place: `device` and `dtype` are resolved once
    ("auto" as `resolve_device` / `resolve_dtype` say), `require` checks a local folder before
    loading so that a missing file is named, and `load` runs one from_pretrained call whose
    failure names the model and the part (`load_pretrained`).
    """

    def __init__(
        self,
        what: str,
        pretrained: str,
        device: str = "auto",
        dtype: str = "auto",
        local_files_only: bool = False,
        max_batch_size: Optional[int] = None,
        key: str = "pretrained",
    ) -> None:
        if max_batch_size is not None and max_batch_size < 1:
            raise ValueError(f"max_batch_size must be >= 1, got {max_batch_size}")
        self.what = what
        self.pretrained = pretrained
        self.local_files_only = local_files_only
        self.key = key  # the config key that names the model, for error messages
        self.device = resolve_device(device)
        self.dtype = resolve_dtype(dtype, self.device)
        # A hub id: found in the cache (then loaded from it alone) or the hub answers, else fail now.
        if not check_local_folder(pretrained, {}, what) and locate_hub_model(what, pretrained, local_files_only, key):
            self.local_files_only = True

    def require(self, required: Dict[str, Sequence[str]], part: str = "") -> bool:
        """`check_local_folder` for this model; `part` is named in the error."""
        return check_local_folder(self.pretrained, required, f"{self.what} ({part})" if part else self.what)

    def load(self, part: str, from_pretrained: Callable[..., T], **kwargs) -> T:
        """`from_pretrained(pretrained, local_files_only=..., **kwargs)`; a failure names `part`."""
        p, offline = self.pretrained, self.local_files_only
        return load_pretrained(part, p, offline, lambda: from_pretrained(p, local_files_only=offline, **kwargs))

    def load_frozen(self, part: str, from_pretrained: Callable[..., M], device=None, **kwargs) -> M:
        """A module loaded by `load`, without gradients, in eval mode, on `device` (default: ours)."""
        module = self.load(part, from_pretrained, **kwargs)
        return module.requires_grad_(False).eval().to(self.device if device is None else device)

    def load_config(self, accepted: Collection[str], kind: str):
        """The model's config.json (transformers AutoConfig); its model_type must be in `accepted`."""
        from transformers import AutoConfig

        self.require({"": ("config.json",)})
        config = self.load(f"the {kind} config", AutoConfig.from_pretrained)
        model_type = getattr(config, "model_type", None)
        if model_type not in accepted:
            archs = ", ".join(getattr(config, "architectures", None) or []) or "?"
            msg = f"{self.what}: '{self.pretrained}' holds a '{model_type}' model ({archs}), not a {kind} model"
            if len(accepted) > 1:
                msg += f"; expected one of {', '.join(accepted)}"
            raise PretrainedLoadError(msg)
        return config


# Where PriorLoader builds the priors: "auto" = on a background thread when CUDA is available
# (the weights' file reads and host-to-device copies release the GIL, and the scene's reading and
# source renders go on meanwhile), in the caller's thread on a machine without CUDA: there the
# loads and the source renders compete for the same cores (measured on 2 cores with the real-size
# folders: launch to the end of localization 9.43 s overlapped against 8.47 s one after the other).
# True or False forces it.
BACKGROUND_LOADING: Any = "auto"


def _build_on(device: Optional[int], cls: Callable[..., T], cfg: Any) -> T:
    if device is not None:
        torch.cuda.set_device(device)
    return cls(cfg)


class PriorLoader:
    """Builds priors, in the order they are asked for, on one background thread while the caller
    goes on (reading the scene, rendering the source views), or at once in the caller's thread
    (`BACKGROUND_LOADING`). `start` checks the config in the caller's thread first (the class's
    Config and its `check_source(cfg)` classmethod when it has one: a missing folder or component
    fails there, at once); `get` waits for a prior and re-raises whatever its construction raised,
    in the caller's thread. One thread keeps the construction order (and so the global random
    state the constructors draw from) that building them one after the other would have."""

    def __init__(self, background: Any = None) -> None:
        background = BACKGROUND_LOADING if background is None else background
        self.background = torch.cuda.is_available() if background == "auto" else bool(background)
        self._pool: Optional[ThreadPoolExecutor] = None
        self._items: Dict[str, Any] = {}

    def start(self, name: str, cls: Callable[..., T], cfg: Any = None) -> None:
        from gs_regional.config import parse_structured

        parsed = parse_structured(cls.Config, cfg, label=cls.__name__) if hasattr(cls, "Config") else cfg
        check = getattr(cls, "check_source", None)
        if check is not None:
            check(parsed)
        if not self.background:
            self._items[name] = cls(cfg)
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="prior-loader")
        # The current CUDA device is the thread's own: the caller's (this process's GPU, see
        # systems/parallel.py use_process_gpu) goes with the job.
        device = torch.cuda.current_device() if torch.cuda.is_available() else None
        self._items[name] = self._pool.submit(_build_on, device, cls, cfg)

    def set(self, name: str, value: Any) -> None:
        self._items[name] = value

    def get(self, name: str, default: Any = None) -> Any:
        value = self._items.get(name, default)
        if isinstance(value, Future):
            value = value.result()  # raises the constructor's error here
            self._items[name] = value
        return value

    def wait(self) -> None:
        """Every prior built (or its error raised); the thread goes."""
        for name in list(self._items):
            self.get(name)
        if self._pool is not None:
            self._pool.shutdown(wait=False)
            self._pool = None


# ------------------------------------------------------------------ image-processor settings
# Vision wrappers read a checkpoint's image-processor config and preprocess in torch on the batch.

_PIL_RESAMPLE = {0: "nearest", 2: "bilinear", 3: "bicubic"}  # others (lanczos, box, ...) -> bicubic


def processor_size(size, key: str) -> Optional[int]:
    """A field of a processor size: a transformers SizeDict, a plain dict or a bare int (the
    shortest edge); None when absent."""
    if size is None:
        return None
    if isinstance(size, int):
        return size if key == "shortest_edge" else None
    return size.get(key) if isinstance(size, dict) else getattr(size, key, None)


def processor_resample(proc) -> str:
    """The torch interpolation mode of the processor's PIL resample filter."""
    return _PIL_RESAMPLE.get(int(getattr(proc, "resample", 3) or 3), "bicubic")


def processor_normalization(proc, device: torch.device) -> Tuple[torch.Tensor, torch.Tensor]:
    """The processor's mean and std as (1, 3, 1, 1) float32 tensors on `device`."""
    mean = torch.tensor(list(proc.image_mean), dtype=torch.float32, device=device).view(1, 3, 1, 1)
    std = torch.tensor(list(proc.image_std), dtype=torch.float32, device=device).view(1, 3, 1, 1)
    return mean, std
