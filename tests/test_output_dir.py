"""An output folder the disk refuses (read-only mount, no permission) is one line naming it and
exit code 2, before any stage runs: nothing of the user's is touched and no traceback shows."""
import errno
import subprocess
from pathlib import Path

import pytest

from trial_helpers import launch
from gs_regional.launch import trial as trial_module



@pytest.fixture
def read_only_mount(tmp_path):
    """A real read-only file system (tmpfs mounted `ro`); needs root and mount rights."""
    mnt = tmp_path / "ro"
    mnt.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs here ({done.stderr.strip() or 'mount failed'}); "
                    "the same path is tested with a simulated EROFS below")
    yield mnt
    subprocess.run(["umount", str(mnt)], check=False)


def test_read_only_exp_root_dir_is_one_line_and_exit_2(read_only_mount, capsys):
    launch(read_only_mount / "outputs", "demo", expect=2)
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"error: the trial folder {read_only_mount / 'outputs'}"), err
    assert "read-only file system" in err[-1] and "exp_root_dir=" in err[-1]
    assert "Traceback" not in "\n".join(err)


def test_a_refused_trial_folder_names_it(tmp_path, monkeypatch, capsys):
    real_mkdir = Path.mkdir

    def mkdir(self, *args, **kwargs):
        if tmp_path in self.parents or self == tmp_path / "outputs":
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(trial_module.Path, "mkdir", mkdir)
    launch(tmp_path / "outputs", "demo", expect=2)
    (line,) = [l for l in capsys.readouterr().err.splitlines() if l.startswith("error:")]
    assert line.startswith(f"error: the trial folder {tmp_path / 'outputs'}")
    assert line.endswith("read-only file system; set exp_root_dir= to a writable folder")
    assert not (tmp_path / "outputs").exists()
