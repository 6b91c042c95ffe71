"""The logic behind `launch.py` (threestudio-style), importable so that tests can run it in-process.

    python launch.py --config X.yaml (--train|--validate|--test|--export) [--gpu N] [key=value ...]

1. import every module and package under `custom/` (plugins register components);
2. read the YAML, apply the overrides;
3. seed, build the datamodule (`data_type`) and the system (`system_type`);
4. make the trial directory `<exp_root_dir>/<name>/<tag>@<timestamp>` (or reuse the one of a
   `resume=<trial>/ckpts/last.ckpt`) with configs/parsed.yaml, configs/raw.yaml and cmd.txt;
5. run a Lightning Trainer (checkpoints in ckpts/, CSV logs in csv_logs/).

Configuration mistakes end with one line `error: ...` and exit code 2 (`--debug` shows the traceback).
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import importlib
import importlib.machinery
import importlib.util
import inspect
import logging
import os
import shlex
import shutil
import sys
import traceback
import types
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

from gs_regional.config import ConfigError, load_config
from gs_regional.registry import RegistryError, find, load_builtins, note_import_error

log = logging.getLogger("gs_regional.launch")

PLUGIN_PACKAGE = "custom"  # plugins are imported as custom.<name>, whatever folder they live in
TIMESTAMP_FORMAT = "%Y%m%d-%H%M%S"
MODES = ("train", "validate", "test", "export")


def default_custom_dir() -> Path:
    """`custom/` beside launch.py (the repository root)."""
    return Path(__file__).resolve().parents[1] / "custom"


# ----------------------------------------------------------------------------------------------
# Plugins
# ----------------------------------------------------------------------------------------------
def _plugin_package(custom_dir: Path) -> types.ModuleType:
    """The package `custom` whose search path is `custom_dir` (created, or reset when the folder
    differs from the one of an earlier call in this process)."""
    folder = str(custom_dir.resolve())
    pkg = sys.modules.get(PLUGIN_PACKAGE)
    if pkg is not None and list(getattr(pkg, "__path__", [])) == [folder]:
        return pkg
    for name in [m for m in sys.modules if m == PLUGIN_PACKAGE or m.startswith(PLUGIN_PACKAGE + ".")]:
        del sys.modules[name]
    spec = importlib.machinery.ModuleSpec(PLUGIN_PACKAGE, None, is_package=True)
    spec.submodule_search_locations = [folder]
    pkg = importlib.util.module_from_spec(spec)
    pkg.__path__ = [folder]
    sys.modules[PLUGIN_PACKAGE] = pkg
    return pkg


def _plugin_entries(custom_dir: Path) -> List[Tuple[str, str]]:
    """(module name, label) of every plugin module `x.py` and package `x/__init__.py`, by name."""
    entries = []
    for entry in sorted(os.listdir(custom_dir)):
        path = custom_dir / entry
        if entry.startswith((".", "_")):
            continue
        if path.is_file() and entry.endswith(".py"):
            entries.append((entry[:-3], f"{custom_dir.name}/{entry}"))
        elif path.is_dir() and (path / "__init__.py").is_file():
            entries.append((entry, f"{custom_dir.name}/{entry}/"))
    return entries


def _describe_import_error(e: BaseException, custom_dir: Path) -> str:
    """'ErrorType: message (file, line N)', the line being the deepest one inside the plugin folder."""
    msg = f"{type(e).__name__}: {e}"
    if isinstance(e, SyntaxError):  # its message already says where
        return msg
    folder = str(custom_dir.resolve())
    where = None
    for frame in traceback.extract_tb(e.__traceback__):
        if os.path.abspath(frame.filename).startswith(folder + os.sep):
            where = f"{os.path.relpath(frame.filename, folder)}, line {frame.lineno}"
    return f"{msg} ({custom_dir.name}/{where})" if where else msg


def load_plugins(custom_dir: Any, debug: bool = False) -> Dict[str, Optional[str]]:
    """Import every plugin under `custom_dir` as `custom.<name>`.

    A missing or empty folder is fine. A plugin that fails to import is logged as an error with
    its name and the error, and remembered by the registry (an unknown-type error then mentions
    it); the other plugins are still imported. Returns {label: None if imported, else the error}.
    """
    custom_dir = Path(custom_dir)
    if not custom_dir.is_dir():
        log.debug("no plugin folder at %s", custom_dir)
        return {}
    _plugin_package(custom_dir)
    importlib.invalidate_caches()  # files may have been written since the last import
    results: Dict[str, Optional[str]] = {}
    for module, label in _plugin_entries(custom_dir):
        full = f"{PLUGIN_PACKAGE}.{module}"
        try:
            importlib.import_module(full)
        except Exception as e:
            # Drop the half-imported module so that a later import tries again.
            for name in [m for m in sys.modules if m == full or m.startswith(full + ".")]:
                del sys.modules[name]
            err = _describe_import_error(e, custom_dir)
            results[label] = err
            note_import_error(f"plugin {label}", err)
            log.error("plugin %s failed to import: %s", label, err)
            if debug:
                log.error("".join(traceback.format_exception(type(e), e, e.__traceback__)))
        else:
            results[label] = None
            note_import_error(f"plugin {label}", None)
            log.debug("loaded plugin %s", label)
    return results


# ----------------------------------------------------------------------------------------------
# Trial directory
# ----------------------------------------------------------------------------------------------
def _claim_dir(base: Path) -> Path:
    """Create `base`, or `base-1`, `base-2`, ... if it exists: never reuse an existing trial dir."""
    base.parent.mkdir(parents=True, exist_ok=True)
    candidate, n = base, 0
    while True:
        try:
            candidate.mkdir()  # atomic: two launches in the same second get different dirs
            return candidate
        except FileExistsError:
            n += 1
            candidate = base.with_name(f"{base.name}-{n}")


def trial_dir_for(cfg: Any, resume: Optional[str]) -> Tuple[Path, bool]:
    """(trial dir, reused?). A resume checkpoint inside `<trial>/ckpts/` reuses `<trial>`."""
    if resume:
        ckpt = Path(resume).resolve()
        if ckpt.parent.name == "ckpts":
            return ckpt.parent.parent, True
        log.warning("resume checkpoint %s is not inside a trial's ckpts/ folder: starting a new trial dir", resume)
    tag = str(cfg.tag or cfg.system_type or "run").replace("/", "-").replace(os.sep, "-")
    name = f"{tag}@{cfg.timestamp}" if cfg.use_timestamp else tag
    return _claim_dir(Path(cfg.exp_root_dir) / str(cfg.name) / name), False


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
    suffix = f"@{cfg.timestamp or datetime.datetime.now().strftime(TIMESTAMP_FORMAT)}" if reused else ""
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


# ----------------------------------------------------------------------------------------------
# Lightning pieces
# ----------------------------------------------------------------------------------------------
def _lightning_classes():
    """Import Lightning lazily (slow) and define the callbacks on first use."""
    global _LCLASSES
    if _LCLASSES is not None:
        return _LCLASSES
    from lightning.pytorch.callbacks import ModelCheckpoint, TQDMProgressBar

    class TrialCheckpoint(ModelCheckpoint):
        """ModelCheckpoint that also writes `last.ckpt` when training ends on a step that is not a
        multiple of `every_n_train_steps` (Lightning only does so if it never saved one)."""

        def on_train_end(self, trainer, pl_module) -> None:
            super().on_train_end(trainer, pl_module)
            if (
                self.save_last
                and trainer.global_step > 0
                and getattr(self, "_last_global_step_saved", None) != trainer.global_step
                and not trainer.fast_dev_run
            ):
                self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))

    class StageProgressBar(TQDMProgressBar):
        """One bar over all training steps (systems run many short epochs), described by the
        system's current stage, e.g. 'refine 2/3'."""

        def _steps_mode(self, trainer) -> bool:
            return trainer.max_steps is not None and trainer.max_steps > 0

        def _describe(self, trainer, pl_module) -> str:
            stage = getattr(pl_module, "stage", "") or ""
            return stage if stage else f"Epoch {trainer.current_epoch}"

        def on_train_epoch_start(self, trainer, *args) -> None:
            if not self._steps_mode(trainer):
                super().on_train_epoch_start(trainer, *args)
            else:
                bar = self.train_progress_bar
                if bar.total != trainer.max_steps:
                    bar.reset(total=trainer.max_steps)
                    bar.initial = 0
                    if not bar.disable:
                        bar.n = trainer.global_step
                        bar.refresh()
            pl_module = args[0] if args else trainer.lightning_module
            self.train_progress_bar.set_description(self._describe(trainer, pl_module))

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
            if not self._steps_mode(trainer):
                super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
            else:
                bar = self.train_progress_bar
                n = trainer.global_step
                if bar is not None and not bar.disable and self._should_update(n, bar.total):
                    bar.n = n
                    bar.set_postfix(self.get_metrics(trainer, pl_module), refresh=False)
                    bar.set_description(self._describe(trainer, pl_module), refresh=False)
                    bar.refresh()
                return
            self.train_progress_bar.set_description(self._describe(trainer, pl_module))

        def on_train_epoch_end(self, trainer, pl_module) -> None:
            if not self._steps_mode(trainer):
                super().on_train_epoch_end(trainer, pl_module)

    _LCLASSES = types.SimpleNamespace(TrialCheckpoint=TrialCheckpoint, StageProgressBar=StageProgressBar)
    return _LCLASSES


_LCLASSES = None


def _check_keys(section: str, given: Dict[str, Any], target: Any, reserved: Sequence[str] = ()) -> None:
    allowed = set(inspect.signature(target).parameters) - {"self", "args", "kwargs"}
    for key in given:
        if key in reserved:
            raise ConfigError(f"config key '{section}.{key}' is set by launch.py and cannot be configured")
        if key not in allowed:
            raise ConfigError(
                f"unknown config key '{section}.{key}': not an argument of {target.__qualname__}; "
                f"allowed keys: {', '.join(sorted(allowed - set(reserved)))}"
            )


def _container(node: Any, section: str) -> Dict[str, Any]:
    from omegaconf import OmegaConf

    if node is None:
        return {}
    value = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
    if not isinstance(value, dict):
        raise ConfigError(f"config section '{section}' must be a mapping, got {value!r}")
    return dict(value)


def trainer_kwargs(cfg: Any, system: Any, mode: str, gpu: Optional[str]) -> Dict[str, Any]:
    """Trainer arguments from the `trainer:` section plus launch.py's defaults."""
    import lightning
    import torch

    kw = _container(cfg.trainer, "trainer")
    _check_keys("trainer", kw, lightning.Trainer.__init__, reserved=("callbacks", "default_root_dir"))
    if mode == "train" and kw.get("max_steps") in (None, -1):
        steps = getattr(system, "total_steps", None)
        if steps is not None:
            kw["max_steps"] = int(steps)
        elif kw.get("max_epochs") is None:
            raise ConfigError(
                "how long to train is not set: give trainer.max_steps (or system.max_steps, or trainer.max_epochs)"
            )
    if gpu is not None:
        try:
            gpu_ids = [int(g) for g in str(gpu).split(",") if g.strip()]
        except ValueError:
            gpu_ids = []
        if not gpu_ids or min(gpu_ids) < 0:
            raise ConfigError(f"--gpu must be a CUDA device index such as 0 (or a list such as 0,1), got '{gpu}'")
    if "accelerator" not in kw:
        if gpu is not None and torch.cuda.is_available():
            kw["accelerator"] = "gpu"
            kw.setdefault("devices", gpu_ids)
        else:
            if gpu is not None:
                log.warning("--gpu %s given but CUDA is not available: running on the CPU", gpu)
            kw["accelerator"] = "cpu"
    kw.setdefault("devices", 1)
    kw.setdefault("log_every_n_steps", 10)
    kw.setdefault("num_sanity_val_steps", 0)
    kw.setdefault("enable_checkpointing", True)
    return kw


def checkpoint_callback(cfg: Any, trial: Path):
    from lightning.pytorch.callbacks import ModelCheckpoint

    ck = _container(cfg.checkpoint, "checkpoint")
    _check_keys("checkpoint", ck, ModelCheckpoint.__init__, reserved=("dirpath",))
    ck.setdefault("save_last", True)
    ck.setdefault("save_top_k", 0)  # only last.ckpt unless asked for more
    ck.setdefault("enable_version_counter", False)  # resuming rewrites last.ckpt, never last-v1.ckpt
    try:
        return _lightning_classes().TrialCheckpoint(dirpath=str(trial / "ckpts"), **ck)
    except Exception as e:
        raise ConfigError(f"bad checkpoint settings: {e}") from None


# ----------------------------------------------------------------------------------------------
# main
# ----------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="launch.py",
        description="Run a gs_regional experiment: python launch.py --config X.yaml --train [key=value ...]",
    )
    p.add_argument("--config", required=True, help="YAML experiment config")
    mode = p.add_mutually_exclusive_group(required=True)
    helps = {
        "train": "train (resume=<ckpt> continues a run)",
        "validate": "run the validation loop (on resume=<ckpt>)",
        "test": "run the test loop (on resume=<ckpt>)",
        "export": "load resume=<ckpt> and call the system's on_export()",
    }
    for m in MODES:
        mode.add_argument(f"--{m}", action="store_true", help=helps[m])
    p.add_argument("--gpu", default=None, help="CUDA device index (e.g. 0); without it the run uses the CPU")
    p.add_argument("--custom-dir", default=None, help="plugin folder (default: custom/ beside launch.py)")
    p.add_argument("--debug", action="store_true", help="show tracebacks of configuration errors")
    return p


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is now (it may be replaced, e.g. by test capture)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def _setup_logging(debug: bool) -> None:
    root = logging.getLogger("gs_regional")
    root.setLevel(logging.DEBUG if debug else logging.INFO)
    if not any(isinstance(h, _StderrHandler) for h in root.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("[%(levelname)s] %(message)s"))
        root.addHandler(handler)


def main(argv: Optional[Sequence[str]] = None, custom_dir: Any = None) -> int:
    """Run launch.py with `argv` (default: sys.argv[1:]); returns the exit code.

    `custom_dir` is the default plugin folder (launch.py passes the one beside itself).
    Errors that are not configuration errors propagate with their traceback.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args, extra = parser.parse_known_args(argv)
    except SystemExit as e:  # argparse already printed the usage and the error
        return int(e.code or 0)
    bad = [x for x in extra if "=" not in x]
    if bad:
        parser.print_usage(sys.stderr)
        print(f"error: unrecognized arguments: {' '.join(bad)} (overrides are key=value)", file=sys.stderr)
        return 2
    _setup_logging(args.debug)
    try:
        return run(args, extra, argv, custom_dir)
    except Exception as e:
        if args.debug or not _is_usage_error(e):
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2


def _is_usage_error(e: BaseException) -> bool:
    """Mistakes in the config or the command line (Lightning's own included, e.g. `--validate`
    with a system that has no validation step), as opposed to bugs that need a traceback."""
    if isinstance(e, (ConfigError, RegistryError)):
        return True
    try:
        from lightning.fabric.utilities.exceptions import MisconfigurationException
    except ImportError:  # pragma: no cover
        return False
    return isinstance(e, MisconfigurationException)


def run(args: argparse.Namespace, overrides: List[str], argv: List[str], custom_dir: Any = None) -> int:
    import lightning
    from lightning.pytorch.loggers import CSVLogger

    mode = next(m for m in MODES if getattr(args, m))
    # Built-ins first, so that a plugin reusing a built-in name fails in its own import.
    load_builtins()
    load_plugins(args.custom_dir or custom_dir or default_custom_dir(), debug=args.debug)

    cfg = load_config(args.config, overrides)
    resume = cfg.resume
    if resume and not os.path.isfile(resume):
        raise ConfigError(f"resume checkpoint not found: {resume}")
    if mode in ("validate", "test", "export") and not resume:
        log.warning("--%s without resume=<checkpoint>: using the freshly initialised system", mode)
    cfg.timestamp = datetime.datetime.now().strftime(TIMESTAMP_FORMAT) if cfg.use_timestamp else ""

    lightning.seed_everything(cfg.seed, workers=True)
    # Build (and so validate) everything before a trial dir is created for the run.
    try:
        dm_cls = find(cfg.data_type, kind="data")
    except RegistryError as e:
        raise RegistryError(f"data_type: {e}") from None
    try:
        system_cls = find(cfg.system_type, kind="systems")
    except RegistryError as e:
        raise RegistryError(f"system_type: {e}") from None
    datamodule = dm_cls(cfg.data)
    system = system_cls(cfg.system, resumed=bool(resume))
    kw = trainer_kwargs(cfg, system, mode, args.gpu)
    from lightning.pytorch.callbacks import ModelCheckpoint

    _check_keys("checkpoint", _container(cfg.checkpoint, "checkpoint"), ModelCheckpoint.__init__, reserved=("dirpath",))

    trial, reused = trial_dir_for(cfg, resume)
    cfg.trial_dir = str(trial)
    try:
        write_trial_files(trial, cfg, args.config, shlex.join(["python", "launch.py", *argv]), reused)
        callbacks = [_lightning_classes().StageProgressBar()] if kw.get("enable_progress_bar", True) else []
        if kw.get("enable_checkpointing", True):
            callbacks.insert(0, checkpoint_callback(cfg, trial))
        if kw.get("logger", True) is True:
            # A resumed run logs into its own folder: Lightning's CSV logger would delete the old file.
            version = f"resume@{cfg.timestamp}" if reused else ""
            kw["logger"] = CSVLogger(save_dir=str(trial), name="csv_logs", version=version)
        try:
            trainer = lightning.Trainer(default_root_dir=str(trial), callbacks=callbacks, **kw)
        except Exception as e:
            raise ConfigError(f"bad trainer settings: {type(e).__name__}: {e}") from None
    except ConfigError:
        if not reused:  # nothing ran: do not leave an empty trial dir behind
            shutil.rmtree(trial, ignore_errors=True)
            with contextlib.suppress(OSError):
                trial.parent.rmdir()  # only if empty
        raise
    system.set_trial_dir(trial)
    system.attach_datamodule(datamodule)
    log.info("trial dir: %s", trial)

    with warnings.catch_warnings():
        # Lightning warns on every manual-optimisation checkpoint that it holds the state after the
        # optimizer step: that is exactly what we want to resume from.
        warnings.filterwarnings("ignore", message="Using ModelCheckpoint with manual optimization")
        warnings.filterwarnings("ignore", message="predict returned None")  # --export predicts nothing
        if mode == "train":
            trainer.fit(system, datamodule=datamodule, ckpt_path=resume)
        elif mode == "validate":
            trainer.validate(system, datamodule=datamodule, ckpt_path=resume)
        elif mode == "test":
            trainer.test(system, datamodule=datamodule, ckpt_path=resume)
        else:
            export(trainer, system, datamodule, resume)
    return 0


def export(trainer: Any, system: Any, datamodule: Any, resume: Optional[str]) -> None:
    """`--export`: Lightning's predict loop restores `resume` exactly as fit does (the system's
    setup, then its checkpoint extras, then the state dict) and BaseSystem.on_predict_end calls
    the system's `on_export()`."""
    from lightning.pytorch.utilities.model_helpers import is_overridden

    from gs_regional.systems.base import BaseSystem

    if isinstance(system, BaseSystem) and type(system).on_export is BaseSystem.on_export:
        raise ConfigError(f"--export: system '{getattr(system, 'registered_name', type(system).__name__)}' has no export")
    # With a datamodule, Lightning takes the predict dataloader only from it: lend it the
    # system's one-batch loader if it has none (the datamodule stays attached for setup()).
    if datamodule is not None and not is_overridden("predict_dataloader", datamodule):
        datamodule.predict_dataloader = system.predict_dataloader
    trainer.predict(system, datamodule=datamodule, ckpt_path=resume, return_predictions=False)
