"""Tiny random-weight models of exactly the classes the real priors use, saved in the hub layouts.

Tests (and a CPU smoke run) load them back through the same `from_pretrained(folder)` paths that a
user's `pretrained=timbrooks/instruct-pix2pix` takes, so the loading and the pipelines are the real
code; only the sizes and the (seeded, random) weights differ. Nothing here touches the network.

    build_tiny_ip2p(folder)            # unet/ vae/ text_encoder/ tokenizer/ scheduler/ model_index.json
    build_tiny_depth_anything(folder)  # config.json, model.safetensors, preprocessor_config.json
    build_tiny_clip(folder)            # config.json, model.safetensors, tokenizer files, preprocessor_config.json
    build_all(folder)                  # the three above in folder/{ip2p,depth_anything,clip}
"""
from __future__ import annotations

import json
import os
from typing import Dict, List, Optional, Tuple

import torch

# Words whose BPE merges the tiny vocabulary contains; everything else falls back to byte tokens.
_WORDS = (
    "a an the of to and with in on into make turn give him her it his photo face man woman person "
    "red blue green mustache hat glasses beard donut sprinkles icing bear statue painting style "
    "like van gogh old young smile snow"
).split()
BOS, EOS = "<|startoftext|>", "<|endoftext|>"
MAX_TEXT_LENGTH = 77  # as CLIP's tokenizer: prompts longer than this are truncated


def _bytes_to_unicode() -> Dict[int, str]:
    """GPT-2/CLIP's reversible byte -> printable unicode map (the byte-level alphabet)."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, map(chr, cs)))


def tiny_clip_vocab(size: Optional[int] = None) -> Tuple[Dict[str, int], List[str]]:
    """A CLIP-style BPE vocabulary: the 256 byte symbols, each also with the end-of-word
    marker, the merges that spell out `_WORDS`, then the bos/eos tokens (as in CLIP, last).

    `size` pads it with never-produced filler tokens to that many entries, so that the ids match
    a real CLIP tokenizer's layout (49408 entries, bos 49406, eos 49407)."""
    alphabet = list(_bytes_to_unicode().values())
    tokens = alphabet + [c + "</w>" for c in alphabet]
    merges: List[str] = []
    seen = set(tokens)
    for word in _WORDS:
        symbols = list(word[:-1]) + [word[-1] + "</w>"]
        while len(symbols) > 1:  # merge left to right; every intermediate is a vocabulary entry
            pair = f"{symbols[0]} {symbols[1]}"
            merged = symbols[0] + symbols[1]
            if pair not in merges:
                merges.append(pair)
            if merged not in seen:
                seen.add(merged)
                tokens.append(merged)
            symbols = [merged] + symbols[2:]
    if size is not None:
        if size < len(tokens) + 2:
            raise ValueError(f"a CLIP vocabulary needs at least {len(tokens) + 2} entries, got size={size}")
        tokens += [f"<|filler_{i}|>" for i in range(size - len(tokens) - 2)]
    tokens += [BOS, EOS]
    return {t: i for i, t in enumerate(tokens)}, merges


def _write_vocab_files(folder: str, size: Optional[int] = None) -> Tuple[Dict[str, int], List[str]]:
    vocab, merges = tiny_clip_vocab(size)
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "vocab.json"), "w", encoding="utf-8") as f:
        json.dump(vocab, f, ensure_ascii=False)
    with open(os.path.join(folder, "merges.txt"), "w", encoding="utf-8") as f:
        f.write("#version: 0.2\n" + "\n".join(merges) + "\n")
    return vocab, merges


def save_tokenizer(folder: str, vocab_size: Optional[int] = None):
    """Write vocab.json/merges.txt, then let CLIPTokenizer read them and save its full layout."""
    from transformers import CLIPTokenizer

    _write_vocab_files(folder, vocab_size)
    tok = CLIPTokenizer.from_pretrained(folder, model_max_length=MAX_TEXT_LENGTH)
    tok.save_pretrained(folder)
    return tok


def _text_config(vocab_size: int, bos_id: int, eos_id: int):
    from transformers import CLIPTextConfig

    return CLIPTextConfig(
        vocab_size=vocab_size,
        hidden_size=32,
        intermediate_size=37,
        num_hidden_layers=2,
        num_attention_heads=4,
        max_position_embeddings=MAX_TEXT_LENGTH,
        projection_dim=32,
        bos_token_id=bos_id,
        eos_token_id=eos_id,
        pad_token_id=eos_id,
    )


def build_tiny_ip2p(folder: str, seed: int = 0) -> str:
    """An InstructPix2Pix pipeline folder (diffusers layout) with tiny random weights."""
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextModel

    os.makedirs(folder, exist_ok=True)
    tok = save_tokenizer(os.path.join(folder, "tokenizer"))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        unet = UNet2DConditionModel(
            sample_size=8,
            in_channels=8,  # noisy latents (4) + image-conditioning latents (4), as IP2P
            out_channels=4,
            layers_per_block=1,
            block_out_channels=(32, 64),
            down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
            up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
            cross_attention_dim=32,
            attention_head_dim=8,
            norm_num_groups=32,
        )
        torch.manual_seed(seed + 1)
        vae = AutoencoderKL(
            in_channels=3,
            out_channels=3,
            down_block_types=("DownEncoderBlock2D",) * 4,  # 4 levels: 3 downsamplings, scale factor 8
            up_block_types=("UpDecoderBlock2D",) * 4,
            block_out_channels=(8, 16, 16, 16),
            layers_per_block=1,
            latent_channels=4,
            norm_num_groups=8,
            sample_size=32,
            scaling_factor=0.18215,
        )
        torch.manual_seed(seed + 2)
        text_encoder = CLIPTextModel(_text_config(len(tok), tok.bos_token_id, tok.eos_token_id))
    scheduler = DDIMScheduler(  # the Stable Diffusion v1 schedule that IP2P was trained with
        num_train_timesteps=1000,
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        clip_sample=False,
        set_alpha_to_one=False,
        steps_offset=1,
        prediction_type="epsilon",
    )
    return save_ip2p_folder(folder, unet, vae, text_encoder, scheduler)


def save_ip2p_folder(folder: str, unet, vae, text_encoder, scheduler) -> str:
    """Save the components (the tokenizer is already in folder/tokenizer) and model_index.json."""
    import diffusers

    unet.save_pretrained(os.path.join(folder, "unet"))
    vae.save_pretrained(os.path.join(folder, "vae"))
    text_encoder.save_pretrained(os.path.join(folder, "text_encoder"))
    scheduler.save_pretrained(os.path.join(folder, "scheduler"))
    index = {  # what diffusers' StableDiffusionInstructPix2PixPipeline.save_pretrained writes
        "_class_name": "StableDiffusionInstructPix2PixPipeline",
        "_diffusers_version": diffusers.__version__,
        "feature_extractor": [None, None],
        "requires_safety_checker": False,
        "safety_checker": [None, None],
        "scheduler": ["diffusers", type(scheduler).__name__],
        "text_encoder": ["transformers", "CLIPTextModel"],
        "tokenizer": ["transformers", "CLIPTokenizer"],
        "unet": ["diffusers", "UNet2DConditionModel"],
        "vae": ["diffusers", "AutoencoderKL"],
    }
    with open(os.path.join(folder, "model_index.json"), "w") as f:
        json.dump(index, f, indent=2)
    return folder


def build_tiny_depth_anything(folder: str, seed: int = 0) -> str:
    """A Depth Anything (V2 layout) folder: small DINOv2 backbone (patch 14) and DPT head."""
    from transformers import DepthAnythingConfig, Dinov2Config

    backbone = Dinov2Config(
        hidden_size=32,
        num_hidden_layers=4,
        num_attention_heads=2,
        mlp_ratio=2,
        patch_size=14,
        image_size=56,
        out_features=["stage1", "stage2", "stage3", "stage4"],
        reshape_hidden_states=False,
    )
    config = DepthAnythingConfig(
        backbone_config=backbone,
        patch_size=14,
        reassemble_hidden_size=32,
        reassemble_factors=[4, 2, 1, 0.5],
        neck_hidden_sizes=[8, 16, 16, 32],
        fusion_hidden_size=16,
        head_hidden_size=8,
        depth_estimation_type="relative",
    )
    return save_depth_anything_folder(folder, config, seed, input_size=56)


def save_depth_anything_folder(folder: str, config, seed: int, input_size: int) -> str:
    """A random DepthAnythingForDepthEstimation of `config` and a processor config resizing to
    `input_size` (the fields of depth-anything/Depth-Anything-V2-Small-hf), saved in `folder`."""
    from transformers import DepthAnythingForDepthEstimation

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed + 3)
        model = DepthAnythingForDepthEstimation(config)
        # transformers' init (std 0.02, zero biases) makes the random head output ~1e-7, nearly all
        # cut to 0 by its final ReLU; PyTorch's conv init and a positive last bias give a disparity
        # that is positive and varies with the image, so calibration code downstream can use it.
        for m in list(model.neck.modules()) + list(model.head.modules()):
            if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d)):
                m.reset_parameters()
        torch.nn.init.constant_(model.head.conv3.bias, 1.0)
    model.save_pretrained(folder)
    processor = {
        "do_normalize": True,
        "do_pad": False,
        "do_rescale": True,
        "do_resize": True,
        "ensure_multiple_of": 14,
        "image_mean": [0.485, 0.456, 0.406],
        "image_processor_type": "DPTImageProcessor",
        "image_std": [0.229, 0.224, 0.225],
        "keep_aspect_ratio": True,
        "resample": 3,
        "rescale_factor": 1 / 255,
        "size": {"height": input_size, "width": input_size},
        "size_divisor": None,
    }
    with open(os.path.join(folder, "preprocessor_config.json"), "w") as f:
        json.dump(processor, f, indent=2)
    return folder


def build_tiny_clip(folder: str, seed: int = 0) -> str:
    """A CLIPModel folder (openai/clip-vit-* layout) with tokenizer and image-processor config."""
    from transformers import CLIPConfig, CLIPModel, CLIPVisionConfig

    tok = save_tokenizer(folder)
    text = _text_config(len(tok), tok.bos_token_id, tok.eos_token_id)
    vision = CLIPVisionConfig(
        hidden_size=32, intermediate_size=37, num_hidden_layers=2, num_attention_heads=4, image_size=32, patch_size=8
    )
    config = CLIPConfig(text_config=text.to_dict(), vision_config=vision.to_dict(), projection_dim=16)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed + 4)
        model = CLIPModel(config)
    model.save_pretrained(folder)
    processor = {  # the fields of openai/clip-vit-large-patch14, at a tiny size
        "crop_size": {"height": 32, "width": 32},
        "do_center_crop": True,
        "do_convert_rgb": True,
        "do_normalize": True,
        "do_rescale": True,
        "do_resize": True,
        "image_mean": [0.48145466, 0.4578275, 0.40821073],
        "image_processor_type": "CLIPImageProcessor",
        "image_std": [0.26862954, 0.26130258, 0.27577711],
        "resample": 3,
        "rescale_factor": 1 / 255,
        "size": {"shortest_edge": 32},
    }
    with open(os.path.join(folder, "preprocessor_config.json"), "w") as f:
        json.dump(processor, f, indent=2)
    return folder


def build_all(folder: str, seed: int = 0) -> Dict[str, str]:
    """Build the three tiny priors under `folder`; returns {"ip2p", "depth_anything", "clip"} -> path."""
    paths = {
        "ip2p": build_tiny_ip2p(os.path.join(folder, "ip2p"), seed),
        "depth_anything": build_tiny_depth_anything(os.path.join(folder, "depth_anything"), seed),
        "clip": build_tiny_clip(os.path.join(folder, "clip"), seed),
    }
    return paths
