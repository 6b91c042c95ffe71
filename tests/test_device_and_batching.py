"""The GPU path: every render of an edit run happens on the module's device, after
Lightning has placed the module there; `renderer_type: auto`; the views of a refinement cycle are
edited in batches with one seed per view, giving the same targets as one view at a time.

On a CPU-only machine the device test checks the order (no render before the trainer has placed
the module) and that every tensor a render receives is on the trainer's device; only a GPU shows a
real CPU-vs-CUDA mismatch, so the same test runs with `--gpu 0` where CUDA is available, and the
gsplat tests run where gsplat and CUDA are.
"""
import logging
import os
from pathlib import Path

import pytest
import torch

from tiny_models_fixture import one_thread, tiny_models  # noqa: F401
from trial_helpers import ROOT, launch, metrics_of, write_scene_folder
from gs_regional.config import ConfigError
from gs_regional.guidance.instructpix2pix import InstructPix2Pix
from gs_regional.registry import register
from gs_regional.renderers import gsplat_rasterizer as gsplat_mod
from gs_regional.renderers.select import check_renderer_config, make_renderer, resolve_renderer_type
from gs_regional.renderers.torch_rasterizer import TorchRasterizer
from gs_regional.sim.scene import make_cameras, make_edit
from gs_regional.systems.in2n import In2N
from gs_regional.systems.regional_edit import RegionalEdit

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (CPU-only machine)")
GSPLAT = pytest.mark.skipif(
    not gsplat_mod.gsplat_available(), reason="needs a CUDA GPU and the gsplat package (pip install 'gs_regional[gsplat]')"
)

# ------------------------------------------------------------------ device


class Placement:
    """Where Lightning placed the system (recorded in on_fit_start, right after the strategy moved
    the module), and what the checking renderer saw."""

    device = None
    renders = 0
    violations = []

    @classmethod
    def reset(cls):
        cls.device, cls.renders, cls.violations = None, 0, []


@register("device-asserting-rasterizer")
class DeviceAssertingRasterizer(TorchRasterizer):
    """torch-rasterizer that records every call made before the module was placed, or with a
    tensor that is not on the placed device."""

    def _render(self, model, camera, background, override_color):
        Placement.renders += 1
        where = Placement.device
        if where is None:
            Placement.violations.append("render before the trainer placed the module")
        else:
            inputs = {name: getattr(model, name) for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")}
            inputs.update(world_to_camera=camera.world_to_camera, background=background, override_color=override_color)
            Placement.violations += [f"{k} on {t.device}, module on {where}" for k, t in inputs.items() if t is not None and t.device != where]
        return super()._render(model, camera, background, override_color)


def _record_placement(system):
    assert system.device == system.trainer.strategy.root_device
    Placement.device = system.trainer.strategy.root_device


@register("placement-recording-regional-edit")
class PlacementRecordingRegionalEdit(RegionalEdit):
    def on_fit_start(self):
        _record_placement(self)
        super().on_fit_start()


@register("placement-recording-in2n")
class PlacementRecordingIn2N(In2N):
    def on_fit_start(self):
        _record_placement(self)
        super().on_fit_start()


@pytest.mark.parametrize("gpu", [None, pytest.param(0, marks=CUDA)], ids=["cpu", "cuda"])
@pytest.mark.parametrize("system,config,small,steps", [
    ("placement-recording-regional-edit", "configs/demo.yaml", True,
     ["system.refine.cycles=2", "system.refine.iterations_per_cycle=3"]),
    ("placement-recording-in2n", "configs/in2n.yaml", "scene", ["system.max_steps=4", "system.edit_every=2"]),
])
def test_every_render_is_on_the_module_device_after_placement(tmp_path, system, config, small, steps, gpu):
    Placement.reset()
    trial = launch(tmp_path, "device", *steps, f"system_type={system}", "system.renderer_type=device-asserting-rasterizer",
                   config=config, small=small, args=() if gpu is None else ("--gpu", str(gpu)))
    assert Placement.renders > 20  # localization, source renders, training, outputs
    assert Placement.violations == [], Placement.violations[:5]
    assert metrics_of(trial)["seconds"]["source_renders"] >= 0  # the stage keeps its name


# ------------------------------------------------------------------ renderer_type: auto


def test_auto_renderer_picks_gsplat_only_on_cuda_with_gsplat(monkeypatch, caplog):
    monkeypatch.setattr(gsplat_mod, "_gsplat", object())  # "gsplat imports"
    assert resolve_renderer_type("auto", torch.device("cuda", 0))[0] == "gsplat-rasterizer"
    # A run on the CPU of a GPU machine (launch.py without --gpu) must not get CUDA-only kernels.
    assert resolve_renderer_type("auto", torch.device("cpu"))[0] == "torch-rasterizer"
    monkeypatch.setattr(gsplat_mod, "_gsplat", None)
    monkeypatch.setattr(gsplat_mod, "_GSPLAT_IMPORT_ERROR", ImportError("No module named 'gsplat'"))
    name, why = resolve_renderer_type("auto", torch.device("cuda", 0))
    assert name == "torch-rasterizer" and "No module named 'gsplat'" in why
    assert resolve_renderer_type("gsplat-rasterizer", torch.device("cpu"))[0] == "gsplat-rasterizer"  # explicit wins
    # The choice is logged, in one line, with the options the chosen renderer does not take.
    with caplog.at_level(logging.INFO, logger="gs_regional"):
        r = make_renderer("auto", {"strip_width": 4, "tile_size": 8}, torch.device("cpu"))
    assert isinstance(r, TorchRasterizer) and r.cfg.strip_width == 4 and r.cfg.tile_size == 8
    lines = [rec.getMessage() for rec in caplog.records if "renderer_type auto" in rec.getMessage()]
    assert lines == ["renderer_type auto: torch-rasterizer (the module runs on cpu)"]


def test_auto_renderer_options(monkeypatch):
    from gs_regional.renderers.select import renderer_options

    # gsplat takes the shared options; the torch rasterizer's own are left out (and named).
    kept, dropped = renderer_options("auto", {"strip_width": 4, "tile_size": 8}, "gsplat-rasterizer")
    assert kept == {"tile_size": 8} and dropped == ["strip_width"]
    # An explicit renderer gets every option (and rejects the ones it does not know).
    assert renderer_options("torch-rasterizer", {"strip_width": 4}, "torch-rasterizer") == ({"strip_width": 4}, [])
    with pytest.raises(ConfigError, match="system.renderer.strip_widht"):
        check_renderer_config("auto", {"strip_widht": 4})
    with pytest.raises(ConfigError, match="system.renderer.strip_width"):
        check_renderer_config("gsplat-rasterizer", {"strip_width": 4})
    check_renderer_config("auto", {"strip_width": 4, "eps2d": 0.3})


def test_configs_default_to_auto():
    from omegaconf import OmegaConf

    for name in ("edit.yaml", "reconstruct.yaml"):
        assert OmegaConf.load(ROOT / "configs" / name).system.renderer_type == "auto", name
    assert RegionalEdit.Config.renderer_type == "auto"


# ------------------------------------------------------------------ batched view edits


def cycle_state(trial):
    state = torch.load(os.path.join(trial, "ckpts", "last.ckpt"), map_location="cpu", weights_only=False)
    return state["gs_regional"]["extra"]


def test_batched_cycle_edits_equal_one_view_at_a_time_with_the_simulator(tmp_path):
    """Demo settings, stopped after the first refinement step: the cycle's targets are the same
    whether the editor takes one view per call or all of them."""
    runs = {}
    for batch in (1, 5):
        runs[batch] = cycle_state(launch(
            tmp_path, f"b{batch}", "trainer.max_steps=1", "system.refine.m=6",
            f"system.guidance.batch_size={batch}", "checkpoint.every_n_train_steps=1",
        ))
    # The m=6 neighbours of the first view (an addition's first cycle has no target for the first
    # view itself).
    assert runs[1]["cycle_views"] == runs[5]["cycle_views"] and len(runs[1]["cycle_views"]) == 6
    # The simulator draws each view's randomness from (its seed, its camera) only: exactly equal.
    assert torch.equal(runs[1]["cycle_targets"], runs[5]["cycle_targets"])


@register("seed-recording-ip2p")
class SeedRecordingIP2P(InstructPix2Pix):
    """The real IP2P, recording the seeds and views of each call its plugin method receives."""

    calls = []

    def _edit(self, images, cond_images, prompt, t_start, seeds, cameras):
        SeedRecordingIP2P.calls.append((t_start, list(seeds), images.shape[0]))
        return super()._edit(images, cond_images, prompt, t_start, seeds, cameras)


def test_batched_cycle_edits_equal_one_view_at_a_time_with_ip2p(tmp_path, tiny_models):  # noqa: F811
    """configs/edit.yaml with the tiny IP2P: batch_size 1 vs 3 gives the same targets (up to the
    UNet's batch-size-dependent float rounding) and each view gets its own seed, the one an
    unbatched edit uses: seed + 1000 (cycle + 1) + view."""
    scene, _ = write_scene_folder(tmp_path, n_cameras=8, size=40)
    common = [
        f"data.source={scene}", "data.test_every=8", f"system.geometry.ply={scene / 'point_cloud.ply'}",
        "system.prompt=give him a mustache", "system.seed=3",
        f"system.guidance.pretrained={tiny_models['ip2p']}", "system.guidance.num_inference_steps=4",
        # float32 on every device: `dtype: auto` is float16 on CUDA, whose rounding alone passes 1e-3.
        "system.guidance.dtype=float32",
        "system.guidance_type=seed-recording-ip2p", "system.ablation.initialize=false",
        "system.localization.max_views=4", "system.localization.gamma=0.5", "system.localization.mask_threshold=0.3",
        "system.refine.cycles=1", "system.refine.t_schedule=[750]", "system.refine.shape_t_schedule=[750]",
        "system.refine.m=5",
        "trainer.max_steps=1", "checkpoint.every_n_train_steps=1", "system.eval.turntable_frames=2",
        "trainer.enable_progress_bar=false",
    ]
    runs, calls = {}, {}
    n, tf32 = torch.get_num_threads(), torch.backends.cudnn.allow_tf32
    torch.set_num_threads(1)  # tiny models: see tiny_models_fixture.one_thread
    torch.backends.cudnn.allow_tf32 = False  # on CUDA, convolutions in full float32 (TF32 is torch's default)
    try:
        for batch in (1, 3):
            SeedRecordingIP2P.calls = []
            runs[batch] = cycle_state(launch(tmp_path / "out", f"b{batch}", *common, f"system.guidance.batch_size={batch}",
                                             config="configs/edit.yaml", small=False))
            calls[batch] = [c for c in SeedRecordingIP2P.calls if c[0] == 750]
    finally:
        torch.set_num_threads(n)
        torch.backends.cudnn.allow_tf32 = tf32
    views = runs[1]["cycle_views"]
    assert runs[3]["cycle_views"] == views and len(views) == 5
    # The m=5 neighbours of v_first: without depth initialization the shape may change, so the
    # first cycle has no target for the first view (an addition's first cycle).
    assert runs[1]["v_first"] not in views
    expected_seeds = [3 + 1000 * 1 + j for j in views]
    assert calls[1] == [(750, [s], 1) for s in expected_seeds]  # one view per UNet batch
    assert [s for c in calls[3] for s in c[1]] == expected_seeds and [c[2] for c in calls[3]] == [3, 2]
    # 1e-3 on [0, 1] images: batch-size-dependent float reductions in the UNet (see
    # tests/test_instructpix2pix.py); different noise per view would differ by far more.
    a, b = runs[1]["cycle_targets"], runs[3]["cycle_targets"]
    assert torch.allclose(a, b, atol=1e-3), float((a - b).abs().max())


# ------------------------------------------------------------------ gsplat on a GPU


@GSPLAT
def test_gsplat_and_torch_rasterizer_agree_on_the_reconstructed_face(tmp_path, shared):
    """Fit the face scene on the GPU, then render it with both rasterizers: >= 40 dB apart and
    gradients close."""
    from gs_regional.geometry.gaussian_model import GaussianModel
    from gs_regional.metrics.image import psnr
    from gs_regional.registry import find

    face = shared("face")
    trial = launch(tmp_path, "face", f"data.source={face}", "data.downscale=4", "trainer.enable_progress_bar=false",
                   config="configs/reconstruct.yaml", small=False, args=("--gpu", "0"))
    model = GaussianModel.from_ply(os.path.join(trial, "save", "reconstructed.ply")).cuda()
    dm = find("scene-datamodule")({"source": str(face), "downscale": 4, "load_images": False})
    dm.setup("fit")
    cams = [c.to("cuda") for c in dm.scene.cameras]
    torch_r, gsplat_r = find("torch-rasterizer")(), find("gsplat-rasterizer")()
    for cam in cams[:: max(1, len(cams) // 8)]:
        grads = []
        for r in (torch_r, gsplat_r):
            model.zero_grad(set_to_none=True)
            out = r.render(model, cam, background=torch.zeros(3, device="cuda"))
            (out["rgb"] * torch.linspace(0, 1, 3, device="cuda")).sum().backward()
            grads.append((out["rgb"].detach(), model.means.grad.clone(), model.sh_dc.grad.clone()))
        (img_t, gm_t, gc_t), (img_g, gm_g, gc_g) = grads
        assert psnr(img_g.clamp(0, 1)[None], img_t.clamp(0, 1)[None]) >= 40.0
        for a, b in ((gm_t, gm_g), (gc_t, gc_g)):
            cos = torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0)
            assert cos > 0.99, float(cos)


@GSPLAT
def test_edit_runs_with_auto_renderer_on_cuda(tmp_path, tiny_models, caplog):  # noqa: F811
    """configs/edit.yaml (renderer_type: auto) with --gpu 0 picks gsplat and runs end to end."""
    scene, _ = write_scene_folder(tmp_path, n_cameras=8, size=64)
    with caplog.at_level(logging.INFO, logger="gs_regional"):
        trial = launch(
            tmp_path / "out", "auto", f"data.source={scene}", "data.test_every=4",
            f"system.geometry.ply={scene / 'point_cloud.ply'}", "system.prompt=give him a mustache",
            f"system.guidance.pretrained={tiny_models['ip2p']}", "system.guidance.num_inference_steps=4",
            "system.guidance.batch_size=4", f"system.depth.pretrained={tiny_models['depth_anything']}",
            "system.localization.max_views=4", "system.localization.gamma=0.5", "system.localization.mask_threshold=0.3",
            "system.refine.cycles=2", "system.refine.t_schedule=[750,500]", "system.refine.iterations_per_cycle=5",
            "system.refine.m=3", "system.eval.turntable_frames=3", "trainer.enable_progress_bar=false",
            config="configs/edit.yaml", small=False, args=("--gpu", "0", "--verbose"),  # --verbose: info lines of every module
        )
    assert any("renderer_type auto: gsplat-rasterizer" in r.getMessage() for r in caplog.records)
    assert (Path(trial) / "save" / "edited.ply").exists()
