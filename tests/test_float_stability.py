"""The demo does not depend on float noise (issue "green on every machine"): the same edit comes
out of source renders perturbed by ±1e-5 under another set of CPU kernels (PyTorch's scalar
kernels instead of the AVX2/AVX-512 ones: another float reduction order on the same machine, as
another CPU model gives). Its figures used to move by 0.04 mask IoU between two CPU models: the
simulators keyed each view's randomness on a hash of its pose rounded to 1e-5, and a last-bit
difference in a pose flipped a rounded digit now and then, redrawing that view's noise."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

from trial_helpers import metrics_of, trial_of
from gs_regional.launch import main
from gs_regional.sim.scene import make_cameras
from gs_regional.sim.truth import camera_seed

ROOT = Path(__file__).resolve().parents[1]
# The demo as `make demo` runs it; two turntable frames and no periodic checkpoints (neither
# enters the metrics).
DEMO = ["--config", str(ROOT / "configs/demo.yaml"), "--train", "system.eval.turntable_frames=2",
        "checkpoint.every_n_train_steps=1000000", "trainer.enable_progress_bar=false"]


def test_a_views_seed_ignores_float_noise_in_its_pose():
    cam = make_cameras(8, 64, 64)[0][3]
    for eps in (1e-7, -1e-7, 3e-6):
        moved = type(cam)(cam.world_to_camera * (1 + eps), fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy,
                          width=cam.width, height=cam.height, image_name=cam.image_name)
        assert camera_seed(moved) == camera_seed(cam)
    assert camera_seed(cam.scaled(0.5)) == camera_seed(cam)  # the same view at another resolution
    assert len({camera_seed(c) for c in make_cameras(8, 64, 64)[0]}) == 8  # distinct views, distinct draws


def key_metrics(m):
    return {k: m.get(k) for k in ("mask_iou", "psnr_region_vs_true_edit", "stopped", "gaussians_after", "edit_coverage")}


def assert_same_edit(a, b):
    """The tolerances a user can rely on across machines: mask IoU within 0.01, footprint PSNR
    within 0.2 dB, the same safe-stop outcome, Gaussian counts within 1 %."""
    assert abs(a["mask_iou"] - b["mask_iou"]) <= 0.01
    assert abs(a["psnr_region_vs_true_edit"] - b["psnr_region_vs_true_edit"]) <= 0.2
    assert a["stopped"] == b["stopped"]
    assert abs(a["gaussians_after"] - b["gaussians_after"]) <= 0.01 * a["gaussians_after"]


@pytest.fixture(scope="module")
def demo_runs(tmp_path_factory):
    out = tmp_path_factory.mktemp("float_noise")
    assert main([*DEMO, f"exp_root_dir={out}", "name=plain"]) == 0
    return out


# One run carries both kinds of float noise (each used to be a demo run of its own, and the suite
# has to fit in CI's time): source renders perturbed by up to 1e-5, under PyTorch's scalar kernels.
# Each alone is a subset of this run's noise; to tell which one moves a figure, drop the perturbation
# from PERTURBED_DEMO or the environment variable.
PERTURBED_DEMO = """
import sys, torch
from gs_regional.launch import main
from gs_regional.systems.edit_base import EditSystemBase
fit_start = EditSystemBase.on_fit_start
def perturbed(self):
    fit_start(self)
    gen = torch.Generator().manual_seed(0)
    self._source_renders = [(r + (torch.rand(r.shape, generator=gen) * 2 - 1) * 1e-5).clamp(0, 1)
                            for r in self._source_renders]
EditSystemBase.on_fit_start = perturbed
sys.exit(main(sys.argv[1:]))
"""


def test_perturbed_source_renders_under_other_cpu_kernels_give_the_same_edit(demo_runs):
    env = {**os.environ, "ATEN_CPU_CAPABILITY": "default",  # PyTorch's scalar kernels
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.run([sys.executable, "-c", PERTURBED_DEMO, *DEMO, f"exp_root_dir={demo_runs}", "name=noisy"],
                          env=env, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    a = key_metrics(metrics_of(trial_of(demo_runs, "plain")))
    b = key_metrics(metrics_of(trial_of(demo_runs, "noisy")))
    print(f"plain {a}\nperturbed renders, scalar kernels {b}")
    assert_same_edit(a, b)
