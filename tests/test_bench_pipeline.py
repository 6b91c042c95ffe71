"""scripts/bench_pipeline.py (gs_regional/bench/pipeline.py) in its tiny mode: the whole regional edit and the in2n baseline through
launch.py with InstructPix2Pix and Depth Anything loaded by from_pretrained from (tiny, random)
folders, on the CPU, with a small budget; and the JSON it writes."""
import json
import os
import subprocess
import sys

import pytest
import torch

from gs_regional.bench.pipeline import resample_gaussians
from gs_regional.sim.scene import make_scene

from trial_helpers import ROOT

# The synthetic scene resampled to 4000 Gaussians; 4 localization views, 2 cycles of 4 steps
# editing the frontal view and its 2 nearest, 4 DDIM steps (the same start timesteps whether or not
# the random-weight depth finds a change of shape).
BUDGET = ["--gaussians", "4000", "--max-views", "4", "--cycles", "2", "--t-schedule", "750", "500",
          "--shape-t-schedule", "750", "500", "--iterations", "4", "--m", "2",
          "--ddim-steps", "4", "--in2n-steps", "6", "--edit-every", "3", "--turntable-frames", "2"]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bench_pipeline")
    cmd = [sys.executable, str(ROOT / "scripts" / "bench_pipeline.py"), "--models", "tiny", "--out", str(tmp / "out"),
           "--models-dir", str(tmp / "priors"), "--device", "cpu", *BUDGET]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    with open(tmp / "out" / "bench_pipeline.json") as f:
        return json.load(f), done.stdout


def test_tiny_pipeline_report(report):
    rep, stdout = report
    assert rep["models"] == "tiny" and rep["dtype"] == "float32"
    assert rep["device"]["device"] == "cpu" and rep["device"]["name"]
    assert rep["scene"]["source"] == "synthetic" and rep["scene"]["sh_degree"] == 3
    assert (rep["scene"]["gaussians_source"], rep["scene"]["gaussians"]) == (9765, 4000)
    assert (rep["scene"]["width"], rep["scene"]["height"]) == (64, 64)
    load = rep["load"]
    assert load["unet_output_shape"] == [1, 4, 8, 8] and load["disparity_shape"] == [1, 64, 64]
    assert all(s > 0 for s in load["seconds"].values())
    regional, in2n = rep["runs"]["regional-edit"], rep["runs"]["in2n"]
    # The per-stage names of the runs' metrics.json.
    assert {"localize", "initialize", "refine_edit", "refine_train", "output"} <= set(regional["seconds"])
    assert {"edit", "train", "output"} <= set(in2n["seconds"])
    for run in (regional, in2n):
        assert run["wall_seconds"] >= run["seconds_total"] > 0
        assert run["peak_rss_bytes"] > 100 * 2**20
        assert run["cuda_peak_bytes"] is None  # CPU run
        assert os.path.isfile(os.path.join(run["trial"], "save", "edited.ply"))
        # The profile: start-up (what the stages do not time), the UNet's seconds and share of the
        # wall time, and the views per UNet call batch_size auto chose (1 on a CPU) at 64x64.
        assert 0 < run["startup_seconds"] < run["wall_seconds"]
        # ... split by phase (launch's clock in metrics.json; "process" the rest), adding up to it.
        parts = run["startup_parts"]
        assert list(parts) == ["plugins", "scene", "system", "trainer", "lightning", "unstaged", "process"]
        assert all(v >= 0 for v in parts.values()) and parts["system"] > 0
        assert sum(parts.values()) == pytest.approx(run["startup_seconds"], abs=0.01)
        assert 0 < run["unet_seconds"] < run["wall_seconds"] and 0 < run["unet_share"] <= 1
        assert run["unet_share"] == pytest.approx(run["unet_seconds"] / run["wall_seconds"], abs=1e-3)
        assert run["batch_size"] == {"64x64": 1}
        assert run["prior_wait_seconds"] >= 0
    # UNet evaluations of this schedule, counted by the real guidance: localization 4 views x 2
    # branches; one full edit of 4 DDIM steps x 3 branches (the random-weight editor's first full
    # edit changes nothing beyond its noise, but its view shows the selection as well as any, so
    # no other view is edited); cycle 1 (t <= 750: 3 of the DDIM timesteps 751/501/251/1) on the
    # 2 views besides the first (the depth shows no trusted change, so the shape may change:
    # an addition's first cycle), cycle 2 (t <= 500: 2 steps) on 3.
    assert regional["unet_evals"] == 4 * 2 + 4 * 3 + 2 * 3 * 3 + 3 * 2 * 3
    # VAE: 4 localization encodes, 1 for the full edit's condition, 2 per partial edit (render + condition).
    assert (regional["vae_encodes"], regional["vae_decodes"]) == (4 + 1 + 2 * 5, 1 + 5)
    # in2n edits at steps 0 and 3 from t in [700, 980): 3 or 4 DDIM steps of 3 branches each.
    assert in2n["vae_decodes"] == 2 and in2n["unet_evals"] in (18, 21, 24)
    # Random-weight Depth Anything explains nothing of the scene's depth: its calibration is rejected
    # with a warning and nothing is added from depth (4 steps do not densify either).
    with open(os.path.join(regional["trial"], "save", "metrics.json")) as f:
        m = json.load(f)
    assert regional["gaussians_after"] >= regional["gaussians_before"] == rep["scene"]["gaussians"]
    assert m["count_added_init"] > 0 or any("depth calibration rejected" in w for w in m["warnings"])
    assert "| regional-edit |" in stdout and "| in2n |" in stdout and "localize s" in stdout
    assert "UNet share" in stdout and "1 at 64x64" in stdout


@pytest.mark.parametrize("n", [3000, 25000])
def test_resample_gaussians(n):
    model, _, _ = make_scene(seed=0)
    out = resample_gaussians(model, n, seed=0)
    assert out.num_gaussians == n
    src_means = model.means.detach()
    if n < model.num_gaussians:  # a subset of the source rows
        d = torch.cdist(out.means.detach(), src_means, compute_mode="donot_use_mm_for_euclid_dist").min(1).values
        assert float(d.max()) == 0.0
    else:  # every source Gaussian kept, copies placed within a few of their own sigmas
        assert torch.equal(out.means.detach()[: model.num_gaussians], src_means)
        shrink = 0.5 * torch.log(torch.tensor(model.num_gaussians / n))
        torch.testing.assert_close(out.log_scales.detach()[: model.num_gaussians], model.log_scales.detach() + shrink)
        extra = out.means.detach()[model.num_gaussians :]
        assert float(torch.cdist(extra, src_means).min(1).values.max()) < 6 * float(model.scales.detach().max())
