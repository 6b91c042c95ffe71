"""The guidance interface shared by `instructpix2pix`, `simulated-editor` and user plugins.

Template method (as threestudio's base modules): the public `relevance`, `mask` and `edit`
validate and convert their arguments once (images, cameras, prompt, timesteps, seeds), split the
views into batches of `batch_size`, call the plugin's `_relevance` / `_edit` once per batch, and
check the shape of what it returns. A plugin implements only `_relevance` and `_edit` and receives
checked inputs, at most `batch_size` views at a time, with one seed per view.

Seeds are per view (`seed=` an int for every view, or a list of one per view) and a plugin draws
each view's randomness from a generator of that view's own seed: a view's result depends on its
image, seed and camera only, never on which views share the call or how the call is batched.
"""
from __future__ import annotations

import contextlib
import logging
import numbers
import time
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple, Union

import torch

from gs_regional.config import ConfigError
from gs_regional.data.cameras import Camera
from gs_regional.utils.base import Configurable, component_name
from gs_regional.utils.image import check_cameras, check_images, check_output_shape, components, gaussian_blur
from gs_regional.utils.pretrained import batches

Seeds = Union[int, Sequence[int]]
AUTO = "auto"
AUTO_MEMORY_SHARE = 0.85  # of the free memory "auto" may fill: room for the renders and allocator slack
AUTO_MAX_BATCH = 16  # beyond this a UNet call is no faster per view on any GPU measured
log = logging.getLogger(__name__)


def fitting_batch(free: int, peak_one: int, peak_two: int, share: float = AUTO_MEMORY_SHARE,
                  most: int = AUTO_MAX_BATCH) -> int:
    """The most views per call whose memory fits `share` of `free` bytes, from the measured peaks
    of one view and of two (each view adds peak_two - peak_one, the first one peak_one)."""
    per_view = max(peak_two - peak_one, 1)
    return int(min(max(1 + (share * free - peak_one) // per_view, 1), most))


def keep_peak_blob(filtered: torch.Tensor, binary: torch.Tensor, relevance: torch.Tensor) -> torch.Tensor:
    """(B, H, W) bool: `filtered` plus, in each view where the speck filter erased the pixel of
    the strongest `relevance`, that pixel's 8-connected blob of `binary`."""
    out = filtered.clone()
    for b in range(relevance.shape[0]):
        peak = int(relevance[b].argmax())
        if binary[b].reshape(-1)[peak] and not filtered[b].reshape(-1)[peak]:
            labels = components(binary[b])
            out[b] |= labels == labels.reshape(-1)[peak]
    return out


class Guidance(Configurable):
    """A 2D editor. Images are (B, H, W, 3) float tensors in [0, 1].

    Counters (reported by systems): `unet_evals` (one guided step on B images = 3*B),
    `vae_encodes`, `vae_decodes` (per image); a plugin updates those it spends. `unet_seconds`:
    the wall seconds of the model calls a plugin wraps in `unet_timer()`.
    """

    @dataclass
    class Config:
        # Views per model call (a UNet call spends 2x these images for relevance, 3x for edit).
        # Larger batches are faster on a GPU and need more memory; results do not depend on it.
        # "auto": on CUDA the most views whose measured memory fits the free memory at the run's
        # resolution (`auto_batch_size`), 1 on a CPU.
        batch_size: Union[int, str] = 1

    # Timesteps (`timestep` of relevance, `t_start` of edit) are integers in
    # [0, num_train_timesteps): Stable Diffusion's training schedule unless a plugin says otherwise.
    num_train_timesteps: int = 1000
    # True for editors that cannot work without one camera per image (simulators rendering a
    # known scene): calls without cameras are then rejected.
    requires_cameras: bool = False

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where)
        if not hasattr(self.cfg, "batch_size"):
            raise TypeError(
                f"{type(self).__name__}.Config must derive from Guidance.Config (it holds batch_size, the views "
                "per model call): write `class Config(Guidance.Config):`"
            )
        Guidance.check_source(self.cfg, component_name(self))
        self._auto_batches: Dict[Tuple[int, int], int] = {}  # (H, W) -> the batch "auto" chose there
        self._batches: Dict[Tuple[int, int], int] = {}  # (H, W) -> the batch used there
        self.reset_counters()

    @classmethod
    def check_source(cls, cfg, name: str = "") -> None:
        """The checks of a parsed config that need no model (a system runs them before it starts
        loading its priors on another thread; a plugin that loads weights extends them)."""
        b = cfg.batch_size
        if not (b == AUTO or (isinstance(b, int) and not isinstance(b, bool) and b >= 1)):
            raise ConfigError(f"{name or cls.__dict__.get('registered_name', cls.__name__)}: batch_size (views per "
                              f"model call) must be >= 1 or '{AUTO}', got {b!r}")

    def batch_size_for(self, images: torch.Tensor) -> int:
        """Views per model call for (B, H, W, 3) `images`: the configured number, or for "auto" the
        one measured once per resolution (`auto_batch_size`)."""
        hw = (int(images.shape[1]), int(images.shape[2]))
        if self.cfg.batch_size != AUTO:
            self._batches[hw] = int(self.cfg.batch_size)
            return int(self.cfg.batch_size)
        if hw not in self._auto_batches:
            self._auto_batches[hw] = self.auto_batch_size(images[:1])
            log.info("%s: batch_size auto -> %d views per model call at %dx%d", component_name(self),
                     self._auto_batches[hw], hw[1], hw[0])
        self._batches[hw] = self._auto_batches[hw]
        return self._auto_batches[hw]

    def batches_chosen(self) -> Dict[str, int]:
        """{"WxH": views per model call} at every resolution called so far (the configured
        batch_size, or what "auto" chose there)."""
        return {f"{w}x{h}": b for (h, w), b in sorted(self._batches.items())}

    def auto_batch_size(self, image: torch.Tensor) -> int:
        """The batch "auto" chooses: 1 off CUDA (a CPU gains nothing from larger batches) or for a
        plugin that cannot measure its memory; on CUDA, `fitting_batch` of the free memory and the
        memory one edit of one and of two copies of `image` (1, H, W, 3) takes (`_probe_peaks`)."""
        device = torch.device(getattr(self, "device", "cpu"))
        if device.type != "cuda":
            return 1
        counters, unet_seconds = self.counters(), self.unet_seconds
        torch.cuda.synchronize(device)
        free = torch.cuda.mem_get_info(device)[0]
        peaks = self._probe_peaks(image)
        self.unet_evals, self.vae_encodes, self.vae_decodes = counters.values()  # the probe is not the edit's
        self.unet_seconds = unet_seconds
        if peaks is None:
            return 1
        return fitting_batch(free, *peaks)

    def _probe_peaks(self, image: torch.Tensor) -> Optional[Tuple[int, int]]:
        """Override to measure: the peak memory (bytes, above what is held before) of `_edit` on one
        and on two copies of `image`. None: not measured, "auto" uses 1."""
        return None

    def reset_counters(self) -> None:
        self.unet_evals = 0
        self.vae_encodes = 0
        self.vae_decodes = 0
        self.unet_seconds = 0.0

    @contextlib.contextmanager
    def unet_timer(self):
        """Adds the block's wall seconds to `unet_seconds`; on CUDA it synchronizes before and
        after, so that the seconds are the model's and not the queue's."""
        device = torch.device(getattr(self, "device", "cpu"))
        cuda = device.type == "cuda"
        if cuda:
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if cuda:
                torch.cuda.synchronize(device)
            self.unet_seconds += time.perf_counter() - t0

    def counters(self) -> Dict[str, int]:
        return {"unet_evals": self.unet_evals, "vae_encodes": self.vae_encodes, "vae_decodes": self.vae_decodes}

    # ------------------------------------------------------------------ the interface

    def relevance(
        self,
        images: torch.Tensor,
        prompt: str,
        timestep: int = 600,
        samples: int = 1,
        seed: Seeds = 0,
        cameras: Optional[Sequence[Camera]] = None,
    ) -> torch.Tensor:
        """Per-view relevance maps (B, H, W) in [0, 1], each normalised to its own max: where the
        instruction `prompt` would change each image, judged at noise level `timestep` and averaged
        over `samples` noise draws (seeded per view by `seed`: an int for every view or a list)."""
        where = f"{component_name(self)}.relevance"
        images = check_images(images, f"{where}: images")
        cameras = check_cameras(cameras, images.shape[0], where, self.requires_cameras)
        self._check_prompt(prompt, where)
        self._check_timestep(timestep, "timestep", where)
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
            raise ValueError(f"{where}: samples must be an integer >= 1, got {samples!r}")
        seeds = self._check_seeds(seed, images.shape[0], where)
        maps = []
        for s in batches(images.shape[0], self.batch_size_for(images)):
            out = self._relevance(images[s], prompt, timestep, samples, seeds[s], _part(cameras, s))
            maps.append(check_output_shape(out, images[s].shape[:3], where))
        return torch.cat(maps)

    def mask(
        self,
        images: torch.Tensor,
        prompt: str,
        threshold: float = 0.6,
        blur_sigma: float = 2.0,
        timestep: int = 600,
        samples: int = 1,
        seed: Seeds = 0,
        cameras: Optional[Sequence[Camera]] = None,
    ) -> torch.Tensor:
        """Binary 2D masks (B, H, W) float: threshold at γ, Gaussian-filter specks away, re-binarise.

        The filter erases any blob under about 2.35 σ in radius (17 px at σ = 2); the blob holding
        the view's strongest response is kept whole even then (`keep_peak_blob`): a part only a few
        pixels across in this view is the region, not a speck.
        γ = 0 means "everything" (a global edit) and returns all ones without running the model.
        """
        if threshold <= 0:
            b, h, w = check_images(images, f"{component_name(self)}.mask: images").shape[:3]
            return torch.ones(b, h, w, device=images.device)
        rel = self.relevance(images, prompt, timestep=timestep, samples=samples, seed=seed, cameras=cameras)
        binary = rel >= threshold
        filtered = gaussian_blur(binary.float(), blur_sigma) > 0.5
        return keep_peak_blob(filtered, binary, rel).float()

    def edit(
        self,
        images: torch.Tensor,
        cond_images: torch.Tensor,
        prompt: str,
        t_start: Optional[int] = None,
        seed: Seeds = 0,
        cameras: Optional[Sequence[Camera]] = None,
    ) -> torch.Tensor:
        """Edited images (B, H, W, 3): noise `images` to `t_start` (None: pure noise, a full edit) and
        denoise conditioned on `cond_images` (the unedited views, same shape) and `prompt`. `seed`:
        an int for every view or a list of one per view; each view is edited as it would be alone."""
        where = f"{component_name(self)}.edit"
        images = check_images(images, f"{where}: images")
        cond_images = check_images(cond_images, f"{where}: cond_images")
        if images.shape != cond_images.shape:
            raise ValueError(
                f"{where}: images {tuple(images.shape)} and cond_images {tuple(cond_images.shape)} must have the same shape"
            )
        cameras = check_cameras(cameras, images.shape[0], where, self.requires_cameras)
        self._check_prompt(prompt, where)
        if t_start is not None:
            self._check_timestep(t_start, "t_start", where)
        seeds = self._check_seeds(seed, images.shape[0], where)
        edited = []
        for s in batches(images.shape[0], self.batch_size_for(images)):
            out = self._edit(images[s], cond_images[s], prompt, t_start, seeds[s], _part(cameras, s))
            edited.append(check_output_shape(out, images[s].shape, where))
        return torch.cat(edited)

    # ------------------------------------------------------------------ what a plugin implements

    def _relevance(
        self, images: torch.Tensor, prompt: str, timestep: int, samples: int, seeds: List[int], cameras: Optional[List[Camera]]
    ) -> torch.Tensor:
        """Implement this: maps (B, H, W) in [0, 1] for a checked (B, H, W, 3) batch `images` of at
        most `batch_size` views, a non-empty `prompt`, an integer `timestep` in [0,
        num_train_timesteps), `samples` >= 1, `seeds` one int per image (draw each view's noise
        from a generator of its own seed) and `cameras` None or a list of one camera per image."""
        raise NotImplementedError(f"{type(self).__name__} must implement _relevance(...)")

    def _edit(
        self,
        images: torch.Tensor,
        cond_images: torch.Tensor,
        prompt: str,
        t_start: Optional[int],
        seeds: List[int],
        cameras: Optional[List[Camera]],
    ) -> torch.Tensor:
        """Implement this: edited (B, H, W, 3) images in [0, 1] for checked batches `images` and
        `cond_images` of the same shape (at most `batch_size` views), a non-empty `prompt`,
        `t_start` None or an integer in [0, num_train_timesteps), `seeds` one int per image (draw
        each view's noise from a generator of its own seed) and `cameras` None or a list of one
        camera per image."""
        raise NotImplementedError(f"{type(self).__name__} must implement _edit(...)")

    # ------------------------------------------------------------------ checks

    @staticmethod
    def _check_seeds(seed: Seeds, n_images: int, where: str) -> List[int]:
        """One int seed per image: an int applies to every image, a sequence gives one each."""
        def is_int(x) -> bool:
            return isinstance(x, numbers.Integral) and not isinstance(x, bool)

        if is_int(seed):
            return [int(seed)] * n_images
        if isinstance(seed, (str, bytes)) or not isinstance(seed, Sequence) or not all(is_int(s) for s in seed):
            raise TypeError(f"{where}: seed must be an int or a list of one int per image, got {seed!r}")
        if len(seed) != n_images:
            raise ValueError(f"{where}: {n_images} images but {len(seed)} seeds")
        return [int(s) for s in seed]

    @staticmethod
    def _check_prompt(prompt: str, where: str) -> None:
        if not isinstance(prompt, str) or not prompt.strip():
            raise ValueError(f"{where}: prompt must be a non-empty instruction string, got {prompt!r}")

    def _check_timestep(self, t: int, name: str, where: str) -> None:
        n = self.num_train_timesteps
        if isinstance(t, bool) or not isinstance(t, int) or not 0 <= t < n:
            raise ValueError(f"{where}: {name} must be an integer timestep in [0, {n - 1}], got {t!r}")


def _part(cameras: Optional[List[Camera]], views: slice) -> Optional[List[Camera]]:
    return None if cameras is None else cameras[views]
