"""The demo does not depend on float noise: the same edit comes out of source renders perturbed by
±1e-5 under another set of CPU kernels (PyTorch's scalar kernels instead of the AVX2/AVX-512 ones:
another float reduction order on the same machine, as another CPU model gives). The simulators key
each view's randomness on its pose in a way that a last-bit difference in the pose leaves alone."""
from trial_helpers import launch_process, metrics_of, trial_of
from gs_regional.sim.scene import make_cameras
from gs_regional.sim.truth import camera_seed

# The demo as `make demo` runs it, not the small demo: this test holds it to make demo's figures,
# so it stays the suite's longest run. Two turntable frames and no periodic checkpoints (neither
# enters the metrics).
DEMO = ["system.eval.turntable_frames=2", "checkpoint.every_n_train_steps=1000000", "trainer.enable_progress_bar=false"]


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
    within 1 dB, the same safe-stop outcome, Gaussian counts within 1 %. Draws of the float noise
    (FLOAT_NOISE_SEED) move the footprint's PSNR by up to about half a dB and the densified count
    by a few dozen Gaussians: the bounds hold every draw, not one."""
    assert abs(a["mask_iou"] - b["mask_iou"]) <= 0.01
    assert abs(a["psnr_region_vs_true_edit"] - b["psnr_region_vs_true_edit"]) <= 1.0
    assert a["stopped"] == b["stopped"]
    assert abs(a["gaussians_after"] - b["gaussians_after"]) <= 0.01 * a["gaussians_after"]


# `make demo`'s figures (the README's demo row, on this project's 2-core CI machine): the noisy run
# below is held to them instead of to a plain run of its own (a demo run less in the suite). A
# change of the method that moves the demo changes these and the README's row together.
DEMO_FIGURES = {"mask_iou": 0.8745, "psnr_region_vs_true_edit": 26.69, "stopped": None, "gaussians_after": 9900}


# One run carries both kinds of float noise (one demo run instead of two, for the suite's time):
# source renders perturbed by up to 1e-5, under PyTorch's scalar kernels.
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
    launch_process(tmp_path, "noisy", *DEMO, small=False, program=PERTURBED_DEMO, timeout=900,
                   env={"ATEN_CPU_CAPABILITY": "default"})  # PyTorch's scalar kernels
    noisy = key_metrics(metrics_of(trial_of(tmp_path, "noisy")))
    print(f"make demo {DEMO_FIGURES}\nperturbed renders, scalar kernels {noisy}")
    assert_same_edit(DEMO_FIGURES, noisy)
