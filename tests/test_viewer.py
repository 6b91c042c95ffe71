"""The web viewer (`launch.py --view TRIAL_DIR`): what it reads from a trial, its command line,
and the page itself in headless Chromium (skipped where viser, playwright or Chromium is absent)."""
import io
import json
import socket
import sys
import time
from contextlib import redirect_stderr
from pathlib import Path

import numpy as np
import pytest
import torch

from gs_regional.launch import view
from gs_regional.launch.summary import RunInfo, format_summary
from gs_regional.sim.scene import make_edit
from trial_helpers import write_scene_folder
from web_tools import browser

SYNTHETIC = {"edit": "recolor", "seed": 0, "n_cameras": 8, "width": 48, "height": 48, "n_object": 1500, "n_background": 1000}
PROMPT = "make his head red"


def write_trial(root: Path, data_type="synthetic-scene", data=None, system=None, edited=None, mask_rows=None,
                metrics=None) -> Path:
    """A finished edit trial as launch.py leaves it: configs/parsed.yaml, save/edited.ply,
    save/edit_mask.npz and save/metrics.json."""
    from omegaconf import OmegaConf

    trial = root / "outputs" / "view" / "trial@0"
    (trial / "configs").mkdir(parents=True)
    (trial / "save").mkdir()
    cfg = {"name": "view", "data_type": data_type, "data": data or SYNTHETIC, "system_type": "regional-edit",
           "system": system or {"prompt": PROMPT}}
    (trial / "configs" / "parsed.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(cfg)))
    edited.save_ply(str(trial / "save" / "edited.ply"))
    if mask_rows is not None:
        np.savez_compressed(trial / "save" / "edit_mask.npz", **mask_rows)
    if metrics is not None:
        (trial / "save" / "metrics.json").write_text(json.dumps(metrics))
    return trial


@pytest.fixture(scope="module")
def recolor_trial(tmp_path_factory):
    """The synthetic recolour edit's true answer written as a trial: the head (the edit's region)
    turned red; the mask selects the head."""
    truth = make_edit("recolor", **{k: SYNTHETIC[k] for k in ("seed", "n_object", "n_background")})
    n = len(truth.edited)
    rows = {"mask": truth.new_region.numpy(), "generation": np.zeros(n, dtype=np.int64),
            "source_index": np.arange(n, dtype=np.int64)}
    metrics = {"prompt": PROMPT, "gaussians_before": n, "gaussians_after": n, "mask_iou": 1.0, "psnr_vs_true_edit": 41.5}
    return write_trial(tmp_path_factory.mktemp("viewer"), edited=truth.edited, mask_rows=rows, metrics=metrics), truth


# ----- what the viewer reads -------------------------------------------------------------------
def test_load_trial_rebuilds_the_synthetic_source_and_reads_the_mask(recolor_trial):
    trial_dir, truth = recolor_trial
    trial = view.load_trial(trial_dir)
    assert trial.edited.num_gaussians == len(truth.edited) and trial.source.num_gaussians == len(truth.source)
    np.testing.assert_array_equal(trial.source.means, truth.source.means.detach().numpy())  # rebuilt, not the edit
    assert not np.array_equal(trial.source.sh_dc, trial.edited.sh_dc)
    np.testing.assert_array_equal(trial.edited_mask, truth.new_region.numpy())
    np.testing.assert_array_equal(trial.source_mask, truth.region.numpy())
    assert len(trial.cameras) == SYNTHETIC["n_cameras"] and trial.test_indices
    assert trial.prompt == PROMPT and trial.metrics["mask_iou"] == 1.0
    assert "edit_mask.npz" in trial.mask_note


def test_load_trial_of_a_scene_folder_reads_the_source_ply(tmp_path):
    """A user's scene (configs/edit.yaml): the source is system.geometry.ply, the cameras come from
    the scene folder, and a trial without a saved mask says so instead of failing."""
    folder, ply = write_scene_folder(tmp_path, n_cameras=6, size=32)
    truth = make_edit("add")
    trial_dir = write_trial(tmp_path, data_type="scene-datamodule", data={"source": str(folder)},
                            system={"prompt": "give him a mustache", "geometry": {"ply": str(ply)}}, edited=truth.edited)
    trial = view.load_trial(trial_dir)
    assert trial.source_label == str(ply) and trial.source.num_gaussians == len(truth.source)
    assert trial.edited.num_gaussians == len(truth.edited) > len(truth.source)
    assert len(trial.cameras) == 6
    assert trial.edited_mask is None and "no edit mask" in trial.mask_note
    assert trial.prompt == "give him a mustache" and trial.metrics == {}

    # A trial from before save/edit_mask.npz: the rows come from its last checkpoint.
    added = truth.edited.generation > 0
    (trial_dir / "ckpts").mkdir()
    torch.save({"state_dict": {"geometry.mask": torch.zeros(len(truth.edited), dtype=torch.bool),
                               "geometry.generation": truth.edited.generation.clone(),
                               "geometry.source_index": torch.where(added, -1, torch.arange(len(truth.edited)))}},
               trial_dir / "ckpts" / "last.ckpt")
    trial = view.load_trial(trial_dir)
    np.testing.assert_array_equal(trial.edited_mask, added.numpy())
    assert not trial.source_mask.any() and "ckpts/last.ckpt" in trial.mask_note


def test_not_a_trial_is_one_line_exit_2(tmp_path):
    pytest.importorskip("viser", reason="the 'viewer' extra (viser) is not installed")
    err = io.StringIO()
    with redirect_stderr(err):
        code = view.main(["--view", str(tmp_path / "nowhere")])
    assert code == 2 and err.getvalue().strip() == f"error: trial dir not found: {tmp_path / 'nowhere'}"


def test_missing_viewer_extra_is_one_line_exit_2(monkeypatch, tmp_path):
    from gs_regional.launch import main

    monkeypatch.setitem(sys.modules, "viser", None)  # `import viser` raises ImportError
    err = io.StringIO()
    with redirect_stderr(err):
        code = main(["--view", str(tmp_path), "--port", "8123"])
    lines = err.getvalue().strip().splitlines()
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith("error: the viewer needs the 'viewer' extra (pip install 'gs_regional[viewer]')")


def test_display_arrays_and_subsampling():
    truth = make_edit("recolor", n_object=600, n_background=500)
    g = truth.edited.to_ply_gaussians()
    mask = truth.new_region.numpy()
    full = view.to_splats(g, mask, cap=0)
    assert full.shown == full.total == g.num_gaussians
    # covariance = R diag(exp(log_scale))^2 R^T: symmetric, with the squared scales as eigenvalues
    # float32 products: symmetric up to rounding (relative 1e-5 holds for any BLAS)
    np.testing.assert_allclose(full.covariances, full.covariances.transpose(0, 2, 1), rtol=1e-5, atol=1e-9)
    eig = np.sort(np.linalg.eigvalsh(full.covariances.astype(np.float64)), axis=1)
    np.testing.assert_allclose(eig, np.sort(np.exp(2 * g.log_scales.astype(np.float64)), axis=1), rtol=1e-4, atol=1e-10)
    part = view.to_splats(g, mask, cap=300)
    assert part.shown == 300 and part.total == g.num_gaussians and part.mask.shape == (300,)
    rows = view.subsample_rows(g.num_gaussians, 300)
    np.testing.assert_array_equal(part.centers, g.means[rows])
    np.testing.assert_array_equal(part.mask, mask[rows])
    highlighted = part.highlighted_rgbs()
    assert np.array_equal(highlighted[~part.mask], part.rgbs[~part.mask])
    assert not np.allclose(highlighted[part.mask], part.rgbs[part.mask])


def test_summary_gives_the_viewer_command(recolor_trial):
    trial_dir, _ = recolor_trial
    info = RunInfo(trial=trial_dir, mode="train", config_path="x.yaml", system_type="regional-edit",
                   data_type="synthetic-scene", resume=None, steps=1, setup_seconds=0.0, wall_seconds=1.0,
                   started_at=time.time())
    lines = format_summary(info).splitlines()
    assert any(line.split() == ["viewer", "python", "launch.py", "--view", str(trial_dir)] for line in lines)
    assert lines[-1] == f"results: {trial_dir}"


# ----- the page in a real browser ---------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _screenshot(page) -> np.ndarray:
    import imageio.v3 as iio

    return iio.imread(page.screenshot(), extension=".png")[..., :3].astype(np.int16)


def _view_area(img: np.ndarray) -> np.ndarray:
    """The 3D view left of the side panel."""
    return img[:, : img.shape[1] * 6 // 10]


def _scene_pixels(img: np.ndarray) -> int:
    """Pixels of the 3D view unlike the empty background (the lower left corner)."""
    return int((np.abs(_view_area(img) - img[-1, 0]).max(-1) > 40).sum())


def _next_frame(page, previous: np.ndarray, seconds: float = 10.0) -> np.ndarray:
    """The first screenshot whose 3D view differs from `previous` (the page updates
    asynchronously), or the last one taken after `seconds`."""
    deadline = time.monotonic() + seconds
    while True:
        img = _screenshot(page)
        if (np.abs(_view_area(img) - _view_area(previous)).max(-1) > 40).sum() > 50 or time.monotonic() > deadline:
            return img
        page.wait_for_timeout(200)


def test_page_renders_the_splats_and_toggles_before_after(recolor_trial):
    pytest.importorskip("viser", reason="the 'viewer' extra (viser) is not installed")
    trial_dir, _ = recolor_trial
    viewer = view.serve(view.load_trial(trial_dir), port=_free_port())
    try:
        with browser() as chromium:
            page = chromium.new_page(viewport={"width": 960, "height": 400})
            page.goto(viewer.url)
            # Wait for the splats: most of the 3D view covered (camera frustums alone are thin lines).
            deadline, edited = time.monotonic() + 45, None  # software WebGL on a busy CPU is slow
            while time.monotonic() < deadline:
                page.wait_for_timeout(500)
                edited = _screenshot(page)
                if _scene_pixels(edited) > 0.2 * edited.shape[0] * edited.shape[1] * 0.6:
                    break
            assert _scene_pixels(edited) > 0.2 * edited.shape[0] * edited.shape[1] * 0.6, "the splats never rendered"
            page.wait_for_timeout(500)  # the depth sort may still move a few splats
            edited = _screenshot(page)

            page.get_by_role("button", name="source", exact=True).click()
            page.get_by_text("Showing: source").wait_for()
            source = _next_frame(page, edited)

            page.get_by_text("Highlight edit mask").click()  # the mask is the head: tinted magenta
            highlighted = _next_frame(page, source)

            # Fewer Gaussians on demand (for browsers without a GPU): the page says it subsampled.
            shown = page.get_by_label("Gaussians shown")
            shown.fill("1000")
            shown.press("Enter")
            page.get_by_text("shows a random 1,000 of its").first.wait_for(timeout=10_000)
            assert all(s.shown == 1000 for s in viewer.splats.values())
    finally:
        viewer.stop()
    edited, source, highlighted = _view_area(edited), _view_area(source), _view_area(highlighted)
    changed = np.abs(edited - source).max(-1) > 40
    # The recolour turns the head red: a compact blob of pixels changes, the rest stays.
    assert changed.sum() > 200, f"before/after toggle changed only {changed.sum()} pixels"
    assert changed.mean() < 0.25
    red = (edited[..., 0] - edited[..., 1:].max(-1))[changed]
    assert np.median(red) > 60, "the edited scene's changed pixels are not the red head"
    tinted = np.abs(highlighted - source).max(-1) > 40
    assert (tinted & changed).sum() > 0.5 * changed.sum(), "the highlighted mask is not where the edit is"
    assert (tinted & ~changed).sum() < 0.5 * changed.sum()
