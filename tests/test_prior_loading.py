"""The priors load on a background thread (gs_regional/utils/pretrained.py PriorLoader) while the
scene is read and the source views render: the config and folder checks still run in the caller's
thread at once, the constructors run in order on one thread, and a construction error is raised
in the thread that first uses the prior; through launch.py, a bad folder is one line naming it."""
import argparse
import glob
import shutil
import threading
from dataclasses import dataclass

import pytest

from gs_regional.config import ConfigError
from gs_regional.launch import main
from gs_regional.utils import pretrained
from gs_regional.utils.pretrained import PretrainedLoadError, PriorLoader

from trial_helpers import ROOT


class _Prior:
    built = []

    @dataclass
    class Config:
        name: str = "a"
        fail: bool = False

    @classmethod
    def check_source(cls, cfg):
        if cfg.name == "missing":
            raise PretrainedLoadError("model folder 'missing' does not exist")

    def __init__(self, cfg=None):
        self.thread = threading.current_thread().name
        _Prior.built.append((cfg or {}).get("name"))
        if (cfg or {}).get("fail"):
            raise PretrainedLoadError("cannot load the unet from '/some/folder': broken")


def test_loader_builds_in_order_on_another_thread():
    _Prior.built = []
    loader = PriorLoader(background=True)
    loader.start("first", _Prior, {"name": "a"})
    loader.start("second", _Prior, {"name": "b"})
    assert loader.get("second").thread != threading.current_thread().name
    loader.wait()
    assert _Prior.built == ["a", "b"] and loader.get("first").thread == loader.get("second").thread
    loader.set("none", None)
    assert loader.get("none") is None and loader.get("absent") is None


def test_loader_checks_now_and_raises_in_the_callers_thread():
    loader = PriorLoader(background=True)
    with pytest.raises(PretrainedLoadError, match="'missing' does not exist"):  # check_source, at once
        loader.start("p", _Prior, {"name": "missing"})
    with pytest.raises(ConfigError):  # the Config, at once
        loader.start("p", _Prior, {"nme": "a"})
    loader.start("p", _Prior, {"fail": True})
    with pytest.raises(PretrainedLoadError, match="/some/folder"):
        loader.wait()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from gs_regional.bench.pipeline import prepare_scene
    from gs_regional.testing.real_size_models import cached_priors

    tmp = tmp_path_factory.mktemp("prior_loading")
    args = argparse.Namespace(ply=None, data=None, resolution=32, gaussians=2000)
    return prepare_scene(args, str(tmp / "scene")), cached_priors("tiny"), tmp


def _launch(scene, tmp, ip2p, depth, capsys):
    sc, _, _ = scene
    out = tmp / "runs"
    rc = main(["--config", str(ROOT / "configs" / "edit.yaml"), "--train", f"exp_root_dir={out}", "name=bad",
               f"data.source={sc['data_source']}", f"system.geometry.ply={sc['ply']}", "system.prompt=a hat",
               f"system.guidance.pretrained={ip2p}", f"system.depth.pretrained={depth}",
               "system.guidance.local_files_only=true", "system.depth.local_files_only=true",
               "system.stop_after=localize", "system.localization.max_views=1", "trainer.enable_progress_bar=false"])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, [line for line in err.splitlines() if line.startswith("error:")], glob.glob(str(out / "bad" / "*"))


@pytest.mark.parametrize("background", [True, False])
def test_missing_folder_is_one_line_before_any_trial(scene, capsys, monkeypatch, background):
    monkeypatch.setattr(pretrained, "BACKGROUND_LOADING", background)
    _, priors, tmp = scene
    missing = str(tmp / "no_such_depth")
    rc, err, trials = _launch(scene, tmp, priors["ip2p"], missing, capsys)
    assert rc == 2 and len(err) == 1 and missing in err[0], err
    assert trials == []


@pytest.mark.parametrize("background", [True, False])
def test_broken_weights_are_one_line_from_the_main_thread(scene, capsys, monkeypatch, background):
    """Weights that do not load fail on the loader thread; the error is raised where the system
    waits for its priors (main thread, before the first stage) and the trial folder goes again.
    Loaded in the caller's thread, the system's construction fails, before any trial folder."""
    monkeypatch.setattr(pretrained, "BACKGROUND_LOADING", background)
    _, priors, tmp = scene
    broken = tmp / "broken_ip2p"
    if not broken.exists():
        shutil.copytree(priors["ip2p"], broken)
        (broken / "unet" / "diffusion_pytorch_model.safetensors").write_bytes(b"not a safetensors file")
    rc, err, trials = _launch(scene, tmp, str(broken), priors["depth_anything"], capsys)
    assert rc == 2 and len(err) == 1 and str(broken) in err[0], err
    assert trials == []
