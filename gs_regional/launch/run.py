"""One experiment run: config → datamodule and system → trial dir → Lightning Trainer → summary."""
from __future__ import annotations

import argparse
import contextlib
import inspect
import logging
import os
import shlex
import time
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import lightning
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger

from gs_regional.config import ConfigError, load_config, unknown_key_message
from gs_regional.launch.callbacks import FitStartClock, TrialCheckpoint, progress_callback
from gs_regional.launch.checkpoints import CONFIG_KEY, TrialCheckpointIO, check_resume_config, load_checkpoint_file
from gs_regional.launch.errors import is_user_error
from gs_regional.launch.logs import LIGHTNING_LOGGERS, filter_warnings
from gs_regional.launch.modes import STAGES, run_mode
from gs_regional.launch.plugins import default_custom_dir, load_plugins
from gs_regional.launch.sections import section_configs
from gs_regional.launch.summary import RunInfo, print_summary, read_metrics
from gs_regional.launch.trial import TrialLock, check_writable, now_timestamp, removed_if_start_fails, trial_dir_for, write_trial_files
from gs_regional.registry import find, load_builtins
from gs_regional.systems import parallel
from gs_regional.utils.io import write_json_atomic

log = logging.getLogger(__name__)


def _check_keys(section: str, given: Dict[str, Any], target: Any, reserved: Sequence[str] = ()) -> None:
    allowed = set(inspect.signature(target).parameters) - {"self", "args", "kwargs"}
    for key in given:
        if key in reserved:
            raise ConfigError(f"config key '{section}.{key}' is set by launch.py and cannot be configured")
        if key not in allowed:
            raise ConfigError(unknown_key_message(f"{section}.{key}", allowed - set(reserved),
                                                  f"the arguments of {target.__qualname__}"))


def _container(node: Any, section: str) -> Dict[str, Any]:
    from omegaconf import OmegaConf

    if node is None:
        return {}
    value = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
    if not isinstance(value, dict):
        raise ConfigError(f"config section '{section}' must be a mapping, got {value!r}")
    return dict(value)


def trainer_kwargs(cfg: Any, system: Any, mode: str, gpu: Optional[str], verbose: bool = False) -> Dict[str, Any]:
    """Trainer arguments from the `trainer:` section plus launch.py's defaults."""
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
        cuda = torch.cuda.is_available()
        parallel.check_gpu_list(gpu_ids, cuda, torch.cuda.device_count() if cuda else 0)
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
    kw.setdefault("enable_model_summary", verbose)  # a table of one GaussianModel says little
    return kw


def data_parallel_kwargs(kw: Dict[str, Any], system: Any, mode: str, scene: Any) -> Dict[str, Any]:
    """Several processes (trainer.devices=N, --gpu 0,1,...): the edit's work shared out over them
    by gs_regional's data-parallel strategy on Lightning's DDP launcher (systems/parallel.py), for
    a system that can share it (`check_processes`) and --train; a clear error otherwise. One
    process: `kw` unchanged."""
    n = parallel.requested_processes(kw)
    if n <= 1:
        return kw
    name = getattr(system, "registered_name", type(system).__name__)
    asked = f"trainer.devices / --gpu ask for {n} processes"
    if not hasattr(system, "check_processes"):
        raise ConfigError(f"system '{name}' runs on one process ({asked}): give one device")
    if mode != "train":
        raise ConfigError(f"--{mode} runs on one process ({asked}): give one device; "
                          "--train shares an edit over several")
    if int(kw.get("num_nodes", 1) or 1) > 1:
        raise ConfigError(f"trainer.num_nodes={kw['num_nodes']}: an edit is shared over the devices of one machine")
    strategy = kw.get("strategy", "auto")
    if not (strategy in (None, "auto", "ddp") or isinstance(strategy, parallel.EditDDPStrategy)):
        raise ConfigError(f"trainer.strategy={strategy!r}: an edit on several processes uses gs_regional's own "
                          "data-parallel strategy (Lightning's DDP without its module wrapper); "
                          "leave trainer.strategy unset")
    system.check_processes(n, scene)
    return {**kw, "strategy": parallel.EditDDPStrategy()}


def checkpoint_callback(cfg: Any, trial: Path):
    ck = checkpoint_settings(cfg)
    ck.setdefault("save_last", True)
    ck.setdefault("save_top_k", 0)  # only last.ckpt unless asked for more
    ck.setdefault("enable_version_counter", False)  # resuming rewrites last.ckpt, never last-v1.ckpt
    try:
        return TrialCheckpoint(dirpath=str(trial / "ckpts"), **ck)
    except Exception as e:
        raise ConfigError(f"bad checkpoint settings: {e}") from None


def checkpoint_settings(cfg: Any) -> Dict[str, Any]:
    """The `checkpoint:` section, checked against ModelCheckpoint's arguments."""
    ck = _container(cfg.checkpoint, "checkpoint")
    _check_keys("checkpoint", ck, ModelCheckpoint.__init__, reserved=("dirpath",))
    return ck


def run(args: argparse.Namespace, overrides: List[str], argv: List[str], custom_dir: Any = None) -> int:
    """The run of `launch.py`'s parsed `args`; its exit code (0: mistakes raise, cli.py reports them)."""
    run_trial(args, overrides, argv, custom_dir)
    return 0


def run_trial(args: argparse.Namespace, overrides: List[str], argv: List[str], custom_dir: Any = None,
              callbacks: Sequence[Any] = ()) -> Optional[Path]:
    """run(), returning the trial dir (None in a process that follows rank 0): gs_regional.edit's way in.
    `callbacks`: more Lightning callbacks for the trainer (the studio's progress and Stop)."""
    started, started_at = time.perf_counter(), time.time()
    clock = PhaseClock(started)
    verbose = bool(args.verbose or args.debug)
    mode = run_mode(args)
    if args.export == "region":
        overrides = [*overrides, "system.export.region=true"]
    # Built-ins first, so that a plugin reusing a built-in name fails in its own import.
    load_builtins()
    load_plugins(args.custom_dir or custom_dir or default_custom_dir(), debug=args.debug)
    clock.mark("plugins")

    # In a process that Lightning's launcher started for a run on several devices: rank 0's trial.
    follower = parallel.handed_down_trial()
    if follower is not None:  # rank 0 says all there is to say
        for name in ("gs_regional", "gs_regional.launch", "gs_regional.config", *LIGHTNING_LOGGERS):
            logging.getLogger(name).setLevel(logging.ERROR)
    cfg = load_config(args.config, overrides, section_configs=section_configs)
    resume = cfg.resume
    if resume and not os.path.isfile(resume):
        raise ConfigError(f"resume checkpoint not found: {resume}")
    if mode in ("validate", "test", "export") and not resume:
        log.warning("--%s without resume=<checkpoint>: using the freshly initialised system", mode)
    cfg.timestamp = follower[1] if follower is not None else now_timestamp() if cfg.use_timestamp else ""

    with warnings.catch_warnings():
        filter_warnings(verbose)
        if follower is not None:
            warnings.simplefilter("ignore")
        lightning.seed_everything(cfg.seed, workers=True, verbose=verbose)
        # Check everything, cheapest first, before a trial dir is created and before any model is
        # loaded: the registered names, the scene (cameras, photos, points: Lightning calls
        # setup() again, the datamodules keep what they loaded), the system's own input files (its
        # `check_inputs`, e.g. the PLY's header), then the system with its priors.
        dm_cls = find(cfg.data_type, kind="data", key="data_type")
        system_cls = find(cfg.system_type, kind="systems", key="system_type")
        if follower is None and not resume:
            check_writable(Path(cfg.exp_root_dir))  # a read-only output folder fails before any load
        datamodule = dm_cls(cfg.data)
        datamodule.setup(STAGES[mode])
        clock.mark("scene")
        if hasattr(system_cls, "check_inputs"):
            system_cls.check_inputs(cfg.system)
        checkpoint = None
        if resume:
            checkpoint = load_checkpoint_file(resume, mmap=True)  # names the file, offers the previous one
            changes = check_resume_config(resume, checkpoint.get(CONFIG_KEY), run_config(cfg),
                                          getattr(system_cls, "RESUME_FIXED_KEYS", ()))
        parallel.use_process_gpu(_container(cfg.trainer, "trainer"), args.gpu)  # priors onto this process's GPU
        system = system_cls(cfg.system, resumed=bool(resume))
        clock.mark("system")
        kw = trainer_kwargs(cfg, system, mode, args.gpu, verbose)
        kw = data_parallel_kwargs(kw, system, mode, getattr(datamodule, "scene", None))
        checkpoint_settings(cfg)

        trial, reused = trial_dir_for(cfg, resume) if follower is None else (follower[0], bool(resume))
        cfg.trial_dir = str(trial)
        with contextlib.ExitStack() as rank_zero_only:
            if follower is None:  # the trial is rank 0's: made, locked and written there
                # Inputs read by the system inside the Lightning run fail there: the trial dir goes again.
                rank_zero_only.enter_context(removed_if_start_fails(trial, reused, is_user_error))
                rank_zero_only.enter_context(TrialLock(trial))
                write_trial_files(trial, cfg, args.config, shlex.join(["python", "launch.py", *argv]), reused)
            if checkpoint is not None and changes:
                log.warning("resume: the config differs from the checkpoint's (%s); this run uses the new values, "
                            "written to %s", "; ".join(changes), trial / "configs" / f"parsed@{cfg.timestamp}.yaml")
            del checkpoint  # Lightning reads it again (the mapped file is not held meanwhile)
            fit_clock = FitStartClock()
            trainer = _make_trainer(cfg, kw, trial, reused, [*callbacks, fit_clock])
            system.set_trial_dir(trial)
            system.attach_datamodule(datamodule)
            log.info("trial dir: %s", trial)
            clock.mark("trainer")
            setup_seconds = time.perf_counter() - started
            if mode == "train":
                with parallel.hand_down_trial(trial, cfg.timestamp):  # to the processes Lightning launches
                    trainer.fit(system, datamodule=datamodule, ckpt_path=resume)
                if follower is None:
                    record_fit_seconds(trial, clock, fit_clock, resumed=bool(resume))
            elif mode == "validate":
                trainer.validate(system, datamodule=datamodule, ckpt_path=resume)
            elif mode == "test":
                trainer.test(system, datamodule=datamodule, ckpt_path=resume)
            else:
                export(trainer, system, datamodule, resume)
    if follower is not None:
        return None
    print_summary(RunInfo(
        trial=trial, mode=mode, config_path=args.config, system_type=cfg.system_type, data_type=cfg.data_type,
        resume=resume, steps=trainer.global_step if mode == "train" else None,
        setup_seconds=setup_seconds, setup_parts=clock.seconds, wall_seconds=time.perf_counter() - started,
        started_at=started_at,
    ))
    return trial


class PhaseClock:
    """Seconds of the phases of a run's start, each from the end of the one before."""

    def __init__(self, started: float) -> None:
        self.last, self.seconds = started, {}

    def mark(self, phase: str, at: Optional[float] = None) -> None:
        at = time.perf_counter() if at is None else at
        self.seconds[phase] = round(at - self.last, 3)
        self.last = at


def record_fit_seconds(trial: Path, clock: PhaseClock, fit_clock: FitStartClock, resumed: bool) -> None:
    """Where a training run's time outside its stages went, added to save/metrics.json (when the
    system wrote one): `seconds_setup` (plugins, scene, system with its priors, trial and trainer,
    Lightning's set-up up to the system's on_fit_start) and `seconds_unstaged` (the rest of fit
    outside the stages: Lightning's loop, checkpoints, teardown; not for a resumed run, whose
    stage seconds include the run before)."""
    ended = time.perf_counter()
    if fit_clock.at is not None:
        clock.mark("lightning", fit_clock.at)
    path = trial / "save" / "metrics.json"
    if not path.is_file():
        return
    metrics = read_metrics(trial)
    extra: Dict[str, Any] = {"seconds_setup": dict(clock.seconds)}
    stages = metrics.get("seconds_total")
    if fit_clock.at is not None and not resumed and isinstance(stages, (int, float)):
        extra["seconds_unstaged"] = round(max(0.0, ended - fit_clock.at - stages), 3)
    write_json_atomic(path, {**metrics, **extra})


def run_config(cfg: Any) -> Dict[str, Any]:
    """The resolved config of a run as stored in its checkpoints (and compared on resume)."""
    from omegaconf import OmegaConf

    return OmegaConf.to_container(cfg, resolve=True)


def _make_trainer(cfg: Any, kw: Dict[str, Any], trial: Path, reused: bool, extra: Sequence[Any] = ()) -> "lightning.Trainer":
    callbacks = [progress_callback()] if kw.get("enable_progress_bar", True) else []
    callbacks += list(extra)
    if kw.get("enable_checkpointing", True):
        callback = checkpoint_callback(cfg, trial)
        callback.run_config = run_config(cfg)
        callbacks.insert(0, callback)
        # Atomic writes in the checkpoint's own folder, weights-only reads that name the file.
        kw = {**kw, "plugins": [*(kw.get("plugins") or []), TrialCheckpointIO()]}
    if kw.get("logger", True) is True:
        # A resumed run logs into its own folder: Lightning's CSV logger would delete the old file.
        version = f"resume@{cfg.timestamp}" if reused else ""
        kw = {**kw, "logger": CSVLogger(save_dir=str(trial), name="csv_logs", version=version)}
    try:
        return lightning.Trainer(default_root_dir=str(trial), callbacks=callbacks, **kw)
    except Exception as e:
        raise ConfigError(f"bad trainer settings: {type(e).__name__}: {e}") from None


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
