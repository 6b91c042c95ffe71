"""The studio (`launch.py --studio`) and the notebook steps under it (gs_regional.localize,
Localized.select, gs_regional.edit(selection=...)): the evidence a localization saves, the
selection re-made from it without the editor, the studio's edit against the command line's, and
the page itself in headless Chromium (skipped where viser, playwright or Chromium is absent)."""
import io
import sys
import time
from contextlib import redirect_stderr

import numpy as np
import pytest
import torch

import gs_regional as gr
from trial_helpers import DEMO, launch, metrics_of, small_demo
from web_tools import browser

PROMPT = "give him a mustache"


def small_overrides(name):
    """tests/data/small_demo.yaml as the API's `overrides` dict, with the run's name."""
    return {**dict(item.split("=", 1) for item in small_demo()), "name": name}


class UnetCount:
    """Counts the simulated editor's relevance and edit calls in this process (the UNet's work)."""

    def __init__(self, monkeypatch):
        from gs_regional.sim.editor import SimulatedEditor

        self.calls = 0
        for name in ("_relevance", "_edit"):
            real = getattr(SimulatedEditor, name)

            def counted(*args, _real=real, **kwargs):
                self.calls += 1
                return _real(*args, **kwargs)

            monkeypatch.setattr(SimulatedEditor, name, counted)


@pytest.fixture(scope="module")
def localized(tmp_path_factory):
    out = tmp_path_factory.mktemp("studio_localize")
    return out, gr.localize(config=DEMO, out=out, overrides=small_overrides("loc"))


# ----- the notebook steps -------------------------------------------------------------------------
def test_localize_keeps_the_evidence_and_select_remakes_the_selection(localized):
    out, loc = localized
    assert isinstance(loc, gr.Localized) and loc.trial == out / "loc" / "add"
    n = loc.source.num_gaussians
    assert n == 9765 and loc.selection.dtype == torch.bool and len(loc.selection) == n
    assert loc.metrics["stopped"] == "stop_after=localize" and loc.metrics["unet_evals"] > 0
    # The evidence: the lift's scores, its neighbourhood rows and the views' relevance masks.
    assert loc.scores.dtype == torch.float32 and loc.scores.shape == (n,)
    assert loc.neighbourhood.shape == (n, 16) and bool((loc.neighbourhood[:, 0] == torch.arange(n)).all())
    assert loc.threshold == 0.5 and len(loc.masks) == 6
    assert all(m.dtype == torch.bool and m.shape == (32, 32) and bool(m.any()) for m in loc.masks.values())
    with np.load(loc.trial / "save" / "localization.npz") as f:
        assert f["scores"].dtype == np.float32 and f["selected"].dtype == bool and f["neighbourhood"].dtype == np.int32
    # At the lift's own threshold the selection is the run's, exactly; other thresholds nest.
    assert 0 < loc.count < n
    assert torch.equal(loc.select(), loc.selection) and torch.equal(loc.select(loc.threshold), loc.selection)
    low, high = loc.select(0.3), loc.select(0.7)
    assert int(low.sum()) > loc.count > int(high.sum()) > 0
    assert bool((high <= loc.selection).all()) and bool((loc.selection <= low).all())
    # The same run's mask.ply holds exactly the selected Gaussians.
    assert gr.GaussianModel.from_ply(str(loc.trial / "save" / "mask.ply")).num_gaussians == loc.count


def test_select_costs_no_editor_call(localized, monkeypatch):
    _, loc = localized
    count = UnetCount(monkeypatch)
    counts = {t: int(loc.select(t).sum()) for t in (0.2, 0.4, 0.6, 0.8)}
    assert count.calls == 0
    assert sorted(counts.values(), reverse=True) == list(counts.values()) and len(set(counts.values())) == 4


def test_localized_edit_edits_a_selection_of_its_evidence(localized):
    _, loc = localized
    chosen = loc.select(0.6)
    result = loc.edit(chosen)
    assert isinstance(result, gr.EditResult) and result.trial.parent == loc.trial.parent
    assert torch.equal(result.selection, chosen) and result.metrics["gaussians_after"] == result.model.num_gaussians
    assert "stopped" not in result.metrics and result.metrics["unet_evals"] > loc.metrics["unet_evals"]


def test_a_given_selection_is_saved_without_scores(localized):
    out, loc = localized
    from gs_regional.sim.scene import make_edit

    region = make_edit("add").region.numpy()
    given = gr.localize(config=DEMO, out=out, overrides={**small_overrides("loc-given"),
                                                         "system.selection_file": str(gr.api._write_selection(region, out))})
    assert given.scores is None and given.masks == {} and given.metrics["unet_evals"] == 0
    assert torch.equal(given.selection, torch.as_tensor(region)) and torch.equal(given.select(0.1), given.selection)


# ----- the studio without a browser ------------------------------------------------------------------
def _session(out, name, *overrides):
    from gs_regional.studio.session import StudioSession

    return StudioSession.open(DEMO, [*small_demo(), f"exp_root_dir={out}", f"name={name}", *overrides])


def test_the_studios_edit_is_the_command_lines(tmp_path):
    """Select region, a threshold moved, then Edit: the trial records the selection file, and
    launch.py on the same config, seed and selection file gives the same edit."""
    from omegaconf import OmegaConf

    s = _session(tmp_path, "studio")
    assert s.load_error is None and s.n == 9765 and s.prompt == PROMPT
    assert s.select_region(PROMPT) is None and s.wait(120)
    assert s.message == "" and s.count == s.localized.count > 0
    assert s.set_threshold(1.0) is None and s.count == 0  # no score exceeds 1
    assert "the selection is empty" in s.start_edit(PROMPT) and not s.busy
    assert s.set_threshold(0.4) is None and s.count == int(s.localized.select(0.4).sum()) > s.localized.count
    assert s.start_edit(PROMPT) is None and s.wait(300), s.message
    assert s.progress.text.startswith("Done"), s.message
    trial = s.edit_trial
    selection_file = OmegaConf.load(trial / "configs" / "parsed.yaml").system.selection_file
    assert np.array_equal(np.load(selection_file), s.localized.select(0.4).numpy())
    cli = launch(tmp_path, "cli", f"system.selection_file={selection_file}")
    ours, theirs = metrics_of(trial), metrics_of(cli)
    assert ours["gaussians_after"] == theirs["gaussians_after"] and ours["unet_evals"] == theirs["unet_evals"]
    psnrs = [k for k in theirs if k.startswith("psnr") and isinstance(theirs[k], float)]
    assert psnrs
    for key in psnrs:  # one process, one machine: the same arithmetic; 0.05 dB leaves room for threads
        assert abs(ours[key] - theirs[key]) <= 0.05, key
    for suffix in (".ply", ".splat", ".compressed.ply"):
        assert s.download(suffix).is_file()
    # A normal trial: the viewer reads it, and --export works on its checkpoint.
    from gs_regional.launch import main
    from gs_regional.launch.view import load_trial

    shown = load_trial(trial)
    assert shown.edited.num_gaussians == ours["gaussians_after"] and int(shown.source_mask.sum()) == s.count
    assert main(["--config", str(trial / "configs" / "parsed.yaml"), "--export", f"resume={trial / 'ckpts' / 'last.ckpt'}"]) == 0
    assert len(list((trial / "save").glob("export_step*[0-9].ply"))) == 1


def test_bad_input_is_a_message_not_a_traceback(tmp_path, monkeypatch):
    from gs_regional.config import ConfigError
    from gs_regional.studio import session

    s = _session(tmp_path, "bad")
    # A run that fails: its one line on the page, and the studio takes the next job.
    def fails(**kwargs):
        raise ConfigError("system.localization.timestep must be in [0, 999], got 1200\n(more detail)")

    monkeypatch.setattr(session, "localize", fails)
    assert s.select_region(PROMPT) is None and s.wait(60)
    assert s.message == "Select region failed: system.localization.timestep must be in [0, 999], got 1200"
    assert not s.busy and s.localized is None
    monkeypatch.undo()
    assert "type an instruction first" in s.select_region("   ")
    assert "press Select region first" in s.start_edit(PROMPT)
    assert "no edit is running" in s.stop()
    with pytest.raises(FileNotFoundError, match="no edit yet"):
        s.download(".splat")
    # A scene that fails to load: the session (and the page) say so, and refuse the jobs.
    broken = _session(tmp_path, "broken", f"system.geometry.ply={tmp_path / 'missing.ply'}")
    assert broken.source is None and "the scene could not be loaded" in broken.load_error
    assert "missing.ply" in broken.load_error and len(broken.load_error.splitlines()) == 1
    assert "the scene could not be loaded" in broken.select_region(PROMPT)
    pytest.importorskip("viser", reason="the 'viewer' extra (viser) is not installed")
    from gs_regional.studio.page import serve

    studio = serve(broken, port=_free_port())  # the page comes up and says it
    try:
        assert "the scene could not be loaded" in studio.page.message.content
        assert studio.page.select_button.disabled and studio.page.edit_button.disabled
    finally:
        studio.stop()


def test_missing_viewer_extra_and_bad_config_are_one_line_exit_2(monkeypatch, tmp_path):
    from gs_regional.studio import build_parser, main

    assert build_parser().parse_args(["--studio"]).host == "127.0.0.1"  # this machine only unless --host
    err = io.StringIO()
    with redirect_stderr(err):
        code = main(["--studio", "--config", str(tmp_path / "nope.yaml")])
    assert code == 2 and err.getvalue() == f"error: config file not found: {tmp_path / 'nope.yaml'}\n"
    monkeypatch.setitem(sys.modules, "viser", None)  # `import viser` raises ImportError
    err = io.StringIO()
    with redirect_stderr(err):
        code = main(["--studio"])
    lines = err.getvalue().strip().splitlines()
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith("error: the studio needs the 'viewer' extra (pip install 'gs_regional[viewer]')")


# ----- the page in a real browser -------------------------------------------------------------------
def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _field(page, label):
    """The input of a labelled control (viser's text input does not tie its label to it)."""
    return page.locator(f"xpath=//label[normalize-space()='{label}']"
                        "/ancestor::div[contains(@class,'mantine-Flex-root')][1]//input[not(@type='hidden')]")


def _screenshot(page) -> np.ndarray:
    import imageio.v3 as iio

    return iio.imread(page.screenshot(), extension=".png")[..., :3].astype(np.int16)


def _view_area(img: np.ndarray) -> np.ndarray:
    """The 3D view left of the side panel, below the browser's software-WebGL notice."""
    return img[img.shape[0] // 4:, : img.shape[1] * 6 // 10]


def _settled_frame(page, previous=None, seconds: float = 20.0) -> np.ndarray:
    """A screenshot once the 3D view stops changing (and differs from `previous`, if given)."""
    deadline, last = time.monotonic() + seconds, _screenshot(page)
    while time.monotonic() < deadline:
        page.wait_for_timeout(400)
        img = _screenshot(page)
        moved = (np.abs(_view_area(img) - _view_area(last)).max(-1) > 30).sum()
        new = previous is None or (np.abs(_view_area(img) - _view_area(previous)).max(-1) > 30).sum() > 30
        if moved < 5 and new:
            return img
        last = img
    return last


def _selected_pixel(studio):
    """Where on the canvas (0..1 from the upper left) the current selection covers a pixel most,
    seen by the page's client camera: a click there lands on selected Gaussians."""
    from gs_regional.studio.session import client_camera

    s = studio.session
    client = next(iter(studio.server.get_clients().values()))
    cam = client.camera
    camera = client_camera(cam.position, cam.wxyz, cam.fov, cam.aspect)
    cover = s.renderer().pixel_weights(s.localized.source, camera).splat(s.selection.float()[:, None])[..., 0]
    cover[: camera.height // 4] = 0  # not under the browser's notice
    cover[:, camera.width * 6 // 10:] = 0  # nor under the side panel
    row, col = divmod(int(torch.argmax(cover)), camera.width)
    assert float(cover[row, col]) > 0.5
    return (col + 0.5) / camera.width, (row + 0.5) / camera.height


def test_the_whole_flow_in_the_browser(tmp_path, monkeypatch):
    pytest.importorskip("viser", reason="the 'viewer' extra (viser) is not installed")
    from gs_regional.geometry.formats import read_splat
    from gs_regional.studio.page import serve

    unet = UnetCount(monkeypatch)
    studio = serve(_session(tmp_path, "studio"), port=_free_port())
    s = studio.session
    try:
        with browser() as chromium:
            page = chromium.new_page(viewport={"width": 1100, "height": 700})
            page.goto(studio.url)
            # An empty instruction is a message on the page.
            _field(page, "Instruction").fill("")
            page.get_by_role("button", name="Select region").click()
            page.get_by_text("type an instruction first").wait_for(timeout=20_000)

            # Select region: the highlighted count appears.
            _field(page, "Instruction").fill(PROMPT)
            page.get_by_role("button", name="Select region").click()
            page.get_by_text("UNet evaluations so far").wait_for(timeout=60_000)
            first = s.count
            assert page.get_by_text(f"Selected: {first:,} of 9,765 Gaussians").is_visible()
            assert page.get_by_text("Relevance maps").is_visible()
            calls = unet.calls
            assert calls > 0

            # The threshold re-lifts: the count changes, and the editor is not called.
            threshold = _field(page, "Threshold")
            threshold.fill("0.3")
            threshold.press("Enter")
            lower = int(s.localized.select(0.3).sum())
            assert lower > first
            page.get_by_text(f"Selected: {lower:,} of 9,765").wait_for(timeout=20_000)
            assert unet.calls == calls and s.threshold == 0.3

            # Remove from selection, then a click on the scene where the selection is: fewer.
            page.get_by_role("button", name="Remove from selection").click()
            page.get_by_text("Click on the scene to remove from").wait_for(timeout=10_000)
            page.wait_for_timeout(500)
            x, y = _selected_pixel(studio)
            box = page.locator("canvas").first.bounding_box()
            page.mouse.click(box["x"] + x * box["width"], box["y"] + y * box["height"])
            page.get_by_text("removed on the scene").wait_for(timeout=20_000)
            assert 0 < s.count < lower and unet.calls == calls
            page.get_by_role("button", name="Stop picking").click()

            # Edit, wait for it; before / after differ; the .splat downloads and reads back.
            page.get_by_text("Highlight selection").click()
            page.get_by_role("button", name="Edit", exact=True).click()
            page.get_by_text("Status: Edit: Done").wait_for(timeout=120_000)
            page.get_by_text("Showing: after").wait_for(timeout=10_000)
            after = _settled_frame(page)
            page.get_by_role("button", name="Before", exact=True).click()
            page.get_by_text("Showing: before").wait_for(timeout=10_000)
            before = _settled_frame(page, after)
            changed = (np.abs(_view_area(after) - _view_area(before)).max(-1) > 40).sum()
            assert changed > 50, f"before/after differ in {changed} pixels"
            with page.expect_download(timeout=30_000) as download:
                page.get_by_role("button", name="Download .splat").click()
            got = read_splat(download.value.path())
            want = read_splat(s.edit_trial / "save" / "edited.splat")
            assert got.num_gaussians == s.result.model.num_gaussians == want.num_gaussians
            np.testing.assert_array_equal(got.means, want.means)
            page.get_by_text("PSNR").first.wait_for(timeout=10_000)  # the metrics panel

            # A long edit: a second Edit is refused; a page closed and opened again shows where the
            # edit is; Stop ends it with its outputs written.
            s.overrides["system.refine.iterations_per_cycle"] = "400"
            page.get_by_role("button", name="Edit", exact=True).click()
            page.get_by_text("Status: Edit: refine").wait_for(timeout=60_000)
            page.get_by_role("button", name="Edit", exact=True).click()
            page.get_by_text("Edit refused: an edit is running").wait_for(timeout=10_000)
            page.close()
            again = chromium.new_page(viewport={"width": 1100, "height": 700})
            again.goto(studio.url)
            again.get_by_text("Status: Edit: refine").wait_for(timeout=30_000)
            assert s.busy
            again.get_by_role("button", name="Stop", exact=True).click()
            again.get_by_text("Status: Edit: Stopped at step").wait_for(timeout=60_000)
            assert (s.edit_trial / "save" / "edited.ply").is_file() and (s.edit_trial / "save" / "metrics.json").is_file()
            assert (s.edit_trial / "ckpts" / "last.ckpt").is_file()  # resume= continues it
            assert s.progress.step < s.progress.total == 1200
    finally:
        studio.stop()


def test_launch_py_serves_the_studio(tmp_path):
    """`python launch.py --studio` (no --config: the demo's scene) serves the page on this machine."""
    pytest.importorskip("viser", reason="the 'viewer' extra (viser) is not installed")
    import os
    import subprocess
    import urllib.request

    from trial_helpers import ROOT

    port = _free_port()
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    proc = subprocess.Popen([sys.executable, str(ROOT / "launch.py"), "--studio", "--port", str(port),
                             f"exp_root_dir={tmp_path}"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        deadline, lines = time.monotonic() + 120, []
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "ready in" in line:
                break
        assert any(f"demo.yaml ready in" in line and f"http://localhost:{port}" in line for line in lines), "".join(lines)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=30) as response:
            assert response.status == 200
    finally:
        proc.terminate()
        proc.wait(timeout=30)
