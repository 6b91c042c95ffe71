"""InstructPix2Pix guidance on tiny random-weight models loaded through the real from_pretrained path."""
import os
import shutil
import socket
import time

import pytest
import torch

from tiny_models_fixture import one_thread, tiny_models  # noqa: F401

import gs_regional
from gs_regional.config import ConfigError
from gs_regional.guidance.instructpix2pix import InstructPix2Pix
from gs_regional.utils.pretrained import PretrainedLoadError, resolve_device, resolve_dtype

pytestmark = pytest.mark.usefixtures("one_thread")
PROMPT = "give him a mustache"


@pytest.fixture(scope="module")
def ip2p(tiny_models):
    return InstructPix2Pix({"pretrained": tiny_models["ip2p"]})


def images(b=2, h=36, w=44, seed=0):
    return torch.rand(b, h, w, 3, generator=torch.Generator().manual_seed(seed))


def test_loads_real_classes_and_registers(ip2p):
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextModel

    assert gs_regional.find("instructpix2pix") is InstructPix2Pix
    assert isinstance(ip2p.unet, UNet2DConditionModel) and ip2p.unet.config.in_channels == 8
    assert isinstance(ip2p.vae, AutoencoderKL) and ip2p.vae_scale_factor == 8
    assert isinstance(ip2p.text_encoder, CLIPTextModel)
    assert isinstance(ip2p.scheduler, DDIMScheduler)
    assert ip2p.scheduler.config.beta_schedule == "scaled_linear" and not ip2p.scheduler.config.clip_sample
    assert ip2p.max_text_length == 77
    # Weights must never land in a system's state dict / checkpoint.
    assert not isinstance(ip2p, torch.nn.Module)
    holder = torch.nn.Module()
    holder.guidance = ip2p
    assert len(holder.state_dict()) == 0


def test_bad_config_values(tiny_models):
    with pytest.raises(ConfigError, match="guidance_scal"):
        InstructPix2Pix({"pretrained": tiny_models["ip2p"], "guidance_scal": 3})
    with pytest.raises(ValueError, match="dtype"):
        resolve_dtype("float8", torch.device("cpu"))
    assert resolve_dtype("auto", torch.device("cpu")) == torch.float32
    assert resolve_dtype("auto", torch.device("cuda")) == torch.float16
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            resolve_device("cuda")


def test_relevance_range_shape_and_counters(ip2p):
    x = images()
    ip2p.reset_counters()
    rel = ip2p.relevance(x, PROMPT, samples=2)
    assert rel.shape == (2, 36, 44) and rel.dtype == torch.float32
    assert float(rel.min()) >= 0.0
    assert torch.allclose(rel.flatten(1).amax(1), torch.ones(2))  # each view normalised to its max
    assert ip2p.counters() == {"unet_evals": 2 * 2 * 2, "vae_encodes": 2, "vae_decodes": 0}
    # Prompt embeddings are cached (text and the empty prompt).
    assert PROMPT in ip2p._emb_cache and "" in ip2p._emb_cache
    # A view's map does not depend on how the batch is split into UNet calls.
    # The default "auto" is one view per UNet call on a CPU (and measures the memory on CUDA).
    assert ip2p.cfg.batch_size == "auto" and ip2p.batch_size_for(x) == 1
    ip2p.cfg.batch_size = 4
    try:
        rel_split = ip2p.relevance(x, PROMPT, samples=2)
    finally:
        ip2p.cfg.batch_size = 1
    # 1e-3: the UNet's float reductions depend on batch size, CPU model, BLAS and thread count
    # (1e-5 failed on one x86 machine); maps are normalised to [0, 1], so 1e-3 never flips a mask.
    assert torch.allclose(rel, rel_split, atol=1e-3)
    assert not torch.allclose(rel[0], rel[1])
    # The prompt matters.
    assert not torch.allclose(rel, ip2p.relevance(x, "make it snow", samples=2), atol=1e-3)


def test_more_samples_reduce_variance_across_seeds(ip2p):
    x = images(1, 16, 16, seed=3)
    var = {}
    for samples in (1, 4):
        maps = torch.stack([ip2p.relevance(x, PROMPT, samples=samples, seed=s) for s in range(4)])
        var[samples] = float(maps.var(dim=0).mean())
    assert var[4] < 0.6 * var[1], var


def test_mask(ip2p):
    x = images()
    ip2p.reset_counters()
    m = ip2p.mask(x, PROMPT, threshold=0.0)
    assert m.shape == (2, 36, 44) and bool((m == 1).all())
    assert ip2p.unet_evals == 0  # γ = 0 does not run the model
    m = ip2p.mask(x, PROMPT, threshold=0.6)
    assert set(torch.unique(m).tolist()) <= {0.0, 1.0}


def test_edit_shape_determinism_counters(ip2p):
    x = images(2, 36, 44)  # not a multiple of 8
    cond = images(2, 36, 44, seed=1)
    ip2p.reset_counters()
    out = ip2p.edit(x, cond, PROMPT, seed=0)
    assert out.shape == (2, 36, 44, 3) and out.dtype == torch.float32
    assert float(out.min()) >= 0 and float(out.max()) <= 1
    # Full edit: 20 guided steps of 3 branches; only the condition images are encoded.
    assert ip2p.counters() == {"unet_evals": 3 * 2 * 20, "vae_encodes": 2, "vae_decodes": 2}
    assert torch.equal(out, ip2p.edit(x, cond, PROMPT, seed=0))
    assert (out - ip2p.edit(x, cond, PROMPT, seed=1)).abs().max() > 1e-3
    ip2p.cfg.batch_size = 4
    try:
        split = ip2p.edit(x, cond, PROMPT, seed=0)
    finally:
        ip2p.cfg.batch_size = 1
    # 1e-3 on [0, 1] images: batch-size-dependent float reductions (see the relevance test).
    assert torch.allclose(out, split, atol=1e-3)


def test_each_view_is_edited_as_alone_with_its_own_seed(ip2p):
    """One seed per view: a batched call gives every view what a call with that view alone gives,
    whatever the batch size; the noise of a view follows its own seed, not its position."""
    x, cond = images(3, 24, 24), images(3, 24, 24, seed=1)
    seeds = [7, 1003, 42]
    alone = torch.cat([ip2p.edit(x[i : i + 1], cond[i : i + 1], PROMPT, t_start=600, seed=s) for i, s in enumerate(seeds)])
    rel_alone = torch.cat([ip2p.relevance(x[i : i + 1], PROMPT, samples=2, seed=s) for i, s in enumerate(seeds)])
    for batch_size in (1, 2, 3):
        ip2p.cfg.batch_size = batch_size
        try:
            edited = ip2p.edit(x, cond, PROMPT, t_start=600, seed=seeds)
            rel = ip2p.relevance(x, PROMPT, samples=2, seed=seeds)
        finally:
            ip2p.cfg.batch_size = 1
        # 1e-3 on [0, 1] images: batch-size-dependent float reductions (see the relevance test).
        assert torch.allclose(edited, alone, atol=1e-3), (batch_size, float((edited - alone).abs().max()))
        assert torch.allclose(rel, rel_alone, atol=1e-3), batch_size
        if batch_size == 1:  # the same computations: exactly equal
            assert torch.equal(edited, alone) and torch.equal(rel, rel_alone)
    swapped = ip2p.edit(x, cond, PROMPT, t_start=600, seed=[seeds[1], seeds[0], seeds[2]])
    assert (swapped[0] - alone[0]).abs().max() > 1e-2 and torch.equal(swapped[2], alone[2])


def test_partial_edit_starts_at_the_scheduled_step(ip2p, monkeypatch):
    x = images(1, 32, 32)
    recorded = []
    add_noise = ip2p.scheduler.add_noise

    def spy(z0, noise, t):
        recorded.append(t.tolist())
        return add_noise(z0, noise, t)

    monkeypatch.setattr(ip2p.scheduler, "add_noise", spy)
    evals = {}
    for t_start in (300, 750, None):
        ip2p.reset_counters()
        ip2p.edit(x, x, PROMPT, t_start=t_start, seed=0)
        evals[t_start] = ip2p.unet_evals
        assert ip2p.vae_encodes == (1 if t_start is None else 2)
    # DDIM "leading" spacing with steps_offset 1: 951, 901, ..., 1; the start is the largest <= t_start.
    assert recorded == [[251], [701]]  # a full edit starts from pure noise, no add_noise
    assert evals == {300: 3 * 6, 750: 3 * 15, None: 3 * 20}
    with pytest.raises(ValueError, match="below the last DDIM timestep"):
        ip2p.edit(x, x, PROMPT, t_start=0)
    with pytest.raises(ValueError, match="t_start"):
        ip2p.edit(x, x, PROMPT, t_start=1000)


def test_matches_diffusers_pipeline(ip2p, tiny_models):
    """A full edit is exactly what diffusers' StableDiffusionInstructPix2PixPipeline computes."""
    import numpy as np
    from diffusers import StableDiffusionInstructPix2PixPipeline
    from PIL import Image

    pipe = StableDiffusionInstructPix2PixPipeline.from_pretrained(
        tiny_models["ip2p"], safety_checker=None, feature_extractor=None
    )
    pipe.set_progress_bar_config(disable=True)
    pixels = (images(1, 32, 32)[0].numpy() * 255).astype(np.uint8)
    ref = pipe(
        PROMPT,
        image=Image.fromarray(pixels),
        num_inference_steps=20,
        guidance_scale=7.5,
        image_guidance_scale=1.5,
        generator=torch.Generator().manual_seed(5),
        output_type="pt",
    ).images
    x = torch.from_numpy(pixels.copy()).float()[None] / 255
    out = ip2p.edit(x, x, PROMPT, seed=5)
    assert torch.allclose(out.permute(0, 3, 1, 2), ref, atol=1e-4)


def test_prompt_errors_and_truncation(ip2p):
    x = images(1, 16, 16)
    for bad in ("", "   "):
        with pytest.raises(ValueError, match="non-empty"):
            ip2p.relevance(x, bad)
        with pytest.raises(ValueError, match="non-empty"):
            ip2p.edit(x, x, bad)
    long_prompt = " ".join(["mustache"] * 100)
    with pytest.warns(UserWarning, match="truncated"):
        rel = ip2p.relevance(x, long_prompt)
    assert rel.shape == (1, 16, 16)


def test_bad_images(ip2p):
    x = images(1, 16, 16)
    with pytest.raises(ValueError, match=r"\(B, H, W, 3\)"):
        ip2p.relevance(torch.rand(1, 16, 16, 4), PROMPT)
    with pytest.raises(TypeError, match="float"):
        ip2p.relevance((x * 255).to(torch.uint8), PROMPT)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        ip2p.relevance(x * 255, PROMPT)
    with pytest.raises(TypeError, match="cond_images"):
        ip2p.edit(x, x.numpy(), PROMPT)
    with pytest.raises(ValueError, match="same shape"):
        ip2p.edit(x, images(1, 24, 16), PROMPT)
    with pytest.raises(ValueError, match="timestep"):
        ip2p.relevance(x, PROMPT, timestep=1000)


def test_missing_component_is_named(tiny_models, tmp_path):
    broken = tmp_path / "ip2p"
    shutil.copytree(tiny_models["ip2p"], broken)
    shutil.rmtree(broken / "vae")
    with pytest.raises(PretrainedLoadError, match=r"lacks the component 'vae'"):
        InstructPix2Pix({"pretrained": str(broken)})
    shutil.copytree(os.path.join(tiny_models["ip2p"], "vae"), broken / "vae")
    os.remove(broken / "scheduler" / "scheduler_config.json")
    with pytest.raises(PretrainedLoadError, match=r"'scheduler'.*scheduler_config.json"):
        InstructPix2Pix({"pretrained": str(broken)})
    with pytest.raises(PretrainedLoadError, match="does not exist"):
        InstructPix2Pix({"pretrained": str(tmp_path / "nowhere")})


def test_uncached_hub_id_fails_fast_without_network(monkeypatch):
    assert os.environ.get("HF_HUB_OFFLINE") == "1"  # set by conftest before any HF import
    attempts = []
    guarded = socket.socket.connect

    def record(self, address):
        attempts.append(address)
        return guarded(self, address)

    monkeypatch.setattr(socket.socket, "connect", record)
    t0 = time.time()
    with pytest.raises(PretrainedLoadError, match="hub id.*offline mode is on"):
        InstructPix2Pix({"pretrained": "gs-regional-test/no-such-model"})
    assert time.time() - t0 < 30
    remote = [a for a in attempts if isinstance(a, tuple) and a[0] not in ("127.0.0.1", "localhost", "::1")]
    assert remote == []


def test_speed_options_do_not_change_results(ip2p, tiny_models):
    """Classic attention, channels_last and cpu_offload (a no-op on CPU) compute the same edit."""
    other = InstructPix2Pix(
        {"pretrained": tiny_models["ip2p"], "sdpa": False, "channels_last": True, "cpu_offload": True,
         "num_inference_steps": 5, "dtype": "float32", "device": "cpu"}
    )
    from diffusers.models.attention_processor import AttnProcessor

    assert all(isinstance(p, AttnProcessor) for p in other.unet.attn_processors.values())
    x = images(1, 24, 24)
    ip2p.cfg.num_inference_steps = 5
    try:
        ref = ip2p.edit(x, x, PROMPT, seed=3)
    finally:
        ip2p.cfg.num_inference_steps = 20
    assert torch.allclose(other.edit(x, x, PROMPT, seed=3), ref, atol=1e-4)
