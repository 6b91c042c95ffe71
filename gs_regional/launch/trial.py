"""Trial directories: `<exp_root_dir>/<name>/<tag>@<timestamp>`, never reusing an existing one
(except the trial of a `resume=` checkpoint), with the config and command that made them."""
from __future__ import annotations

import contextlib
import datetime
import errno
import logging
import os
import shutil
from pathlib import Path
from typing import Any, Callable, Iterator, Optional, Tuple

log = logging.getLogger(__name__)

TIMESTAMP_FORMAT = "%Y%m%d-%H%M%S"


def now_timestamp() -> str:
    return datetime.datetime.now().strftime(TIMESTAMP_FORMAT)


class OutputDirError(OSError):
    """The trial folder cannot be created (a read-only file system, no permission, a full disk):
    the user's to fix, by pointing `exp_root_dir=` at a writable folder."""

    def __str__(self) -> str:
        return self.strerror  # one line naming the folder, without "[Errno N]"


def check_writable(folder: Path) -> None:
    """Raise OutputDirError unless `folder`, or its nearest existing parent, may be written."""
    existing = folder.absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not os.access(existing, os.W_OK | os.X_OK):
        code = errno.EROFS if _read_only_mount(existing) else errno.EACCES
        raise OutputDirError(code, f"the trial folder {folder} cannot be created: {os.strerror(code).lower()} "
                                   f"({existing}); set exp_root_dir= to a writable folder")


def _read_only_mount(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def _claim_dir(base: Path) -> Path:
    """Create `base`, or `base-1`, `base-2`, ... if it exists: never reuse an existing trial dir."""
    candidate, n = base, 0
    try:
        base.parent.mkdir(parents=True, exist_ok=True)
        while True:
            try:
                candidate.mkdir()  # atomic: two launches in the same second get different dirs
                return candidate
            except FileExistsError:
                n += 1
                candidate = base.with_name(f"{base.name}-{n}")
    except OSError as e:
        reason = os.strerror(e.errno).lower() if e.errno else str(e)
        raise OutputDirError(e.errno, f"the trial folder {candidate} cannot be created: {reason}; "
                                      "set exp_root_dir= to a writable folder") from e


def path_component(key: str, value: str) -> str:
    """`value` as one folder name: the trial root is the only place a run writes, so a name or tag
    that is empty, `.`/`..` or holds a path separator is refused, naming the key."""
    from gs_regional.config import ConfigError

    value = str(value)
    separators = {"/", "\\", os.sep, os.altsep or "/", "\0"}
    if value in ("", ".", "..") or any(sep in value for sep in separators):
        raise ConfigError(
            f"{key}='{value}' must be a single folder name (no '/', '\\', '.' or '..'): the trial dir is "
            f"<exp_root_dir>/<name>/<tag>@<timestamp> and a run writes nowhere else"
        )
    return value


def trial_dir_for(cfg: Any, resume: Optional[str]) -> Tuple[Path, bool]:
    """(trial dir, reused?). A resume checkpoint inside `<trial>/ckpts/` reuses `<trial>`."""
    if resume:
        ckpt = Path(resume).resolve()
        if ckpt.parent.name == "ckpts":
            return ckpt.parent.parent, True
        log.warning("resume checkpoint %s is not inside a trial's ckpts/ folder: starting a new trial dir", resume)
    name = path_component("name", cfg.name)
    tag = path_component("tag" if cfg.tag else "system_type", cfg.tag or cfg.system_type or "run")
    folder = f"{tag}@{cfg.timestamp}" if cfg.use_timestamp else tag
    return _claim_dir(Path(cfg.exp_root_dir) / name / folder), False


LOCK_NAME = ".lock"


class TrialLock:
    """An exclusive lock on a trial dir (`<trial>/.lock`, flock) while a run writes into it: a
    second run of the same trial (two resumes of one checkpoint) is refused instead of writing the
    same checkpoint and appending to the same logs. The kernel drops the lock when the process
    ends, however it ends (kill -9 included), so a stale lock never blocks a resume."""

    def __init__(self, trial: Path) -> None:
        self.path = Path(trial) / LOCK_NAME
        self._fd: Optional[int] = None

    def acquire(self) -> "TrialLock":
        import fcntl

        from gs_regional.config import ConfigError

        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode("utf-8", "replace").strip() or "another process"
            os.close(fd)
            raise ConfigError(
                f"trial dir {self.path.parent} is in use by another run ({holder}); wait for it to end "
                "(two runs writing one trial would mix their checkpoints and logs)"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock
            self._fd = None

    def __enter__(self) -> "TrialLock":
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()


def _write_text(path: Path, text: str) -> None:
    from gs_regional.utils.io import atomic_write

    with atomic_write(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)


def write_trial_files(trial: Path, cfg: Any, config_path: str, command: str, reused: bool) -> None:
    """configs/parsed.yaml (resolved, after overrides), configs/raw.yaml (the file as given) and
    cmd.txt. A resumed run keeps the first run's files and adds `@<timestamp>` copies."""
    from omegaconf import OmegaConf

    configs = trial / "configs"
    configs.mkdir(parents=True, exist_ok=True)
    suffix = f"@{cfg.timestamp or now_timestamp()}" if reused else ""
    for stem, text in (
        ("parsed", OmegaConf.to_yaml(cfg, resolve=True)),
        ("raw", Path(config_path).read_text(encoding="utf-8")),
    ):
        path = configs / f"{stem}.yaml"
        if path.exists() and reused:
            path = configs / f"{stem}{suffix}.yaml"
        _write_text(path, text)
    cmd = trial / "cmd.txt"
    previous = cmd.read_text(encoding="utf-8") if cmd.exists() else ""
    _write_text(cmd, previous + command + "\n")


def has_checkpoint(trial: Path) -> bool:
    return any((trial / "ckpts").glob("*.ckpt"))


@contextlib.contextmanager
def removed_if_start_fails(trial: Path, reused: bool, is_user_error: Callable[[BaseException], bool]) -> Iterator[None]:
    """Delete a trial dir this run created when the run fails on a mistake in its inputs or
    config (`is_user_error`) before any checkpoint was written: the one-line error says all there
    is to say, and an empty trial dir would only be clutter. A trial with a checkpoint, a reused
    one, or one that ends in a bug (traceback) is kept."""
    try:
        yield
    except BaseException as e:
        if not reused and is_user_error(e) and not has_checkpoint(trial):
            shutil.rmtree(trial, ignore_errors=True)
            with contextlib.suppress(OSError):
                trial.parent.rmdir()  # only if empty
        raise
