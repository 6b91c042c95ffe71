"""InstructPix2Pix guidance (diffusers UNet + VAE + CLIP text encoder + DDIM scheduler).

Two operations (DESIGN §3.1, §3.3):
  * `_relevance(images, prompt)`: noise the image latents to τ and take the per-pixel difference of
    the text-conditioned and the empty-prompt noise predictions (both conditioned on the image);
  * `_edit(images, cond_images, prompt, t_start)`: partial (or full) DDIM denoising with IP2P's
    3-branch classifier-free guidance, as diffusers' StableDiffusionInstructPix2PixPipeline.
The public `relevance` / `mask` / `edit` of `Guidance` check the arguments before calling them.

The weights live in this plain `Configurable`, not in any nn.Module of a system, so they never end
up in a Lightning checkpoint. diffusers/transformers are imported lazily (importing the package
stays light). The loading helpers live in gs_regional/utils/pretrained.py.
"""
from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple, Union

import torch
import torch.nn.functional as F

from gs_regional.data.cameras import Camera
from gs_regional.guidance.base import Guidance
from gs_regional.registry import register
from gs_regional.utils.image import resize, to_nchw
from gs_regional.utils.pretrained import Pretrained, PretrainedLoadError

# -------------------------------------------------------------------------------- the guidance

_IP2P_COMPONENTS = {
    "unet": ("config.json",),
    "vae": ("config.json",),
    "text_encoder": ("config.json",),
    "tokenizer": ("vocab.json", "tokenizer.json", "tokenizer_config.json"),
    "scheduler": ("scheduler_config.json",),
}


@register("instructpix2pix")
class InstructPix2Pix(Guidance):
    @dataclass
    class Config(Guidance.Config):
        # batch_size (Guidance.Config): views per UNet call; the UNet batch is 2x this in
        # relevance and 3x in edit. "auto" measures the memory of one and two views once per
        # resolution and takes the most that fit (`_probe_peaks`; 1 on a CPU).
        batch_size: Union[int, str] = "auto"
        pretrained: str = "timbrooks/instruct-pix2pix"  # hub id or local folder (diffusers layout)
        dtype: str = "auto"  # auto = float16 on CUDA, float32 on CPU; float32 | float16 | bfloat16
        device: str = "auto"
        guidance_scale: float = 7.5  # text guidance s_t
        image_guidance_scale: float = 1.5  # image guidance s_i
        num_inference_steps: int = 20  # DDIM steps of a full edit
        channels_last: bool = False
        sdpa: bool = True  # torch scaled-dot-product attention (AttnProcessor2_0) when available
        cpu_offload: bool = False  # keep modules on the CPU and move each to the device only while used
        local_files_only: bool = False

    def __init__(self, cfg=None, where: str = "") -> None:
        super().__init__(cfg, where)
        c = self.cfg
        source = self.check_source(c)
        self.device, self.dtype = source.device, source.dtype
        self._load(source)
        self._emb_cache: Dict[str, torch.Tensor] = {}

    # ------------------------------------------------------------------ loading

    @classmethod
    def check_source(cls, c: "InstructPix2Pix.Config") -> Pretrained:
        """The checks that need no weights (a parsed config): the settings, the device, and the
        folder with its five components (or the hub id in the cache or on the hub)."""
        super().check_source(c)
        if c.num_inference_steps < 1:
            raise ValueError(f"num_inference_steps must be >= 1, got {c.num_inference_steps}")
        source = Pretrained("InstructPix2Pix", c.pretrained, c.device, c.dtype, c.local_files_only,
                            key="system.guidance.pretrained")
        source.require(_IP2P_COMPONENTS)
        return source

    def _load(self, source: Pretrained) -> None:
        from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
        from transformers import CLIPTextModel, CLIPTokenizer

        c = self.cfg
        p = c.pretrained
        source.require(_IP2P_COMPONENTS)
        # With cpu_offload the modules live on the CPU and visit the device only while used.
        home = torch.device("cpu") if c.cpu_offload else self.device

        def load(sub: str, from_pretrained, **kw):
            return source.load(f"InstructPix2Pix component '{sub}'", from_pretrained, subfolder=sub, **kw)

        def load_frozen(sub: str, from_pretrained, **kw):
            return source.load_frozen(f"InstructPix2Pix component '{sub}'", from_pretrained, home, subfolder=sub, **kw)

        self.tokenizer = load("tokenizer", CLIPTokenizer.from_pretrained)
        self.text_encoder = load_frozen("text_encoder", CLIPTextModel.from_pretrained, dtype=self.dtype)
        self.vae = load_frozen("vae", AutoencoderKL.from_pretrained, torch_dtype=self.dtype)
        self.unet = load_frozen("unet", UNet2DConditionModel.from_pretrained, torch_dtype=self.dtype)
        sched_cfg = load("scheduler", DDIMScheduler.load_config)
        overrides = {}
        if sched_cfg.get("_class_name") != "DDIMScheduler":
            # The hub IP2P ships an Euler scheduler config; DDIM's own defaults (clip_sample=True,
            # set_alpha_to_one=True) are wrong for Stable Diffusion latents, so use SD's DDIM settings.
            overrides = dict(clip_sample=False, set_alpha_to_one=False)
        self.scheduler = DDIMScheduler.from_config(sched_cfg, **overrides)
        self.num_train_timesteps = int(self.scheduler.config.num_train_timesteps)  # the range Guidance checks

        if self.unet.config.in_channels != 2 * self.vae.config.latent_channels:
            raise PretrainedLoadError(
                f"InstructPix2Pix: the unet of '{p}' has in_channels={self.unet.config.in_channels}; IP2P needs "
                f"{2 * self.vae.config.latent_channels} (noisy latents + image latents). Is it an InstructPix2Pix model?"
            )
        self.vae_scale_factor = 2 ** (len(self.vae.config.block_out_channels) - 1)
        self.scaling_factor = float(self.vae.config.scaling_factor)
        self.max_text_length = min(
            int(self.tokenizer.model_max_length), int(self.text_encoder.config.max_position_embeddings)
        )

        if c.sdpa and hasattr(F, "scaled_dot_product_attention"):
            from diffusers.models.attention_processor import AttnProcessor2_0 as Processor
        else:
            from diffusers.models.attention_processor import AttnProcessor as Processor
        self.unet.set_attn_processor(Processor())
        self.vae.set_attn_processor(Processor())
        if c.channels_last:
            self.unet.to(memory_format=torch.channels_last)

    @contextlib.contextmanager
    def _using(self, module: torch.nn.Module):
        """With cpu_offload, hold `module` on the device only for the duration of the block."""
        if not self.cfg.cpu_offload or self.device.type == "cpu":
            yield module
            return
        module.to(self.device)
        try:
            yield module
        finally:
            module.to("cpu")

    # ------------------------------------------------------------------ text

    def _embed(self, prompt: str) -> torch.Tensor:
        """(1, L, D) text-encoder hidden states, cached per prompt ("" is the unconditional one)."""
        if prompt in self._emb_cache:
            return self._emb_cache[prompt]
        n = len(self.tokenizer(prompt, truncation=False).input_ids)
        if n > self.max_text_length:
            warnings.warn(
                f"prompt is {n} tokens long; the text encoder takes {self.max_text_length}, so it is truncated: "
                f"{prompt[:60]!r}...",
                stacklevel=3,
            )
        ids = self.tokenizer(
            prompt, padding="max_length", max_length=self.max_text_length, truncation=True, return_tensors="pt"
        ).input_ids
        with torch.no_grad(), self._using(self.text_encoder) as te:
            emb = te(ids.to(self.device)).last_hidden_state.to(self.device, self.dtype)
        self._emb_cache[prompt] = emb
        return emb

    # ------------------------------------------------------------------ images <-> latents

    def _prepare(self, images: torch.Tensor) -> torch.Tensor:
        """(B, H, W, 3) in [0, 1] -> (B, 3, H8, W8) on the device, H8/W8 the nearest multiples of 8."""
        f = self.vae_scale_factor
        h, w = images.shape[1:3]
        size = (max(f, round(h / f) * f), max(f, round(w / f) * f))
        x = resize(to_nchw(images), size)
        return x.clamp(0, 1).to(self.device)

    def _encode(self, x: torch.Tensor) -> torch.Tensor:
        """Mode of the VAE posterior (unscaled), float32 (B, 4, H/8, W/8)."""
        with torch.no_grad(), self._using(self.vae) as vae:
            z = vae.encode((x * 2 - 1).to(self.dtype)).latent_dist.mode().float()
        self.vae_encodes += x.shape[0]
        return z

    def _decode(self, z: torch.Tensor) -> torch.Tensor:
        """Scaled latents -> (B, 3, H, W) images in [0, 1], float32."""
        with torch.no_grad(), self._using(self.vae) as vae:
            x = vae.decode((z / self.scaling_factor).to(self.dtype)).sample.float()
        self.vae_decodes += z.shape[0]
        return ((x + 1) / 2).clamp(0, 1)

    def _unet(self, unet, latents: torch.Tensor, t: torch.Tensor, image_latents: torch.Tensor, emb: torch.Tensor):
        inp = torch.cat([latents, image_latents], dim=1).to(self.dtype)
        if self.cfg.channels_last:
            inp = inp.contiguous(memory_format=torch.channels_last)
        with self.unet_timer():
            return unet(inp, t.to(self.device), encoder_hidden_states=emb).sample.float()

    def _noise(self, shape, generators: List[torch.Generator]) -> torch.Tensor:
        """(B, *shape) noise, view b drawn from generators[b]: on the CPU, so that a view's noise
        depends neither on the device nor on the other views of the call."""
        return torch.stack([torch.randn(shape, generator=g, dtype=torch.float32) for g in generators]).to(self.device)

    @staticmethod
    def _generators(seeds: List[int]) -> List[torch.Generator]:
        return [torch.Generator("cpu").manual_seed(int(s)) for s in seeds]

    # ------------------------------------------------------------------ the interface

    def _relevance(
        self, images: torch.Tensor, prompt: str, timestep: int, samples: int, seeds: List[int], cameras: Optional[List[Camera]]
    ) -> torch.Tensor:
        """Per-view maps (B, H, W) in [0, 1]: D = mean over latent channels of
        |ε(z_τ, x, c) − ε(z_τ, x, ∅)|, averaged over `samples` noise draws, bilinearly upsampled from
        latent to image size, then divided by its per-view max (each view's strongest response is 1;
        an all-zero map stays 0). z0 is the mode of the VAE posterior (deterministic). View b's
        noise draws come from a generator of seeds[b]."""
        b, h, w = images.shape[:3]
        mode = self._encode(self._prepare(images))  # one encode serves as z0 and as the image condition
        z0 = mode * self.scaling_factor
        cond, null = self._embed(prompt), self._embed("")
        emb = torch.cat([cond.expand(b, -1, -1), null.expand(b, -1, -1)])
        t = torch.tensor(timestep, dtype=torch.long)
        generators = self._generators(seeds)
        diff = torch.zeros(b, *mode.shape[2:], device=self.device)
        with torch.no_grad(), self._using(self.unet) as unet:
            for _ in range(samples):
                z_t = self.scheduler.add_noise(z0, self._noise(z0.shape[1:], generators), t.expand(b))
                eps_c, eps_u = self._unet(unet, z_t.repeat(2, 1, 1, 1), t, mode.repeat(2, 1, 1, 1), emb).chunk(2)
                diff += (eps_c - eps_u).abs().mean(dim=1)
                self.unet_evals += 2 * b
        diff = F.interpolate((diff / samples)[:, None], size=(h, w), mode="bilinear", align_corners=False)[:, 0]
        diff = diff / diff.flatten(1).amax(dim=1).clamp_min(1e-12)[:, None, None]
        return diff.clamp(0, 1).to(images.device)

    def _probe_peaks(self, image: torch.Tensor) -> Optional[Tuple[int, int]]:
        """Peak CUDA memory (bytes above what is held before) of one guided step of `_edit` on one
        and on two copies of `image`: what `batch_size: auto` sizes its batch from. The VAE and
        the UNet run at the call's resolution, so one denoising step shows the whole peak."""
        if self.device.type != "cuda":
            return None
        self.scheduler.set_timesteps(self.cfg.num_inference_steps)
        t_last = int(self.scheduler.timesteps[-1])  # one denoising step
        peaks = []
        for n in (1, 2):
            views = image.expand(n, -1, -1, -1).contiguous()
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            held = torch.cuda.memory_allocated(self.device)
            self._edit(views, views, "", t_last, [0] * n, None)
            torch.cuda.synchronize(self.device)
            peaks.append(torch.cuda.max_memory_allocated(self.device) - held)
        return peaks[0], peaks[1]

    def _edit(
        self, images: torch.Tensor, cond_images: torch.Tensor, prompt: str, t_start: Optional[int], seeds: List[int], cameras
    ) -> torch.Tensor:
        """Edited images (B, H, W, 3) in [0, 1] at the input size.

        t_start=None: start from pure noise and run all `num_inference_steps` DDIM steps (a full
        edit). Otherwise noise the (mode) latents of `images` to the largest scheduled timestep
        <= t_start and run only the scheduled steps from there. Guidance as diffusers' IP2P
        pipeline: ε = ε_u + s_t(ε_txt − ε_img) + s_i(ε_img − ε_u), branches (text + image),
        (empty text + image), (empty text + zero image latents). View b's noise comes from a
        generator of seeds[b], so it is edited exactly as it would be alone (up to float rounding).
        """
        sched = self.scheduler
        sched.set_timesteps(self.cfg.num_inference_steps)
        steps = sched.timesteps
        if t_start is not None:
            steps = steps[steps <= t_start]
            if len(steps) == 0:
                raise ValueError(
                    f"t_start={t_start} is below the last DDIM timestep {int(sched.timesteps[-1])} for "
                    f"num_inference_steps={self.cfg.num_inference_steps}: nothing to denoise"
                )
        b, h, w = images.shape[:3]
        image_lat = self._encode(self._prepare(cond_images))
        noise = self._noise(image_lat.shape[1:], self._generators(seeds))
        if t_start is None:
            lat = noise * sched.init_noise_sigma
        else:
            z0 = self._encode(self._prepare(images)) * self.scaling_factor
            lat = sched.add_noise(z0, noise, steps[:1].expand(b))
        text, null = self._embed(prompt), self._embed("")
        s_t, s_i = self.cfg.guidance_scale, self.cfg.image_guidance_scale
        cond_lat = torch.cat([image_lat, image_lat, torch.zeros_like(image_lat)])
        emb = torch.cat([text.expand(b, -1, -1), null.expand(b, -1, -1), null.expand(b, -1, -1)])
        with torch.no_grad(), self._using(self.unet) as unet:
            for t in steps:
                inp = sched.scale_model_input(lat.repeat(3, 1, 1, 1), t)
                eps_txt, eps_img, eps_unc = self._unet(unet, inp, t, cond_lat, emb).chunk(3)
                eps = eps_unc + s_t * (eps_txt - eps_img) + s_i * (eps_img - eps_unc)
                lat = sched.step(eps, t, lat).prev_sample
                self.unet_evals += 3 * b
        edited = self._decode(lat)
        edited = resize(edited, (h, w)).clamp(0, 1)
        return edited.permute(0, 2, 3, 1).contiguous().to(images.device)
