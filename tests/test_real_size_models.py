"""The real-size random priors have the published shapes (checked on the meta device: no weights
are allocated), and built prior folders are cached."""
import json
import os

import torch

from gs_regional.testing.real_size_models import (
    CLIP_VOCAB_SIZE,
    cached_priors,
    real_size_depth_anything_config,
    real_size_ip2p_modules,
)
from gs_regional.testing.tiny_models import save_tokenizer


def n_params(module):
    return sum(p.numel() for p in module.parameters())


def test_published_parameter_counts(tmp_path):
    from transformers import DepthAnythingForDepthEstimation

    tok = save_tokenizer(str(tmp_path / "tokenizer"), vocab_size=CLIP_VOCAB_SIZE)
    # CLIP's tokenizer layout: 49408 entries, bos 49406, eos 49407.
    assert (len(tok), tok.bos_token_id, tok.eos_token_id) == (49408, 49406, 49407)
    assert tok("give him a mustache").input_ids[0] == 49406 and tok("give him a mustache").input_ids[-1] == 49407
    with torch.device("meta"):
        unet, vae, text_encoder = real_size_ip2p_modules(len(tok), tok.bos_token_id, tok.eos_token_id)
        depth = DepthAnythingForDepthEstimation(real_size_depth_anything_config())
    # SD 1.5's UNet (859,520,964) plus the 4 extra input channels of IP2P's first conv (4 x 320 x 3 x 3).
    assert n_params(unet) == 859_520_964 + 4 * 320 * 9
    assert n_params(vae) == 83_653_863  # the SD VAE
    assert n_params(text_encoder) == 123_060_480  # CLIP ViT-L/14 text tower
    assert n_params(depth) == 24_785_089  # Depth-Anything-V2-Small
    assert unet.config.in_channels == 8 and unet.config.cross_attention_dim == 768
    assert depth.config.neck_hidden_sizes == [48, 96, 192, 384] and depth.config.fusion_hidden_size == 64


def test_cached_priors_build_once(tmp_path):
    first = cached_priors("tiny", str(tmp_path))
    assert set(first) == {"ip2p", "depth_anything"}
    marker = os.path.join(first["ip2p"], "complete.json")
    stamp = os.path.getmtime(marker)
    assert cached_priors("tiny", str(tmp_path)) == first and os.path.getmtime(marker) == stamp
    assert json.load(open(marker))["kind"] == "tiny"
    # A folder without its completion marker (an interrupted build) is rebuilt, not used.
    os.remove(os.path.join(first["depth_anything"], "complete.json"))
    again = cached_priors("tiny", str(tmp_path))
    assert os.path.isfile(os.path.join(again["depth_anything"], "complete.json"))
    assert os.path.isfile(os.path.join(again["depth_anything"], "model.safetensors"))
    assert not [d for d in os.listdir(os.path.dirname(first["ip2p"])) if d.startswith(".")]  # no temporaries left
