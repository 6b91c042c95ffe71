"""What a user sees on the console: one-line errors for bad input files (exit 2, no trial dir
left behind, a traceback with --debug), a quiet run whose progress is whole lines when the output
is no terminal, and the end-of-run summary whose paths exist."""
import json
import re
import zlib
from pathlib import Path

import numpy as np
import pytest

from gs_regional.data.colmap import ColmapError
from gs_regional.data.images import ImageLoadError
from gs_regional.data.nerfstudio import TransformsError
from gs_regional.geometry.ply import PlyError
from gs_regional.launch import main
from gs_regional.launch.summary import RunInfo, format_summary
from trial_helpers import launch_args, launch_process, small_demo



def _transforms(folder: Path, image_name: str) -> None:
    """A nerfstudio transforms.json with one camera whose photo is `image_name`."""
    pose = np.eye(4)
    pose[2, 3] = 3.0
    frame = {"file_path": image_name, "transform_matrix": pose.tolist()}
    data = {"fl_x": 50.0, "fl_y": 50.0, "cx": 16.0, "cy": 16.0, "w": 32, "h": 32, "frames": [frame]}
    (folder / "transforms.json").write_text(json.dumps(data))


def _png_with_bad_data(path: Path) -> None:
    """A PNG signature and header followed by a corrupt image stream."""
    ihdr = b"IHDR" + (32).to_bytes(4, "big") * 2 + bytes([8, 2, 0, 0, 0])
    chunk = len(ihdr[4:]).to_bytes(4, "big") + ihdr + zlib.crc32(ihdr).to_bytes(4, "big")
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk + b"\x00\x00\x00\x10IDATgarbage-garbage")


def bad_transforms(tmp):
    (tmp / "transforms.json").write_text('{"frames": [')
    return "configs/reconstruct.yaml", [f"data.source={tmp}"], TransformsError, tmp / "transforms.json"


def bad_image(tmp):
    _transforms(tmp, "photo.png")
    _png_with_bad_data(tmp / "photo.png")
    return "configs/reconstruct.yaml", [f"data.source={tmp}"], ImageLoadError, tmp / "photo.png"


def bad_colmap(tmp):
    model = tmp / "sparse" / "0"
    model.mkdir(parents=True)
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (model / name).write_bytes(b"\x05\x00")  # ends inside the first count
    return "configs/reconstruct.yaml", [f"data.source={tmp}"], ColmapError, model


def bad_ply(tmp):
    # Read by the system inside the Lightning run, after the trial dir exists: it must go again.
    (tmp / "scene.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nend_header\n")
    return "configs/demo.yaml", [f"system.geometry.ply={tmp / 'scene.ply'}", *small_demo()], PlyError, tmp / "scene.ply"


@pytest.mark.parametrize("case", [bad_transforms, bad_image, bad_colmap, bad_ply])
def test_bad_input_file_is_one_line_and_leaves_no_trial_dir(case, tmp_path, capsys):
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    config, overrides, error_type, culprit = case(inputs)
    out = tmp_path / "outputs"
    argv = launch_args(out, "bad", *overrides, config=config, small=False)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("error: ") and str(culprit) in last, err
    assert not out.exists() or not any(out.rglob("*")), sorted(out.rglob("*"))

    with pytest.raises(error_type, match=re.escape(str(culprit))):  # --debug: the traceback
        main(argv + ["--debug"])


def run_launch(*args, **kwargs):
    """launch.py in a fresh process (its output is no terminal): (stdout, stderr). Bytes, decoded
    here: text mode would turn carriage returns into newlines."""
    proc = launch_process(*args, **kwargs)
    return proc.stdout.decode(), proc.stderr.decode()


LIGHTNING_NOISE = ("Tip:", "Trainable params", "GPU available", "TPU available", "Seed set", "val_dataloader",
                   "Warning", "max_steps=", "LOCAL_RANK")


def test_demo_run_is_quiet_and_ends_with_a_summary_of_existing_outputs(tmp_path):
    # The small demo (3 cycles of 4 steps) with the progress it leaves out: what this test reads.
    stdout, stderr = run_launch(tmp_path, "demo", "trainer.enable_progress_bar=true")
    (trial,) = (tmp_path / "demo").iterdir()
    # Quiet: the trial dir on stderr, nothing from Lightning, no warnings.
    assert stderr.strip().splitlines() == [f"trial dir: {trial}"], stderr
    for noise in LIGHTNING_NOISE:
        assert noise not in stdout + stderr, noise
    # Progress, named after the stages: whole lines (the output is no terminal), a line when a
    # stage is seen to start and one at each tenth of the steps, never a carriage return.
    assert "\r" not in stdout + stderr
    progress, summary = stdout.rsplit("\n\n", 1)
    lines = [re.fullmatch(r"(.+): (\d+)/12 steps \((\d+)%\), \d\d:\d\d", line) for line in progress.splitlines()]
    assert all(lines), progress
    stages = list(dict.fromkeys(m.group(1) for m in lines))
    # (localize and initialize are seen at the checkpoints that end them, output at the last one)
    assert stages == ["start", "localize", "initialize", "refine 1/3", "refine 2/3", "refine 3/3", "output"], progress
    assert {int(m.group(2)) * 10 // 12 for m in lines} == set(range(11))  # each tenth of the steps
    assert len(lines) <= len(stages) + 11 and lines[-1].group(1, 2) == ("output", "12")

    lines = summary.strip().splitlines()
    assert lines[-1] == f"results: {trial}"
    rows = dict(re.fullmatch(r"(\S.*?)\s{2,}(.*)", line).groups() for line in lines[:-1])
    assert rows["ran"].startswith("train regional-edit on synthetic-scene") and "12 steps" in rows["ran"]
    m = json.loads((trial / "save" / "metrics.json").read_text())
    assert rows["Gaussians"] == (f"{m['gaussians_before']:,} before, +{m['count_added_init']:,} from depth, "
                                 + (f"+{m['count_added_cycles']:,} from the cycles' depth and paint, " if m.get("count_added_cycles") else "")
                                 + f"+{m['count_densified']:,} densified"
                                 + (f", -{m['count_pruned']:,} pruned" if m.get("count_pruned") else "")
                                 + f" -> {m['gaussians_after']:,} after")
    assert m["refined_as"] == "addition"
    assert rows["refined as"] == f"an addition: the depth of view {m['v_first']} shows a change of shape"
    assert f"mask IoU {m['mask_iou']:.3f}" in rows["metrics"]
    assert f"PSNR vs true edit {m['psnr_vs_true_edit']:.2f} dB" in rows["metrics"]
    assert all(stage in rows["stages (s)"] for stage in ("localize", "initialize", "refine_train", "output"))
    # The time outside the stages, split by phase, in the summary and in metrics.json.
    setup = m["seconds_setup"]
    assert list(setup) == ["plugins", "scene", "system", "trainer", "lightning"] and all(v >= 0 for v in setup.values())
    assert rows["start-up (s)"] == (", ".join(f"{k} {v:.1f}" for k, v in setup.items())
                                    + f"; in training outside the stages {m['seconds_unstaged']:.1f}")
    assert 0 < m["seconds_unstaged"] < m["seconds_total"]
    paths = {label: Path(rows[label]) for label in ("edited scene", "before/after", "turntable", "metrics.json")}
    for label, path in paths.items():
        assert path.is_file() and path.parent == trial / "save", (label, path)
    assert paths["edited scene"].name == "edited.ply" and paths["turntable"].stem == "turntable"


def test_verbose_brings_back_lightning_messages(tmp_path):
    (tmp_path / "custom").mkdir()
    config = tmp_path / "tiny.yaml"
    config.write_text("name: tiny\ndata_type: tiny-data\nsystem_type: tiny-system\n")
    (tmp_path / "custom" / "tiny.py").write_text(TINY)
    out, err = run_launch(tmp_path, "tiny", config=config, small=False,  # the quiet run is checked on the demo above
                          args=("--custom-dir", str(tmp_path / "custom"), "--verbose"))
    for noise in ("Trainable params", "Seed set", "GPU available"):  # model summary, Lightning's info lines
        assert noise in out + err, noise
    assert "debug [gs_regional.launch.plugins]: loaded plugin custom/tiny.py" in err
    assert out.strip().splitlines()[-1].startswith("results: ")


TINY = '''
import lightning
import torch

from gs_regional.registry import register
from gs_regional.systems.base import BaseSystem


@register("tiny-data")
class TinyData(lightning.LightningDataModule):
    def __init__(self, cfg=None):
        super().__init__()

    def train_dataloader(self):
        return torch.utils.data.DataLoader(torch.arange(2), batch_size=1)


@register("tiny-system")
class TinySystem(BaseSystem):
    def __init__(self, cfg=None, resumed=False):
        super().__init__(None, resumed=resumed)
        self.x = torch.nn.Parameter(torch.zeros(3))

    @property
    def total_steps(self):
        return 2

    def configure_optimizers(self):
        return torch.optim.SGD([self.x], lr=0.1)

    def training_step(self, batch, batch_idx):
        opt = self.optimizers()
        opt.zero_grad()
        self.manual_backward((self.x - 1).square().sum())
        opt.step()

    def on_train_end(self):
        self.write_metrics_json({"x_sum": float(self.x.sum())})
'''


def test_summary_says_an_edit_was_refined_as_a_recolour_and_how_much_of_the_selection_kept_its_colours(tmp_path):
    """An instruction to add something whose depth shows no change of shape is refined as a
    recolour: nothing is added. The summary says so, and how many selected Gaussians the gate left
    at their colours, beside the Gaussian counts that alone would read as an addition that failed."""
    save = tmp_path / "save"
    save.mkdir()
    (save / "metrics.json").write_text(json.dumps({
        "refined_as": "recolour", "v_first": 3, "count_selected": 1351, "count_recolour_declined": 167,
        "gaussians_before": 9765, "gaussians_after": 9765, "count_added_init": 0, "count_densified": 0}))
    info = RunInfo(trial=tmp_path, mode="train", config_path="c.yaml", system_type="regional-edit", data_type="d",
                   resume=None, steps=5, setup_seconds=1.0, wall_seconds=2.0, started_at=0.0)
    def rows():
        lines = format_summary(info).splitlines()[:-1]
        return dict(re.fullmatch(r"(\S.*?)\s{2,}(.*)", line).groups() for line in lines)

    assert rows()["refined as"] == (
        "a recolour: the depth of view 3 shows no change of shape, no Gaussian is added; 167 of the 1,351 selected "
        "Gaussians keep their colours (the edited views recolour them too little, or they are parts of their own)")
    (save / "metrics.json").write_text(json.dumps({"refined_as": "recolour", "v_first": 3, "init": {"recolour_edge": 4}}))
    assert rows()["refined as"] == ("a recolour: the depth of view 3 changes only at the recoloured part's edge (4 "
                                    "Gaussians placed there removed), no Gaussian is added")
    (save / "metrics.json").write_text(json.dumps({"refined_as": "addition", "v_first": 3, "init": {"rejected": "x"}}))
    assert rows()["refined as"] == "an addition: the depth calibration was rejected, so refinement densifies the region"


def test_summary_falls_back_to_the_metrics_a_system_reports(tmp_path):
    save = tmp_path / "save"
    save.mkdir()
    (save / "metrics.json").write_text(json.dumps({"updates": 5, "loss": 0.25, "name": "x", "seconds": 3.5}))
    (save / "reconstructed.ply").write_bytes(b"")
    info = RunInfo(trial=tmp_path, mode="train", config_path="c.yaml", system_type="s", data_type="d", resume=None,
                   steps=5, setup_seconds=1.0, wall_seconds=2.0, started_at=0.0)
    text = format_summary(info)
    assert "updates 5" in text and "loss 0.25" in text and "fit 3.5" in text
    assert f"fitted scene  {save / 'reconstructed.ply'}" in text
    assert text.splitlines()[-1] == f"results: {tmp_path}"
