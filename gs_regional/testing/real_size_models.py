"""Random-weight priors with the PUBLISHED shapes, saved in the hub layouts, for timing the real
code path where the weights cannot be downloaded (the images they make are meaningless; the
compute and memory are those of the released models).

    build_real_size_ip2p(folder)            # timbrooks/instruct-pix2pix: SD 1.5 UNet with 8 input
                                            # channels, the SD VAE, CLIP ViT-L/14 text encoder
    build_real_size_depth_anything(folder)  # depth-anything/Depth-Anything-V2-Small-hf
    cached_priors("tiny" | "real-size")     # {"ip2p", "depth_anything"} -> folder, built once

The tokenizer is built offline as the tiny one is (gs_regional.testing.tiny_models), padded to
CLIP's 49408 entries so that the ids (bos 49406, eos 49407) and the embedding table match.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from typing import Dict, Optional

import torch

from gs_regional.testing.tiny_models import (
    MAX_TEXT_LENGTH,
    build_tiny_depth_anything,
    build_tiny_ip2p,
    save_depth_anything_folder,
    save_ip2p_folder,
    save_tokenizer,
)

CLIP_VOCAB_SIZE = 49408
# Bump when what a builder writes changes, so that cached folders are rebuilt.
BUILD_VERSION = 2


def real_size_ip2p_modules(vocab_size: int, bos_token_id: int, eos_token_id: int):
    """(unet, vae, text_encoder) of InstructPix2Pix at the published sizes, randomly initialised
    on the current default device (build them under `torch.device("meta")` to inspect the shapes
    without allocating)."""
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    unet = UNet2DConditionModel(  # Stable Diffusion 1.5's UNet; IP2P widens the first conv to 8 channels
        sample_size=64,
        in_channels=8,
        out_channels=4,
        layers_per_block=2,
        block_out_channels=(320, 640, 1280, 1280),
        down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=768,
        attention_head_dim=8,
        norm_num_groups=32,
        act_fn="silu",
        downsample_padding=1,
        flip_sin_to_cos=True,
        freq_shift=0,
    )
    vae = AutoencoderKL(  # the Stable Diffusion VAE (scale factor 8)
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * 4,
        up_block_types=("UpDecoderBlock2D",) * 4,
        block_out_channels=(128, 256, 512, 512),
        layers_per_block=2,
        latent_channels=4,
        norm_num_groups=32,
        sample_size=256,
        scaling_factor=0.18215,
    )
    text_encoder = CLIPTextModel(
        CLIPTextConfig(  # openai/clip-vit-large-patch14's text tower
            vocab_size=vocab_size,
            hidden_size=768,
            intermediate_size=3072,
            num_hidden_layers=12,
            num_attention_heads=12,
            max_position_embeddings=MAX_TEXT_LENGTH,
            hidden_act="quick_gelu",
            projection_dim=768,
            bos_token_id=bos_token_id,
            eos_token_id=eos_token_id,
            pad_token_id=eos_token_id,
        )
    )
    return unet, vae, text_encoder


def build_real_size_ip2p(folder: str, seed: int = 0) -> str:
    """InstructPix2Pix at its published size (1.07 B parameters, ~4.3 GB in float32)."""
    from diffusers import EulerAncestralDiscreteScheduler

    os.makedirs(folder, exist_ok=True)
    tok = save_tokenizer(os.path.join(folder, "tokenizer"), vocab_size=CLIP_VOCAB_SIZE)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        unet, vae, text_encoder = real_size_ip2p_modules(len(tok), tok.bos_token_id, tok.eos_token_id)
    # The hub folder ships an Euler-ancestral config; the guidance switches it to SD's DDIM.
    scheduler = EulerAncestralDiscreteScheduler(
        num_train_timesteps=1000,
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        steps_offset=1,
        prediction_type="epsilon",
    )
    return save_ip2p_folder(folder, unet, vae, text_encoder, scheduler)


def real_size_depth_anything_config():
    """Depth-Anything-V2-Small's config: DINOv2 ViT-S/14 backbone (4 of its 12 layers tapped),
    DPT neck 48/96/192/384, fusion 64 (24.8 M parameters)."""
    from transformers import DepthAnythingConfig, Dinov2Config

    backbone = Dinov2Config(
        hidden_size=384,
        num_hidden_layers=12,
        num_attention_heads=6,
        mlp_ratio=4,
        patch_size=14,
        image_size=518,
        layerscale_value=1.0,
        out_features=["stage9", "stage10", "stage11", "stage12"],
        reshape_hidden_states=False,
    )
    return DepthAnythingConfig(
        backbone_config=backbone,
        patch_size=14,
        reassemble_hidden_size=384,
        reassemble_factors=[4, 2, 1, 0.5],
        neck_hidden_sizes=[48, 96, 192, 384],
        fusion_hidden_size=64,
        head_hidden_size=32,
        head_in_index=-1,
        depth_estimation_type="relative",
    )


def build_real_size_depth_anything(folder: str, seed: int = 0) -> str:
    """Depth-Anything-V2-Small with random weights and its 518 px image-processor config."""
    return save_depth_anything_folder(folder, real_size_depth_anything_config(), seed, input_size=518)


_BUILDERS = {
    "tiny": {"ip2p": build_tiny_ip2p, "depth_anything": build_tiny_depth_anything},
    "real-size": {"ip2p": build_real_size_ip2p, "depth_anything": build_real_size_depth_anything},
}


def default_cache_dir() -> str:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "gs_regional", "priors")


def cached_priors(kind: str, cache_dir: Optional[str] = None, seed: int = 0) -> Dict[str, str]:
    """{"ip2p", "depth_anything"} -> folder of the `kind` ("tiny" or "real-size") random priors,
    built on first use under `cache_dir` (default ~/.cache/gs_regional/priors). A folder is built
    in a temporary sibling and renamed into place when complete, so an interrupted build is
    never taken for a cached one. The key includes the diffusers/transformers versions, whose
    save formats the folders follow."""
    import diffusers
    import transformers

    if kind not in _BUILDERS:
        raise ValueError(f"unknown prior kind '{kind}'; use one of {', '.join(_BUILDERS)}")
    root = os.path.expanduser(cache_dir or default_cache_dir())
    key = f"{kind}-v{BUILD_VERSION}-seed{seed}-diffusers{diffusers.__version__}-transformers{transformers.__version__}"
    folders = {}
    for name, build in _BUILDERS[kind].items():
        final = os.path.join(root, key, name)
        if not os.path.isfile(os.path.join(final, "complete.json")):
            os.makedirs(os.path.dirname(final), exist_ok=True)
            tmp = tempfile.mkdtemp(prefix=f".{name}-", dir=os.path.dirname(final))
            try:
                build(tmp, seed=seed)
                with open(os.path.join(tmp, "complete.json"), "w") as f:
                    json.dump({"kind": kind, "component": name, "seed": seed, "version": BUILD_VERSION}, f)
                if os.path.isdir(final) and not os.path.isfile(os.path.join(final, "complete.json")):
                    shutil.rmtree(final)  # left by an interrupted build of an older version
                os.rename(tmp, final)
            except OSError:
                shutil.rmtree(tmp, ignore_errors=True)
                if not os.path.isfile(os.path.join(final, "complete.json")):
                    raise
                # else another process finished the same folder first: use that one
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise
        folders[name] = final
    return folders
