"""launch.py end to end, with a tiny system and datamodule that a plugin written by the test
registers (independent of the real systems and datamodule)."""
import csv
import errno
import glob
import io
import logging
import os
import re
import subprocess
import sys

import lightning  # noqa: F401  (imported here so its log handler binds to the real stderr)
import pytest
import torch
import yaml

from trial_helpers import ROOT
from gs_regional.launch import load_plugins, main
from gs_regional.launch.callbacks import StageProgressBar, StageProgressLines, progress_callback
from gs_regional.launch.checkpoints import DiskFullError, load_checkpoint_file, save_atomic
from gs_regional.registry import note_import_error


TINY_PLUGIN = '''
import random
from dataclasses import dataclass, field
from typing import List

import lightning
import numpy as np
import torch

from gs_regional.config import parse_structured
from gs_regional.registry import register
from gs_regional.systems.base import BaseSystem


class Endless(torch.utils.data.IterableDataset):
    def __iter__(self):
        i = 0
        while True:
            yield i
            i += 1


@register("tiny-data")
class TinyData(lightning.LightningDataModule):
    @dataclass
    class Config:
        batches: int = 2  # per epoch; shuffled with the global RNG (the hard case for resuming)
        endless: bool = False

    def __init__(self, cfg=None):
        super().__init__()
        self.cfg = parse_structured(self.Config, cfg, where="data")

    def train_dataloader(self):
        if self.cfg.endless:
            return torch.utils.data.DataLoader(Endless(), batch_size=None)
        return torch.utils.data.DataLoader(torch.arange(self.cfg.batches), batch_size=1, shuffle=True)


@dataclass
class Inner:
    scale: float = 1.0


@register("tiny-system")
class TinySystem(BaseSystem):
    """Optimises one tensor towards a noisy target with manual optimisation."""

    @dataclass
    class Config:
        target: List[float] = field(default_factory=lambda: [1.0, -2.0, 3.0])
        lr: float = 0.1
        noise: float = 0.5
        max_steps: int = 6
        crash_at_step: int = -1
        inner: Inner = field(default_factory=Inner)

    def __init__(self, cfg=None, resumed=False):
        super().__init__(cfg, resumed=resumed)
        self.x = torch.nn.Parameter(torch.zeros(3))
        self.updates = 0

    def configure_optimizers(self):
        return torch.optim.Adam([self.x], lr=self.cfg.lr)

    def training_step(self, batch, batch_idx):
        step = self.global_step
        if step == self.cfg.crash_at_step:
            raise RuntimeError(f"simulated crash at step {step}")
        self.set_stage(f"phase {1 + step // 3}")
        # noise from all three global RNGs: an exact resume must restore each of them
        jitter = torch.randn(3) + float(np.random.randn()) + random.gauss(0.0, 1.0)
        target = torch.tensor(self.cfg.target) * self.cfg.inner.scale + self.cfg.noise * jitter
        loss = ((self.x - target) ** 2).sum()
        opt = self.optimizers()
        opt.zero_grad()
        self.manual_backward(loss)
        opt.step()
        self.updates += 1
        self.log_metrics({"loss": loss.detach()})

    def extra_state(self):
        return {"updates": self.updates}

    def load_extra_state(self, state):
        self.updates = state["updates"]

    def on_train_end(self):
        self.save_image("final.png", torch.rand(4, 4, 3))
        self.write_metrics_json({"updates": self.updates})

    def on_export(self):
        torch.save(self.x.detach().clone(), self.save_path("export/x.pt"))
'''

CONFIG = """\
name: tiny
seed: 1
data_type: tiny-data
system_type: tiny-system
system:
  lr: 0.1
trainer:
  log_every_n_steps: 1
  enable_model_summary: false
checkpoint:
  every_n_train_steps: 2
"""


@pytest.fixture(scope="module")
def setup_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("launch")
    (root / "custom").mkdir()
    (root / "custom" / "tiny_plugin.py").write_text(TINY_PLUGIN)
    (root / "tiny.yaml").write_text(CONFIG)
    return root


def run(root, *args, name="tiny", progress=False):
    argv = ["--config", str(root / "tiny.yaml"), *args, "--custom-dir", str(root / "custom"),
            f"exp_root_dir={root / 'outputs'}", f"name={name}"]
    if not progress:
        argv.append("trainer.enable_progress_bar=false")
    return main(argv)


def trials(root, name):
    return sorted(glob.glob(str(root / "outputs" / name / "*")), key=os.path.getmtime)


def final_x(trial):
    ckpt = torch.load(os.path.join(trial, "ckpts", "last.ckpt"), map_location="cpu", weights_only=False)
    return ckpt["global_step"], ckpt["state_dict"]["x"]


def test_train_writes_the_trial_layout(setup_dir, capsys):
    root = setup_dir
    # 5 steps with a checkpoint every 2: last.ckpt must still hold the end of the run.
    assert run(root, "--train", "system.max_steps=5", "system.inner.scale=2", name="layout", progress=True) == 0
    (trial,) = trials(root, "layout")
    assert os.path.basename(trial).startswith("tiny-system@")  # tag defaults to the system type
    assert len(os.path.basename(trial)) == len("tiny-system@20250101-120000")
    parsed = yaml.safe_load(open(os.path.join(trial, "configs", "parsed.yaml")))
    assert parsed["system"]["inner"]["scale"] == 2 and parsed["trial_dir"] == trial and parsed["name"] == "layout"
    assert open(os.path.join(trial, "configs", "raw.yaml")).read() == CONFIG
    cmd = open(os.path.join(trial, "cmd.txt")).read()
    assert cmd.startswith("python launch.py --config") and "system.inner.scale=2" in cmd
    step, x = final_x(trial)
    assert step == 5 and x.abs().sum() > 0
    rows = list(csv.DictReader(open(os.path.join(trial, "csv_logs", "metrics.csv"))))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5] and all(float(r["loss"]) > 0 for r in rows)
    assert os.path.isfile(os.path.join(trial, "save", "final.png"))
    assert open(os.path.join(trial, "save", "metrics.json")).read().count('"updates": 5') == 1
    out = capsys.readouterr().out
    assert "\r" not in out  # captured output is no terminal: lines, not a bar's redraws
    assert "phase 1" in out and "phase 2: 5/5 steps (100%)" in out  # the stage and the steps


def test_existing_trial_dir_is_never_overwritten(setup_dir):
    root = setup_dir
    for _ in range(2):
        assert run(root, "--train", "use_timestamp=false", "tag=fixed", "system.max_steps=1", name="suffix") == 0
    assert [os.path.basename(t) for t in trials(root, "suffix")] == ["fixed", "fixed-1"]


RESUME_RUN = ["--train", "system.max_steps=7", "checkpoint.every_n_train_steps=3"]


def uninterrupted(root, data):
    """The final tensor of a run that was not interrupted (computed once per data setting)."""
    name = "full-" + data.replace("=", "-").replace(".", "-")
    if not trials(root, name):
        assert run(root, *RESUME_RUN, data, name=name) == 0
    (full,) = trials(root, name)
    return final_x(full)


def crash_and_resume(root, data, name):
    with pytest.raises(RuntimeError, match="simulated crash at step 5"):
        run(root, *RESUME_RUN, data, "system.crash_at_step=5", name=name)
    (trial,) = trials(root, name)
    assert final_x(trial)[0] == 3  # the last checkpoint before the crash (mid-epoch)
    assert run(root, *RESUME_RUN, data, f"resume={trial}/ckpts/last.ckpt", name=name) == 0
    assert trials(root, name) == [trial]  # resumed in the same trial dir
    return trial


@pytest.mark.parametrize("data", ["data.batches=2", "data.endless=true"])
def test_resume_after_a_crash_matches_an_uninterrupted_run(setup_dir, data):
    root = setup_dir
    trial = crash_and_resume(root, data, "resume-" + data.replace("=", "-").replace(".", "-"))
    (s_full, x_full), (s_res, x_res) = uninterrupted(root, data), final_x(trial)
    assert s_full == s_res == 7
    assert torch.equal(x_full, x_res), (x_full, x_res)
    extra = torch.load(os.path.join(trial, "ckpts", "last.ckpt"), weights_only=False)["gs_regional"]["extra"]
    assert extra == {"updates": 7}
    configs = sorted(os.listdir(os.path.join(trial, "configs")))
    assert "parsed.yaml" in configs and any(c.startswith("parsed@") for c in configs)  # first run's kept
    assert len(open(os.path.join(trial, "cmd.txt")).read().splitlines()) == 2
    assert os.path.isdir(os.path.join(trial, "csv_logs")) and any(
        d.startswith("resume@") for d in os.listdir(os.path.join(trial, "csv_logs"))
    )


def test_resume_without_rng_restore_differs(setup_dir, monkeypatch):
    """Control for the test above: without restoring the RNG the resumed run is not the same."""
    import gs_regional.systems.base as base

    monkeypatch.setattr(base, "restore_rng_state", lambda state: None)
    trial = crash_and_resume(setup_dir, "data.batches=2", "no-rng")
    assert not torch.equal(uninterrupted(setup_dir, "data.batches=2")[1], final_x(trial)[1])


def test_export_loads_the_checkpoint_and_calls_on_export(setup_dir):
    root = setup_dir
    assert run(root, "--train", "system.max_steps=2", name="export") == 0
    (trial,) = trials(root, "export")
    assert run(root, "--export", f"resume={trial}/ckpts/last.ckpt", name="export") == 0
    exported = torch.load(os.path.join(trial, "save", "export", "x.pt"))
    assert torch.equal(exported, final_x(trial)[1])


def test_broken_plugin_is_reported_and_the_good_one_still_loads(setup_dir, tmp_path, caplog, capsys):
    custom = tmp_path / "plugins"
    custom.mkdir()
    (custom / "a_broken.py").write_text(
        "from gs_regional.registry import register\nimport no_such_module_xyz\n\n"
        "@register('broken-thing')\nclass Broken:\n    pass\n"
    )
    (custom / "b_good").mkdir()
    (custom / "b_good" / "__init__.py").write_text(
        "from gs_regional.registry import register\n\n@register('good-thing')\nclass Good:\n    pass\n"
    )
    (custom / "notes.txt").write_text("not a plugin")
    with caplog.at_level(logging.ERROR, logger="gs_regional"):
        results = load_plugins(custom)
    assert results == {
        "plugins/a_broken.py": "ModuleNotFoundError: No module named 'no_such_module_xyz' (plugins/a_broken.py, line 2)",
        "plugins/b_good/": None,
    }
    assert any("a_broken.py" in r.getMessage() and r.levelno == logging.ERROR for r in caplog.records)
    from gs_regional.registry import find

    assert find("good-thing").__name__ == "Good"

    # A config that names the broken plugin's type: exit 2, and the error says why it is unknown.
    cfg = tmp_path / "broken.yaml"
    cfg.write_text(CONFIG.replace("system_type: tiny-system", "system_type: broken-thing"))
    rc = main(["--config", str(cfg), "--train", "--custom-dir", str(custom), f"exp_root_dir={tmp_path / 'out'}"])
    err = capsys.readouterr().err
    assert rc == 2
    line = err.strip().splitlines()[-1]  # the fatal line comes last, after the logged plugin error
    assert line.startswith("error:")
    assert "unknown systems type 'broken-thing'" in line and "a_broken.py" in line and "no_such_module_xyz" in line
    assert "Traceback" not in err
    assert not os.path.exists(tmp_path / "out")  # no trial dir for a run that never started
    note_import_error("plugin plugins/a_broken.py", None)  # registry state is global: leave none behind


def test_config_errors_exit_2_with_one_line(setup_dir, capsys):
    root = setup_dir
    rc = main(["--config", str(root / "nope.yaml"), "--train", "--custom-dir", str(root / "custom")])
    err = capsys.readouterr().err
    assert rc == 2 and f"error: config file not found: {root / 'nope.yaml'}" in err and "Traceback" not in err

    assert run(root, "--train", "system.inner.scalee=2", name="typo") == 2
    err = capsys.readouterr().err
    assert "error: unknown config key 'system.inner.scalee' (did you mean 'scale'?)" in err
    assert run(root, "--train", "trainer.max_stepz=3", name="typo") == 2
    assert "unknown config key 'trainer.max_stepz'" in capsys.readouterr().err
    assert run(root, "--train", "checkpoint.every_n_train_step=3", name="typo") == 2
    assert "unknown config key 'checkpoint.every_n_train_step'" in capsys.readouterr().err
    assert run(root, "--train", "resume=/no/such/last.ckpt", name="typo") == 2
    assert "resume checkpoint not found: /no/such/last.ckpt" in capsys.readouterr().err
    assert not os.path.exists(root / "outputs" / "typo")
    with pytest.raises(Exception, match="system.inner.scalee"):  # --debug shows the traceback
        run(root, "--train", "--debug", "system.inner.scalee=2", name="typo")
    assert main(["--train"]) == 2  # argparse: --config is required


def test_launch_py_subprocess_exit_code(tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("name: x\nsytem_type: tiny-system\n")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "launch.py"), "--config", str(cfg), "--train", "--custom-dir", str(tmp_path)],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
    )
    assert proc.returncode == 2, proc.stderr
    assert "error:" in proc.stderr and "'sytem_type' (did you mean 'system_type'?)" in proc.stderr
    assert "Traceback" not in proc.stderr


# ----- progress ----------------------------------------------------------------------------------
PROGRESS_LINE = re.compile(r"(?P<stage>.+): (?P<done>\d+)/(?P<total>\d+) steps \((?P<pct>\d+)%\), \d\d:\d\d")


def test_progress_is_a_line_per_stage_and_per_tenth_when_not_a_terminal(setup_dir, capsys):
    """In a log file (captured output is no terminal either) progress is whole lines: one when the
    stage changes (every 3 steps here), one at each tenth of the steps, no carriage returns."""
    assert run(setup_dir, "--train", "system.max_steps=40", name="lines", progress=True) == 0
    captured = capsys.readouterr()
    assert "\r" not in captured.out + captured.err
    lines = [m.groupdict() for m in map(PROGRESS_LINE.fullmatch, captured.out.splitlines()) if m]
    assert lines[0] == {"stage": "start", "done": "0", "total": "40", "pct": "0"}
    assert lines[-1] == {"stage": "phase 14", "done": "40", "total": "40", "pct": "100"}
    stages = [line["stage"] for line in lines[1:]]
    assert list(dict.fromkeys(stages)) == [f"phase {i}" for i in range(1, 15)]  # each stage, in order
    tenths = {int(line["done"]) * 10 // 40 for line in lines}
    assert tenths == set(range(11))  # every tenth of the run has its line
    assert len(lines) <= 1 + 14 + 10  # and nothing else: one per stage change or tenth


def test_progress_disabled_writes_no_progress(setup_dir, capsys):
    assert run(setup_dir, "--train", "system.max_steps=4", name="quiet", progress=False) == 0
    out = capsys.readouterr().out
    assert not any(PROGRESS_LINE.fullmatch(line) for line in out.splitlines()), out
    assert out.strip().splitlines()[-1].startswith("results: ")


def test_progress_is_a_bar_on_a_terminal_only():
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    assert isinstance(progress_callback(Terminal()), StageProgressBar)
    assert isinstance(progress_callback(io.StringIO()), StageProgressLines)


# ----- a full disk -------------------------------------------------------------------------------
TORCH_FULL_DISK = "[enforce fail at inline_container.cc:672] . unexpected pos 9472 vs 9360"


def _save_fails_from_call(n, error):
    """torch.save that writes the first n - 1 checkpoints, then half of one and raises `error`."""
    real_save, calls = torch.save, []

    def save(obj, f, *args, **kwargs):
        calls.append(1)
        if len(calls) < n:
            return real_save(obj, f, *args, **kwargs)
        f.write(b"PK\x03\x04half a checkpoint")
        raise error

    return save


def test_full_disk_during_a_checkpoint_is_one_line_and_keeps_the_last_one(setup_dir, monkeypatch, capsys):
    monkeypatch.setattr(torch, "save", _save_fails_from_call(2, RuntimeError(TORCH_FULL_DISK)))
    assert run(setup_dir, "--train", "system.max_steps=5", name="full-disk") == 2  # saves at steps 2, 4, 5
    monkeypatch.undo()
    (trial,) = trials(setup_dir, "full-disk")
    ckpt = os.path.join(trial, "ckpts", "last.ckpt")
    err = capsys.readouterr().err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"error: checkpoint {ckpt} could not be written: the disk is full (no space left on device")
    assert last.endswith(f"free some space, then resume={ckpt}")
    assert os.listdir(os.path.dirname(ckpt)) == ["last.ckpt"]  # nothing half-written left
    assert final_x(trial)[0] == 2  # the checkpoint before the full disk, complete


def test_full_disk_at_the_first_checkpoint_leaves_nothing(setup_dir, monkeypatch, capsys):
    monkeypatch.setattr(torch, "save", _save_fails_from_call(1, OSError(errno.ENOSPC, "No space left on device")))
    assert run(setup_dir, "--train", "system.max_steps=5", name="full-disk-first") == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert re.fullmatch(r"error: checkpoint \S+/ckpts/last\.ckpt could not be written: the disk is full "
                        r"\(no space left on device, .* free in \S+/ckpts\); nothing half-written is left; "
                        r"free some space and run again", last), last
    # No checkpoint was written: the trial dir goes, as after any error before the first one.
    assert trials(setup_dir, "full-disk-first") == []
    assert not list((setup_dir / "outputs").rglob("*.tmp"))


def test_save_atomic_on_a_full_disk(tmp_path, monkeypatch):
    path = tmp_path / "ckpts" / "last.ckpt"
    save_atomic({"state_dict": {"x": torch.ones(3)}}, path)
    real_save = torch.save
    cases = [RuntimeError(TORCH_FULL_DISK),
             RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed"),
             OSError(errno.EDQUOT, "Disk quota exceeded")]
    for error in cases:
        monkeypatch.setattr(torch, "save", _save_fails_from_call(1, error))
        with pytest.raises(DiskFullError) as e:
            save_atomic({"state_dict": {"x": torch.zeros(3)}}, path)
        assert str(path) in str(e.value) and "the disk is full" in str(e.value) and e.value.__cause__ is error
        assert os.listdir(path.parent) == ["last.ckpt"]
    assert "disk quota exceeded" in str(e.value)
    if os.path.exists("/dev/full"):  # what torch really raises when the disk takes no more
        def save_to_full_disk(obj, f, *args, **kwargs):
            with open("/dev/full", "wb") as full:
                real_save(obj, full, *args, **kwargs)

        monkeypatch.setattr(torch, "save", save_to_full_disk)
        with pytest.raises(DiskFullError, match="no space left on device"):
            save_atomic({"state_dict": {"x": torch.zeros(100_000)}}, path)
    monkeypatch.setattr(torch, "save", _save_fails_from_call(1, RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="^a bug$"):  # other failures stay what they are
        save_atomic({"state_dict": {}}, path)
    monkeypatch.undo()
    assert torch.equal(load_checkpoint_file(path)["state_dict"]["x"], torch.ones(3))  # the first, intact


def test_checkpoints_keep_only_the_optimizer_rows_an_edit_trained(tmp_path):
    """Adam's moments are zero for every row a regional edit does not train: the checkpoint file
    holds the rows that are not (a fraction of its dense size), Lightning's load gets the same
    dense state back bit for bit, and the live optimizer is untouched by the save."""
    from gs_regional.launch.checkpoints import TrialCheckpointIO

    rows = torch.nn.Parameter(torch.randn(20_000, 16))
    scalar = torch.nn.Parameter(torch.randn(()))  # 0-d state stays as it is
    opt = torch.optim.Adam([rows, scalar], lr=0.1)
    for _ in range(3):
        opt.zero_grad()
        loss = (rows[100:140] ** 2).sum() + (rows[7] * 0.0).sum() + scalar ** 2  # row 7: a zero gradient
        loss.backward()
        opt.step()
    live = {k: v.clone() for k, v in opt.state[rows].items()}
    checkpoint = {"state_dict": {"rows": rows.detach()}, "optimizer_states": [opt.state_dict()]}
    io, packed, dense = TrialCheckpointIO(), tmp_path / "packed.ckpt", tmp_path / "dense.ckpt"
    io.save_checkpoint(checkpoint, packed)
    save_atomic(checkpoint, dense)
    assert os.path.getsize(packed) < 0.6 * os.path.getsize(dense)  # the moments were 2/3 of the file
    assert all(torch.equal(opt.state[rows][k], v) for k, v in live.items())  # the save copied, not changed

    loaded = io.load_checkpoint(packed)
    again = torch.optim.Adam([torch.nn.Parameter(rows.detach().clone()), torch.nn.Parameter(scalar.detach().clone())], lr=0.1)
    again.load_state_dict(loaded["optimizer_states"][0])
    restored = again.state_dict()["state"]
    for pid, state in opt.state_dict()["state"].items():
        for k, v in state.items():
            assert torch.equal(restored[pid][k], v), (pid, k)
    assert int((restored[0]["exp_avg_sq"] != 0).any(1).sum()) == 40  # rows 100-139 (row 7's stays 0)
    # A checkpoint written before packing (dense moments) loads as it was.
    assert torch.equal(io.load_checkpoint(dense)["optimizer_states"][0]["state"][0]["exp_avg"], live["exp_avg"])
