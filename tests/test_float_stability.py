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

from trial_helpers import metrics_of, trial_of
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
    within 1 dB, the same safe-stop outcome, Gaussian counts within 1 %. The footprint's bound is
    measured: the demo gave 25.95 dB; with its source renders perturbed by 1e-5, 25.79 (this test:
    FLOAT_NOISE_SEED 0, scalar kernels) and 25.47, 25.80, 25.81 (seeds 1-3, the machine's kernels),
    densification taking 106 to 144 Gaussians. At the 0.2 dB this test allowed before, seed 1 fails
    by 0.29 dB: it passed on one draw of the noise (docs/results.md)."""
    assert abs(a["mask_iou"] - b["mask_iou"]) <= 0.01
    assert abs(a["psnr_region_vs_true_edit"] - b["psnr_region_vs_true_edit"]) <= 1.0
    assert a["stopped"] == b["stopped"]
    assert abs(a["gaussians_after"] - b["gaussians_after"]) <= 0.01 * a["gaussians_after"]


# `make demo`'s figures (the README's demo row, on this project's 2-core CI machine): the noisy run
# below is held to them instead of to a plain run of its own (a demo run less in the suite). A
# change of the method that moves the demo changes these and the README's row together.
DEMO_FIGURES = {"mask_iou": 0.8990, "psnr_region_vs_true_edit": 25.95, "stopped": None, "gaussians_after": 9871}


# One run carries both kinds of float noise (each used to be a demo run of its own, and the suite
# has to fit in CI's time): source renders perturbed by up to 1e-5, under PyTorch's scalar kernels.
# Each alone is a subset of this run's noise; to tell which one moves a figure, drop the perturbation
# from PERTURBED_DEMO or the environment variable. Another draw of the noise:
# FLOAT_NOISE_SEED=N python -m pytest -s tests/test_float_stability.py (prints the figures).
PERTURBED_DEMO = """
import os, sys, torch
from gs_regional.launch import main
from gs_regional.systems.edit_base import EditSystemBase
fit_start = EditSystemBase.on_fit_start
def perturbed(self):
    fit_start(self)
    gen = torch.Generator().manual_seed(int(os.environ.get("FLOAT_NOISE_SEED", "0")))
    self._source_renders = [(r + (torch.rand(r.shape, generator=gen) * 2 - 1) * 1e-5).clamp(0, 1)
                            for r in self._source_renders]
EditSystemBase.on_fit_start = perturbed
sys.exit(main(sys.argv[1:]))
"""


def test_perturbed_source_renders_under_other_cpu_kernels_give_the_same_edit(tmp_path):
    env = {**os.environ, "ATEN_CPU_CAPABILITY": "default",  # PyTorch's scalar kernels
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.run([sys.executable, "-c", PERTURBED_DEMO, *DEMO, f"exp_root_dir={tmp_path}", "name=noisy"],
                          env=env, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    noisy = key_metrics(metrics_of(trial_of(tmp_path, "noisy")))
    print(f"make demo {DEMO_FIGURES}\nperturbed renders, scalar kernels {noisy}")
    assert_same_edit(DEMO_FIGURES, noisy)
