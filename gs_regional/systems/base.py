"""`BaseSystem`: what every system (a LightningModule run by launch.py) shares.

* a typed, strictly parsed `Config` (errors name the key as `system.<key>`);
* manual optimisation (systems run stages, not one loss): note that Lightning's `global_step`
  (and so `max_steps`) only advances when an optimizer's `step()` is called;
* `stage`: a short text the progress bar shows ("localize", "refine 2/3");
* the trial directory (`trial_dir`, `save_dir` = `<trial>/save`) and helpers that write images,
  grids, videos and metrics there atomically;
* checkpoint extras: python/numpy/torch RNG states, the stage and `extra_state()`, restored by
  `on_load_checkpoint` *before* Lightning applies the state dict (so subclasses can resize
  parameters whose size changed, e.g. Gaussians added by an edit).

`GaussianSystem` adds what every system that optimises a GaussianModel shares: the learning rates
(`system.lr`) and the Adam optimizer built from them.

Paths are deliberately not stored in checkpoints: resuming in the same (or a moved) trial dir
writes where launch.py says.
"""
from __future__ import annotations

import json
import logging
import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence

import lightning
import numpy as np
import torch
import torch.utils.data

from gs_regional.config import parse_structured
from gs_regional.geometry.gaussian_model import LearningRates
from gs_regional.systems import parallel
from gs_regional.utils import visualize
from gs_regional.utils.io import write_json_atomic

log = logging.getLogger(__name__)

CHECKPOINT_KEY = "gs_regional"


def capture_rng_state() -> Dict[str, Any]:
    """Python, numpy and torch (CPU and CUDA) global RNG states, in types that `torch.load`
    accepts with weights_only=True (numpy's key array is stored as a tensor)."""
    np_name, np_keys, np_pos, np_has_gauss, np_gauss = np.random.get_state()
    state: Dict[str, Any] = {
        "python": random.getstate(),
        "numpy": {
            "name": np_name,
            "keys": torch.from_numpy(np_keys.astype(np.int64)),
            "pos": int(np_pos),
            "has_gauss": int(np_has_gauss),
            "gauss": float(np_gauss),
        },
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: Mapping[str, Any]) -> None:
    if "python" in state:
        version, internal, gauss = state["python"]
        random.setstate((version, tuple(internal), gauss))
    if "numpy" in state:
        s = state["numpy"]
        keys = np.asarray(torch.as_tensor(s["keys"]).numpy(), dtype=np.uint32)
        np.random.set_state((s["name"], keys, s["pos"], s["has_gauss"], s["gauss"]))
    if "torch" in state:
        torch.set_rng_state(torch.as_tensor(state["torch"], dtype=torch.uint8).cpu())
    if "cuda" in state and torch.cuda.is_available():
        cuda_states = list(state["cuda"])
        if len(cuda_states) == torch.cuda.device_count():
            torch.cuda.set_rng_state_all(cuda_states)
        else:
            log.warning(
                "checkpoint has CUDA RNG states for %d devices, this machine has %d: not restored",
                len(cuda_states), torch.cuda.device_count(),
            )


class BaseSystem(lightning.LightningModule):
    @dataclass
    class Config:
        pass

    cfg: Any

    def __init__(self, cfg: Any = None, resumed: bool = False) -> None:
        super().__init__()
        self.cfg = parse_structured(self.Config, cfg, where="system")
        self.resumed = resumed
        self.automatic_optimization = False
        self.stage = ""
        self._trial_dir: Optional[Path] = None
        self._datamodule = None

    # ----- stage and step budget -------------------------------------------------------------
    def set_stage(self, name: str) -> None:
        """Name what the system is doing now; shown in the progress bar and logged on change."""
        if name != self.stage:
            log.info("stage: %s", name)
        self.stage = name

    @property
    def total_steps(self) -> Optional[int]:
        """Steps a full run takes (launch.py's default for trainer.max_steps); None if unknown."""
        steps = getattr(self.cfg, "max_steps", None)
        return int(steps) if steps is not None else None

    # ----- directories -----------------------------------------------------------------------
    def set_trial_dir(self, path: Any) -> None:
        self._trial_dir = Path(path)

    @property
    def trial_dir(self) -> Path:
        if self._trial_dir is None:
            raise RuntimeError(
                f"{type(self).__name__} has no trial directory: call system.set_trial_dir(path) "
                "before training (launch.py does this)"
            )
        return self._trial_dir

    @property
    def save_dir(self) -> Path:
        d = self.trial_dir / "save"
        d.mkdir(parents=True, exist_ok=True)
        return d

    def save_path(self, name: str) -> Path:
        """`<trial>/save/<name>`, with its parent folders created. `name` must stay inside save/."""
        p = Path(name)
        if p.is_absolute() or ".." in p.parts:
            raise ValueError(f"output name '{name}' must be a relative path inside the save directory")
        out = self.save_dir / p
        out.parent.mkdir(parents=True, exist_ok=True)
        return out

    # ----- data --------------------------------------------------------------------------------
    def attach_datamodule(self, datamodule: Any) -> None:
        """Give the system its datamodule outside fit/validate/test (used by --export)."""
        self._datamodule = datamodule

    def attached_trainer(self) -> Optional["lightning.Trainer"]:
        """The trainer, or None outside fit/validate/test (Lightning's public `trainer` raises then)."""
        try:
            return self.trainer
        except RuntimeError:
            return None

    @property
    def datamodule(self) -> Any:
        trainer = self.attached_trainer()
        if trainer is not None and getattr(trainer, "datamodule", None) is not None:
            return trainer.datamodule
        return self._datamodule

    # ----- outputs -----------------------------------------------------------------------------
    # With several processes (systems/parallel.py) rank 0 alone writes: the helpers below do
    # nothing elsewhere (and return the path rank 0 writes).
    @property
    def writes_outputs(self) -> bool:
        """Whether this process writes the run's outputs: always with one process, rank 0 of several."""
        return parallel.is_rank_zero(self)

    def save_image(self, name: str, img: Any) -> str:
        """Write an (H, W, 3) image in [0, 1] (tensor or array) to save/<name>; returns the path."""
        if not self.writes_outputs:
            return str(self.trial_dir / "save" / name)
        return visualize.save_image(self.save_path(name), img)

    def save_image_grid(self, name: str, rows: Sequence[Sequence[Any]], labels=None) -> str:
        """Tile `rows` (a list of lists of images) into one image at save/<name>."""
        if not self.writes_outputs:
            return str(self.trial_dir / "save" / name)
        return visualize.save_image(self.save_path(name), visualize.make_grid(rows, labels=labels))

    def save_video(self, name: str, frames: Sequence[Any], fps: float = 24) -> str:
        """Write an mp4 (or, without ffmpeg, a GIF beside it) to save/<name>; returns the path."""
        if not self.writes_outputs:
            return str(self.trial_dir / "save" / name)
        return visualize.save_video(self.save_path(name), frames, fps=fps)

    def log_metrics(self, metrics: Mapping[str, Any], step: Optional[int] = None) -> None:
        """Send scalars straight to the run's loggers (the CSV log), at `step` (default: global step)."""
        trainer = self.attached_trainer()
        if trainer is None or not trainer.loggers:
            return
        values = {k: float(v.detach().cpu().item() if isinstance(v, torch.Tensor) else v) for k, v in metrics.items()}
        for logger in trainer.loggers:
            logger.log_metrics(values, step=self.global_step if step is None else step)

    def write_metrics_json(self, metrics: Mapping[str, Any], merge: bool = True) -> str:
        """Write save/metrics.json atomically. With `merge`, keys already in the file (from earlier
        stages, or the run before a resume) are kept unless `metrics` replaces them."""
        if not self.writes_outputs:
            return str(self.trial_dir / "save" / "metrics.json")
        path = self.save_path("metrics.json")
        data: Dict[str, Any] = {}
        if merge and path.exists():
            try:
                with open(path, encoding="utf-8") as f:
                    data = json.load(f)
            except (OSError, ValueError) as e:
                log.warning("could not read %s (%s); rewriting it", path, e)
                data = {}
        data.update(metrics)
        write_json_atomic(path, data)
        return str(path)

    # ----- export --------------------------------------------------------------------------------
    def on_export(self) -> None:
        """What `launch.py --export` does, after the `resume=` checkpoint is loaded. Override it."""
        raise NotImplementedError(f"system '{getattr(self, 'registered_name', type(self).__name__)}' has no export")

    # --export runs Lightning's predict loop (so setup() and checkpoint loading happen as in fit):
    # one dummy batch unless the datamodule has its own predict_dataloader, then on_export().
    def predict_dataloader(self):
        return torch.utils.data.DataLoader([0], batch_size=1)

    def predict_step(self, batch: Any, batch_idx: int) -> None:
        return None

    def on_predict_end(self) -> None:
        self.on_export()

    # ----- checkpoints -------------------------------------------------------------------------
    def extra_state(self) -> Dict[str, Any]:
        """Extra state saved in checkpoints (tensors, numbers, strings, lists, dicts). Extend it."""
        return {}

    def load_extra_state(self, state: Dict[str, Any]) -> None:
        """Restore `extra_state()`; runs before the state dict is loaded into the module."""

    def save_stage_checkpoint(self) -> None:
        """Checkpoint now, inside a training step, at the end of a stage (e.g. localization) that
        the step goes on from: a resume repeats the step from where this left it (the system's
        own state says which stage comes next) with the RNG as it is now. Needs the run's
        checkpoint callback (launch.py's), otherwise does nothing."""
        trainer = self.attached_trainer()
        callback = getattr(trainer, "checkpoint_callback", None) if trainer is not None else None
        if callback is None or not hasattr(callback, "save_now"):
            return
        self._mid_step_save = True
        try:
            callback.save_now(trainer)
        finally:
            self._mid_step_save = False

    def on_save_checkpoint(self, checkpoint: Dict[str, Any]) -> None:
        mid_step = getattr(self, "_mid_step_save", False)
        checkpoint[CHECKPOINT_KEY] = {
            "stage": self.stage,
            "rng": capture_rng_state(),
            "rng_restore": "at_load" if self._saved_at_epoch_end() and not mid_step else "before_next_step",
            "extra": self.extra_state(),
        }

    def on_load_checkpoint(self, checkpoint: Dict[str, Any]) -> None:
        state = checkpoint.get(CHECKPOINT_KEY)
        if state is None:
            log.warning("checkpoint has no gs_regional state (RNG, stage); resuming without it")
            return
        self.stage = state.get("stage", "")
        self.load_extra_state(state.get("extra", {}))
        # Where the RNG state is put back decides whether a resumed run draws the same numbers as
        # an uninterrupted one. The state was captured right after a step. If that step ended an
        # epoch, the uninterrupted run then made a new DataLoader iterator (which may draw from the
        # global RNG) before the next step, and so does the resumed run: restore now. Otherwise
        # (mid-epoch, endless datasets) the uninterrupted run went straight on to the next step,
        # while the resumed run makes an iterator first: restore just before the next step.
        if state.get("rng_restore", "at_load") == "at_load":
            restore_rng_state(state.get("rng", {}))
        else:
            self._pending_rng = state.get("rng", {})

    def on_train_batch_start(self, batch: Any, batch_idx: int) -> None:
        """Subclasses that override this must call super() (it restores the RNG on resume)."""
        pending = self.__dict__.pop("_pending_rng", None)
        if pending is not None:
            restore_rng_state(pending)

    def _saved_at_epoch_end(self) -> bool:
        trainer = self.attached_trainer()
        try:  # public loop attributes; absent (None trainer, other loop layout) means "not at the end"
            return bool(trainer.fit_loop.epoch_loop.batch_progress.is_last_batch)
        except AttributeError:
            return False


class GaussianSystem(BaseSystem):
    """A system that optimises the Gaussians `self.geometry` of the scene `self.scene` with Adam
    (manual optimisation: subclasses call `self.optimizers()` in their training step)."""

    @dataclass
    class Config:
        lr: LearningRates = field(default_factory=LearningRates)  # the `means` rate is x the scene extent

    def configure_optimizers(self):
        groups = self.geometry.optimizer_param_groups(self.cfg.lr, spatial_scale=self.scene.extent)
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15)
