"""The tiny random-weight priors: hub layouts, real classes, determinism, build time."""
import json
import os
import time

import pytest
import torch
from safetensors.torch import load_file

from tiny_models_fixture import one_thread, tiny_models  # noqa: F401

from gs_regional.testing.tiny_models import build_all, build_tiny_depth_anything

pytestmark = pytest.mark.usefixtures("one_thread")

WEIGHTS = {
    "ip2p": ["unet/diffusion_pytorch_model.safetensors", "vae/diffusion_pytorch_model.safetensors",
             "text_encoder/model.safetensors"],
    "depth_anything": ["model.safetensors"],
    "clip": ["model.safetensors"],
}


def test_ip2p_layout_and_classes(tiny_models):
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextModel, CLIPTokenizer

    root = tiny_models["ip2p"]
    index = json.load(open(os.path.join(root, "model_index.json")))
    assert index["_class_name"] == "StableDiffusionInstructPix2PixPipeline"
    assert index["unet"] == ["diffusers", "UNet2DConditionModel"] and index["tokenizer"] == ["transformers", "CLIPTokenizer"]
    unet = UNet2DConditionModel.from_pretrained(root, subfolder="unet")
    assert (unet.config.in_channels, unet.config.out_channels, unet.config.cross_attention_dim) == (8, 4, 32)
    vae = AutoencoderKL.from_pretrained(root, subfolder="vae")
    assert len(vae.config.block_out_channels) == 4
    assert vae.encode(torch.zeros(1, 3, 32, 32)).latent_dist.mode().shape == (1, 4, 4, 4)  # scale factor 8
    te = CLIPTextModel.from_pretrained(root, subfolder="text_encoder")
    sched = DDIMScheduler.from_pretrained(root, subfolder="scheduler")
    c = sched.config
    assert (c.beta_schedule, c.beta_start, c.beta_end, c.num_train_timesteps) == ("scaled_linear", 0.00085, 0.012, 1000)
    tok = CLIPTokenizer.from_pretrained(root, subfolder="tokenizer")
    assert tok.model_max_length == 77 and te.config.max_position_embeddings == 77
    assert len(tok) == te.config.vocab_size
    ids = tok("Give him a mustache!").input_ids
    tokens = tok.convert_ids_to_tokens(ids)
    assert tokens == ["<|startoftext|>", "give</w>", "him</w>", "a</w>", "mustache</w>", "!</w>", "<|endoftext|>"]
    assert tok.pad_token == "<|endoftext|>" and te.config.eos_token_id == tok.eos_token_id
    # Words outside the small vocabulary still tokenize (byte-level fallback), never to unknowns.
    assert tok.unk_token_id not in tok("zebra xylophone").input_ids[1:-1]


def test_depth_and_clip_layouts(tiny_models):
    from transformers import AutoModelForDepthEstimation, CLIPModel, CLIPTokenizer

    da = AutoModelForDepthEstimation.from_pretrained(tiny_models["depth_anything"])
    assert type(da).__name__ == "DepthAnythingForDepthEstimation"
    assert da.config.backbone_config.model_type == "dinov2" and da.config.backbone_config.patch_size == 14
    assert os.path.isfile(os.path.join(tiny_models["depth_anything"], "preprocessor_config.json"))
    clip = CLIPModel.from_pretrained(tiny_models["clip"])
    tok = CLIPTokenizer.from_pretrained(tiny_models["clip"])
    assert len(tok) == clip.config.text_config.vocab_size
    assert os.path.isfile(os.path.join(tiny_models["clip"], "preprocessor_config.json"))


def test_deterministic_and_fast(tiny_models, tmp_path):
    t0 = time.time()
    again = build_all(str(tmp_path / "again"))
    elapsed = time.time() - t0
    for name, files in WEIGHTS.items():
        for f in files:
            a, b = load_file(os.path.join(tiny_models[name], f)), load_file(os.path.join(again[name], f))
            assert a.keys() == b.keys()
            assert all(torch.equal(a[k], b[k]) for k in a), f"{name}/{f} differs between two builds"
    assert elapsed < 30, f"building the tiny models took {elapsed:.1f} s"
    other = build_tiny_depth_anything(str(tmp_path / "seed1"), seed=1)
    a = load_file(os.path.join(tiny_models["depth_anything"], "model.safetensors"))
    b = load_file(os.path.join(other, "model.safetensors"))
    assert any(not torch.equal(a[k], b[k]) for k in a)
