"""`guidance.batch_size: auto`: one view per model call on a CPU; on CUDA the most views whose
memory, measured once per resolution with a probe call, fits the free memory."""
import pytest
import torch

from gs_regional.config import ConfigError
from gs_regional.guidance import base as guidance_base
from gs_regional.guidance.base import AUTO_MAX_BATCH, Guidance, fitting_batch

GiB = 1 << 30


class ProbedEditor(Guidance):
    """A plugin on a (pretended) CUDA device whose probe reports known peaks per view."""

    def __init__(self, cfg=None, per_view=GiB, first=3 * GiB) -> None:
        super().__init__(cfg)
        self.device = torch.device("cuda")
        self.peaks = (first, first + per_view)
        self.probed, self.batches = [], []

    def _probe_peaks(self, image):
        self.probed.append(tuple(image.shape))
        self.unet_evals += 3  # a probe spends a UNet call; the counters must not show it
        return self.peaks

    def _edit(self, images, cond_images, prompt, t_start, seeds, cameras):
        self.batches.append(images.shape[0])
        return images


def test_fitting_batch_fills_the_share_of_free_memory():
    # 20 GiB free, 85 % usable = 17 GiB: the first view takes 3, each further one 1 -> 15 views.
    assert fitting_batch(20 * GiB, 3 * GiB, 4 * GiB) == 15
    assert fitting_batch(2 * GiB, 3 * GiB, 4 * GiB) == 1  # even one does not fit: never below 1
    assert fitting_batch(1000 * GiB, 3 * GiB, 4 * GiB) == AUTO_MAX_BATCH
    assert fitting_batch(20 * GiB, 3 * GiB, 3 * GiB) == AUTO_MAX_BATCH  # no growth measured: the cap


def test_auto_is_one_view_per_call_on_a_cpu():
    ed = ProbedEditor({"batch_size": "auto"})
    ed.device = torch.device("cpu")
    x = torch.rand(5, 8, 8, 3)
    ed.edit(x, x, "edit it")
    assert ed.batches == [1] * 5 and ed.probed == []


def test_auto_measures_once_per_resolution_and_splits_by_it(monkeypatch):
    monkeypatch.setattr(torch.cuda, "synchronize", lambda device=None: None)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (8 * GiB, 80 * GiB))
    ed = ProbedEditor({"batch_size": "auto"})
    x = torch.rand(7, 8, 12, 3)
    ed.edit(x, x, "edit it")
    # 0.85 * 8 GiB = 6.8 GiB: 3 for the first view, 1 for each next -> 4 views per call.
    assert ed.batches == [4, 3] and ed.probed == [(1, 8, 12, 3)]
    assert ed.counters()["unet_evals"] == 0  # the probe is not counted as the edit's
    ed.edit(x, x, "edit it")
    assert ed.probed == [(1, 8, 12, 3)]  # measured once at this resolution
    y = torch.rand(2, 16, 16, 3)
    ed.edit(y, y, "edit it")
    assert ed.probed == [(1, 8, 12, 3), (1, 16, 16, 3)]


def test_a_plugin_without_a_probe_gets_one_view(monkeypatch):
    monkeypatch.setattr(torch.cuda, "synchronize", lambda device=None: None)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (8 * GiB, 80 * GiB))
    ed = ProbedEditor({"batch_size": "auto"})
    monkeypatch.setattr(ed, "_probe_peaks", lambda image: Guidance._probe_peaks(ed, image))
    x = torch.rand(3, 8, 8, 3)
    ed.edit(x, x, "edit it")
    assert ed.batches == [1, 1, 1]


@pytest.mark.parametrize("bad", ["big", 0, -2])
def test_bad_batch_size_names_the_key(bad):
    with pytest.raises(ConfigError, match=r"batch_size \(views per model call\) must be >= 1 or 'auto'"):
        ProbedEditor({"batch_size": bad})


def test_configs_ship_auto():
    from omegaconf import OmegaConf
    from trial_helpers import ROOT

    edit = OmegaConf.load(ROOT / "configs" / "edit.yaml")
    assert edit.system.guidance.batch_size == guidance_base.AUTO
