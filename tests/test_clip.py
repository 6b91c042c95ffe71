"""CLIP metrics on a tiny random-weight CLIPModel loaded through from_pretrained."""
import numpy as np
import pytest
import torch

from tiny_models_fixture import one_thread, tiny_models  # noqa: F401

from gs_regional.utils.pretrained import PretrainedLoadError
from gs_regional.metrics.clip import ClipMetrics, _features

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def clip(tiny_models):
    return ClipMetrics(tiny_models["clip"])


def images(b=3, h=40, w=52, seed=0):
    return torch.rand(b, h, w, 3, generator=torch.Generator().manual_seed(seed))


def test_image_similarity(clip):
    x, y = images(seed=0), images(seed=1)
    assert clip.image_similarity(x, x) == pytest.approx(1.0, abs=1e-5)
    s = clip.image_similarity(x, y)
    assert isinstance(s, float) and -1 <= s < 1 - 1e-4
    emb = clip.image_embeddings(x)
    assert emb.shape == (3, 16) and torch.allclose(emb.norm(dim=-1), torch.ones(3), atol=1e-5)


def test_direction_similarity(clip):
    src, edited = images(seed=0), images(seed=2)
    s = clip.direction_similarity(src, edited, "a photo of a face", "a photo of a face with a mustache")
    assert isinstance(s, float) and np.isfinite(s) and -1 <= s <= 1
    # Swapping the edit direction in image space flips the sign of the cosine.
    back = clip.direction_similarity(edited, src, "a photo of a face", "a photo of a face with a mustache")
    assert back == pytest.approx(-s, abs=1e-5)
    # By hand for one pair: cosine of the differences of normalised embeddings.
    img = clip.image_embeddings(torch.cat([src[:1], edited[:1]]))
    txt = clip.text_embeddings(["a photo of a face", "a photo of a face with a mustache"])
    ref = torch.nn.functional.cosine_similarity(img[1] - img[0], txt[1] - txt[0], dim=0)
    one = clip.direction_similarity(src[:1], edited[:1], ["a photo of a face"], ["a photo of a face with a mustache"])
    assert one == pytest.approx(float(ref), abs=1e-5)


def test_preprocessing_matches_the_image_processor(clip, tiny_models):
    from transformers import AutoImageProcessor

    proc = AutoImageProcessor.from_pretrained(tiny_models["clip"])
    smooth = torch.nn.functional.interpolate(
        torch.rand(1, 3, 6, 8, generator=torch.Generator().manual_seed(1)), size=(60, 80), mode="bilinear"
    )
    pixels = (smooth[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    ref = torch.as_tensor(np.asarray(proc(images=pixels, return_tensors="np")["pixel_values"]))
    ours = clip.preprocess(torch.from_numpy(pixels).float()[None] / 255)
    assert ours.shape == ref.shape == (1, 3, 32, 32)
    assert (ours - ref).abs().mean() < 0.02


def test_errors(clip, tiny_models):
    with pytest.raises(ValueError, match="count"):
        clip.image_similarity(images(3), images(2))
    with pytest.raises(ValueError, match="edit_text has 2 entries"):
        clip.direction_similarity(images(3), images(3), "a", ["b", "c"])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        clip.image_similarity(images(1) * 2, images(1))
    with pytest.raises(PretrainedLoadError, match="not a CLIP model"):
        ClipMetrics(tiny_models["depth_anything"])


def test_features_accepts_output_objects_and_tensors():
    from transformers.modeling_outputs import BaseModelOutputWithPooling

    t = torch.ones(2, 4)
    assert _features(t) is t
    assert _features(BaseModelOutputWithPooling(last_hidden_state=None, pooler_output=t)) is t
