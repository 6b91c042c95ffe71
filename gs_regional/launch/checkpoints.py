"""Checkpoint files of a trial: written atomically on the checkpoint's own file system (the
previous one kept until the new one is complete), read with the weights-only unpickler, and a
resume checked before the run touches the trial: the file loads, and the config it was written
with is compared with the one given now."""
from __future__ import annotations

import errno
import logging
import os
import shutil
import uuid
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

from gs_regional.config import ConfigError

log = logging.getLogger(__name__)

PREVIOUS_SUFFIX = ".previous"  # last.ckpt -> last.ckpt.previous: the checkpoint before the newest
CONFIG_KEY = "gs_regional_config"  # the run's resolved config, stored in every checkpoint

# Config keys that define what a checkpoint holds: resuming with another value would continue a
# different run's state (another scene, prompt or seed). Prefixes of dotted keys.
RESUME_FIXED_KEYS: Tuple[str, ...] = (
    "seed", "data_type", "data", "system_type", "system.seed", "system.prompt", "system.geometry_type",
    "system.geometry",
)
# Keys that never matter to a resume (where the run writes, when it started, how to resume).
RESUME_IGNORED_KEYS: Tuple[str, ...] = ("timestamp", "trial_dir", "resume", "exp_root_dir", "name", "tag",
                                        "use_timestamp", "description")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; the message names the file (and the previous one)."""


class DiskFullError(OSError):
    """A checkpoint that could not be written for lack of space; the message names the file."""

    def __init__(self, path: str, message: str) -> None:
        super().__init__(errno.ENOSPC, message, path)
        self.message = message

    def __str__(self) -> str:  # OSError's would read "[Errno 28] ..."
        return self.message


# What torch.save raises when a write fails half-way (the disk filled up): its zip writer checks
# the position after each record ("unexpected pos"), or reports the failed write itself.
_TORCH_WRITE_FAILURES = ("unexpected pos", "no space left", "file write failed")


def disk_full_reason(e: BaseException) -> Optional[str]:
    """Why the disk took no more, if `e` (or an exception it was raised from or while handling)
    says so: OSError ENOSPC / EDQUOT, or torch's RuntimeError of a failed write; else None."""
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno == errno.EDQUOT:
            return "disk quota exceeded"
        if isinstance(e, OSError) and e.errno == errno.ENOSPC:
            return "no space left on device"
        if isinstance(e, RuntimeError) and any(m in str(e).lower() for m in _TORCH_WRITE_FAILURES):
            return "no space left on device"
        e = e.__cause__ or e.__context__
    return None


def _free_space(folder: str) -> str:
    """'1.2 MB free in <folder>', for the message of a full disk."""
    try:
        free = float(shutil.disk_usage(folder).free)
    except OSError as e:
        return f"free space in {folder} unknown: {e}"
    unit = "B"
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if free < 1024 or unit == "TB":
            break
        free /= 1024
    return f"{free:.0f} {unit} free in {folder}" if unit == "B" else f"{free:.1f} {unit} free in {folder}"


def disk_full_error(path: str, reason: str) -> DiskFullError:
    """The one-line error of a checkpoint `path` not written for lack of space, saying what is kept."""
    folder = os.path.dirname(path)
    if os.path.isfile(path):
        then = f"the last complete checkpoint is kept: free some space, then resume={path}"
    else:
        then = "free some space and run again"
    return DiskFullError(path, f"checkpoint {path} could not be written: the disk is full ({reason}, "
                               f"{_free_space(folder)}); nothing half-written is left; {then}")


def previous_path(path: os.PathLike | str) -> Path:
    return Path(f"{os.fspath(path)}{PREVIOUS_SUFFIX}")


def _fsync_dir(folder: str) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems cannot sync a directory
        pass
    finally:
        os.close(fd)


def save_atomic(checkpoint: Dict[str, Any], path: os.PathLike | str) -> None:
    """torch.save to a temporary file beside `path`, fsync it, keep the current `path` as
    `<path>.previous`, then rename the new file onto `path`. A kill at any moment leaves `path`
    either the old complete checkpoint or the new complete one (a rename within one directory is
    atomic; a temporary file in $TMPDIR, on another file system, would be copied, not renamed).
    A full disk removes the partial file and raises DiskFullError naming `path`."""
    path = os.path.abspath(os.fspath(path))
    folder = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    tmp = os.path.join(folder, f".{os.path.basename(path)}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        with open(tmp, "wb") as f:
            torch.save(checkpoint, f)
            f.flush()
            os.fsync(f.fileno())
        if os.path.exists(path):
            prev_tmp = tmp + PREVIOUS_SUFFIX
            try:
                os.link(path, prev_tmp)  # the current file stays at `path` meanwhile
            except OSError:  # no hard links on this file system
                shutil.copyfile(path, prev_tmp)
            os.replace(prev_tmp, previous_path(path))
        os.replace(tmp, path)
        _fsync_dir(folder)
    except BaseException as e:
        for leftover in (tmp, tmp + PREVIOUS_SUFFIX):
            if os.path.exists(leftover):
                os.remove(leftover)
        reason = disk_full_reason(e) if isinstance(e, Exception) else None
        if reason:
            raise disk_full_error(path, reason) from e  # one line for the user; --debug shows torch's error
        raise


def load_checkpoint_file(path: os.PathLike | str, map_location: Any = "cpu", mmap: bool = False) -> Dict[str, Any]:
    """The checkpoint at `path`, read with the weights-only unpickler (an untrusted file cannot run
    code). Any failure is a CheckpointError that names the file and, if there is one, the
    previous checkpoint to resume from instead."""
    path = os.fspath(path)
    try:
        checkpoint = torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except Exception as e:  # noqa: BLE001 - truncated zip, bad pickle, refused global: all "unusable"
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        msg = f"checkpoint {path} cannot be loaded ({type(e).__name__}: {reason[:300]})"
        prev = previous_path(path)
        if prev.is_file():
            msg += f"; the checkpoint before it is kept: resume={prev}"
        raise CheckpointError(msg) from None
    if not isinstance(checkpoint, dict) or "state_dict" not in checkpoint:
        raise CheckpointError(f"checkpoint {path} is not a Lightning checkpoint of a gs_regional run (no state_dict)")
    return checkpoint


# ------------------------------------------------------------------------- optimizer state rows
PACKED_ROWS = "packed_rows"  # marks an optimizer state tensor stored as its rows that are not all zero


def _pack_rows(value: Any) -> Any:
    """A state tensor as {PACKED_ROWS: row indices, "values": those rows, "shape"} when at most half
    of its rows hold a non-zero; anything else as it is."""
    if not isinstance(value, torch.Tensor) or value.dim() == 0 or value.shape[0] < 2:
        return value
    rows = (value.reshape(value.shape[0], -1) != 0).any(1).nonzero().squeeze(1)
    if 2 * rows.numel() > value.shape[0]:
        return value
    return {PACKED_ROWS: rows, "values": value[rows], "shape": list(value.shape)}


def _unpack_rows(value: Any) -> Any:
    if not (isinstance(value, dict) and PACKED_ROWS in value):
        return value
    dense = value["values"].new_zeros(value["shape"])
    dense[value[PACKED_ROWS]] = value["values"]
    return dense


def pack_optimizer_states(checkpoint: Dict[str, Any]) -> Dict[str, Any]:
    """The checkpoint with each optimizer's per-parameter state tensors (Adam's moments) packed to
    their non-zero rows. A regional edit trains a few percent of a scene's Gaussians: the moments
    of the others stay zero, and were two thirds of a checkpoint (bench_scale's checkpoint stage).
    New dicts throughout: the optimizer's own state is not touched."""
    states = checkpoint.get("optimizer_states")
    if not states:
        return checkpoint
    packed = [{**opt, "state": {pid: {k: _pack_rows(v) for k, v in st.items()} for pid, st in opt["state"].items()}}
              if isinstance(opt, dict) and isinstance(opt.get("state"), dict) else opt for opt in states]
    return {**checkpoint, "optimizer_states": packed}


def unpack_optimizer_states(checkpoint: Dict[str, Any]) -> Dict[str, Any]:
    """`pack_optimizer_states` undone, in place (a checkpoint written densely is left as it is)."""
    for opt in checkpoint.get("optimizer_states") or []:
        if isinstance(opt, dict) and isinstance(opt.get("state"), dict):
            for st in opt["state"].values():
                for k, v in st.items():
                    st[k] = _unpack_rows(v)
    return checkpoint


class TrialCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint I/O with `save_atomic` and `load_checkpoint_file`, the optimizer
    state packed to its non-zero rows in the file (`pack_optimizer_states`)."""

    def save_checkpoint(self, checkpoint: Dict[str, Any], path: Any, storage_options: Optional[Any] = None) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} takes no storage_options, got {storage_options!r}")
        save_atomic(pack_optimizer_states(checkpoint), path)

    def load_checkpoint(self, path: Any, map_location: Optional[Any] = None, weights_only: Optional[bool] = None):
        return unpack_optimizer_states(load_checkpoint_file(path, map_location=map_location or "cpu"))


# ------------------------------------------------------------------------------ config on resume
def flatten(tree: Any, prefix: str = "") -> Dict[str, Any]:
    """{"a.b.c": value} of a nested mapping (lists are values)."""
    if isinstance(tree, dict):
        out: Dict[str, Any] = {}
        for k, v in tree.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out if out or not prefix else {prefix: {}}
    return {prefix: tree}


def _under(key: str, prefixes: Sequence[str]) -> bool:
    return any(key == p or key.startswith(p + ".") for p in prefixes)


def config_changes(saved: Dict[str, Any], current: Dict[str, Any]) -> List[Tuple[str, Any, Any]]:
    """(key, value in the checkpoint, value now) of every setting that differs, ignored keys aside.
    A key missing on one side shows as `<unset>`."""
    a, b = flatten(saved), flatten(current)
    unset = "<unset>"
    return [(k, a.get(k, unset), b.get(k, unset)) for k in sorted(set(a) | set(b))
            if not _under(k, RESUME_IGNORED_KEYS) and a.get(k, unset) != b.get(k, unset)]


def check_resume_config(path: str, saved: Optional[Dict[str, Any]], current: Dict[str, Any],
                        fixed: Sequence[str] = ()) -> List[str]:
    """Compare the config a checkpoint was written with and the one given now: changes of keys
    that define the checkpoint's state (`RESUME_FIXED_KEYS` and the system's own `fixed`, relative
    to `system`) raise a ConfigError listing them; other changes are returned as lines to log."""
    if saved is None:
        log.warning("resume: %s holds no config (written by an older version); changes cannot be checked", path)
        return []
    changes = config_changes(saved, current)
    fixed_keys = RESUME_FIXED_KEYS + tuple(f"system.{k}" for k in fixed)
    refused = [c for c in changes if _under(c[0], fixed_keys)]
    lines = [f"{k}: {old!r} -> {new!r}" for k, old, new in changes]
    if refused:
        listed = "; ".join(f"{k}: {old!r} -> {new!r}" for k, old, new in refused)
        raise ConfigError(
            f"resume={path}: the checkpoint was written with other values of settings that define its state "
            f"({listed}); resume with the checkpoint's values or start a new run"
        )
    return lines
