"""The `reconstruct` system end to end through launch.py, on small fast scenes: outputs, progressive
SH, resuming across densification, random initialisation, and the error for a scene without photos."""
import os

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from trial_helpers import shared_path
from trial_helpers import ROOT, launch, metrics_of, ply_arrays
from gs_regional.launch import main

CONFIG = str(ROOT / "configs" / "reconstruct.yaml")

# The face scene at 32x32 px, 16 of its 65 cameras (2 held out), 120 steps, densifying every 20 so
# that the number of Gaussians changes before and after the cut at step HALF; the SH degree rises
# every HALF steps.
STEPS, HALF = 120, 60
FACE_SMALL = [
    "data.downscale=16", "data.max_cameras=16",
    f"system.max_steps={STEPS}", "system.sh_degree=3", f"system.sh_degree_every={HALF}",
    "system.densify.start=20", "system.densify.every=20", "system.densify.stop=1000",
    "system.densify.opacity_reset_every=0",
    f"checkpoint.every_n_train_steps={HALF}", "trainer.enable_progress_bar=false",
]


FIT = {"config": CONFIG, "small": False}  # launch's settings for a fit of configs/reconstruct.yaml


def geometry_state(ckpt):
    state = torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]
    return {k: v for k, v in state.items() if k.startswith("geometry.") and torch.is_tensor(v)}


@pytest.fixture(scope="module")
def face_runs(tmp_path_factory):
    """An uninterrupted fit of STEPS steps, and one stopped at step HALF then resumed to STEPS."""
    face = str(shared_path("face"))
    tmp = tmp_path_factory.mktemp("reconstruct")
    full = launch(tmp, "full", f"data.source={face}", *FACE_SMALL, **FIT)
    half = launch(tmp, "cut", f"data.source={face}", *FACE_SMALL, f"trainer.max_steps={HALF}", **FIT)
    at_half = geometry_state(os.path.join(half, "ckpts", "last.ckpt"))
    resumed = launch(tmp, "cut", f"data.source={face}", *FACE_SMALL, f"resume={os.path.join(half, 'ckpts', 'last.ckpt')}",
                     **FIT)
    assert resumed == half  # resuming reuses the trial dir
    return {"full": full, "resumed": resumed, "at_half": at_half}


def test_fit_writes_metrics_and_ply(face_runs):
    trial = face_runs["full"]
    m = metrics_of(trial)
    for key in ("psnr_test", "ssim_test", "n_gaussians", "seconds"):
        assert key in m, f"metrics.json lacks {key}: {m}"
    assert m["steps"] == STEPS and m["held_out"] and m["test_views"] == 2  # cameras 0 and 8 of 16
    # STEPS steps already fit the held-out views far better than a flat grey image would.
    assert m["psnr_test"] > 17.0 and 0.5 < m["ssim_test"] <= 1.0
    assert m["seconds"] > 0
    ply = ply_arrays(os.path.join(trial, "save", "reconstructed.ply"))
    assert len(ply["x"]) == m["n_gaussians"]
    # Initialised from the 9875 SfM points, then densified.
    assert m["n_gaussians"] != 9875
    assert os.path.isfile(os.path.join(trial, "save", "test_views.png"))


def test_progressive_sh_degree(face_runs):
    """Degree 1 is trained from step HALF; degrees 2 (from step 2 HALF = STEPS) and 3 never were:
    their coefficients are still exactly zero."""
    ply = ply_arrays(os.path.join(face_runs["full"], "save", "reconstructed.ply"))
    rest = np.stack([ply[f"f_rest_{i}"] for i in range(45)], 1).reshape(-1, 3, 15)  # INRIA: channel-major
    assert np.abs(rest[:, :, :3]).max() > 1e-4
    assert np.all(rest[:, :, 3:] == 0)


def test_resume_across_densification_matches_uninterrupted(face_runs):
    full = geometry_state(os.path.join(face_runs["full"], "ckpts", "last.ckpt"))
    resumed = geometry_state(os.path.join(face_runs["resumed"], "ckpts", "last.ckpt"))
    n_half = face_runs["at_half"]["geometry.means"].shape[0]
    n_end = full["geometry.means"].shape[0]
    assert n_half != 9875 and n_end != n_half, "densification should change the count before and after the cut"
    assert metrics_of(face_runs["resumed"])["steps"] == STEPS
    for key, value in full.items():
        other = resumed[key]
        assert other.shape == value.shape, f"{key}: {tuple(other.shape)} != {tuple(value.shape)}"
        if value.is_floating_point():
            assert torch.allclose(other, value, atol=1e-5, rtol=0), f"{key} differs by {(other - value).abs().max()}"
        else:
            assert torch.equal(other, value), key
    a = ply_arrays(os.path.join(face_runs["full"], "save", "reconstructed.ply"))
    b = ply_arrays(os.path.join(face_runs["resumed"], "save", "reconstructed.ply"))
    for name in a:
        np.testing.assert_allclose(b[name], a[name], atol=1e-5, rtol=0, err_msg=name)


def test_random_init_on_a_scene_without_points(tmp_path):
    """The synthetic scene has photos but no SfM points: init=points falls back to random points."""
    cfg = OmegaConf.load(CONFIG)
    cfg.data_type, cfg.data = "synthetic-scene", {"n_cameras": 12, "width": 32, "height": 32}
    config = tmp_path / "synthetic.yaml"
    OmegaConf.save(cfg, config)
    trial = launch(tmp_path, "synthetic", "system.random_points=2000", "system.max_steps=60", "system.densify.start=20",
                   "system.densify.every=20", "trainer.enable_progress_bar=false", "checkpoint.every_n_train_steps=1000",
                   config=config, small=False)
    m = metrics_of(trial)
    assert m["steps"] == 60 and m["held_out"]
    assert len(ply_arrays(os.path.join(trial, "save", "reconstructed.ply"))["x"]) == m["n_gaussians"]
    assert m["n_gaussians"] != 2000  # densified and pruned


def test_scene_without_photos_is_a_clear_error(tmp_path, capsys):
    face = str(shared_path("face"))
    launch(tmp_path, "nophotos", f"data.source={face}", "data.load_images=false", *FACE_SMALL, expect=2, **FIT)
    err = capsys.readouterr().err
    assert "reconstruct needs photos" in err and face in err, err
    assert "Traceback" not in err


def test_bad_init_is_a_config_error(tmp_path, capsys):
    face = str(shared_path("face"))
    launch(tmp_path, "badinit", f"data.source={face}", "system.init=sfm", expect=2, **FIT)
    assert "system.init must be 'points' or 'random'" in capsys.readouterr().err


def test_export_rewrites_the_outputs_from_a_checkpoint(face_runs, capsys):
    trial = face_runs["full"]
    before = metrics_of(trial)
    os.remove(os.path.join(trial, "save", "reconstructed.ply"))
    argv = ["--config", CONFIG, "--export", f"data.source={shared_path('face')}", *FACE_SMALL,
            f"resume={os.path.join(trial, 'ckpts', 'last.ckpt')}"]
    assert main(argv) == 0
    after = metrics_of(trial)
    assert after["steps"] == STEPS and 0 < after["seconds"] <= before["seconds"]  # the fit's time, not the export's
    assert after["psnr_test"] == pytest.approx(before["psnr_test"], abs=1e-4)
    assert len(ply_arrays(os.path.join(trial, "save", "reconstructed.ply"))["x"]) == before["n_gaussians"]
