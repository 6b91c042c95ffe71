"""The Lightning callbacks of a run, built on Lightning's public API only (callback hooks,
`Trainer.save_checkpoint`, documented attributes), so that a Lightning upgrade cannot break resume."""
from __future__ import annotations

import sys
from typing import Any, Dict, Optional

from lightning.pytorch.callbacks import ModelCheckpoint, TQDMProgressBar
from lightning.pytorch.callbacks.progress.tqdm_progress import Tqdm


class TrialCheckpoint(ModelCheckpoint):
    """ModelCheckpoint whose `last.ckpt` always holds the end of training, written after the
    system's outputs.

    ModelCheckpoint writes `last.ckpt` every `every_n_train_steps` steps. The checkpoint of the
    last step is written here once the system's `on_train_end` (which writes its outputs) has
    returned: a run killed while writing its outputs resumes from the checkpoint before, so the
    resume trains the last steps again and writes the outputs (a checkpoint of the last step
    would resume to a finished loop that Lightning skips, outputs and all). The checkpoint also
    holds the run's config (`run_config`, compared on resume), and `save_now` lets a system
    checkpoint a stage boundary inside a step.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.run_config: Optional[Dict[str, Any]] = None
        self.train_ended = False

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: Dict[str, Any]) -> None:
        super().on_save_checkpoint(trainer, pl_module, checkpoint)
        if self.run_config is not None:
            from gs_regional.launch.checkpoints import CONFIG_KEY

            checkpoint[CONFIG_KEY] = self.run_config

    def last_checkpoint_path(self) -> str:
        return self.last_model_path or self.format_checkpoint_name({}, self.CHECKPOINT_NAME_LAST)

    def save_now(self, trainer) -> None:
        """Write `last.ckpt` now (a system marks the end of a stage inside a training step)."""
        if self.save_last and not trainer.fast_dev_run:
            trainer.save_checkpoint(self.last_checkpoint_path(), self.save_weights_only)

    @staticmethod
    def _at_last_step(trainer) -> bool:
        return trainer.max_steps is not None and trainer.max_steps > 0 and trainer.global_step >= trainer.max_steps

    def on_train_batch_end(self, trainer, *args: Any, **kwargs: Any) -> None:
        if not self._at_last_step(trainer):  # the last step's checkpoint comes after the outputs
            super().on_train_batch_end(trainer, *args, **kwargs)

    def on_train_epoch_end(self, trainer, *args: Any, **kwargs: Any) -> None:
        if not self._at_last_step(trainer):
            super().on_train_epoch_end(trainer, *args, **kwargs)

    def on_train_end(self, trainer, pl_module) -> None:
        # Not ModelCheckpoint's (it writes last.ckpt now, before the system's outputs).
        self.train_ended = True  # the system's own on_train_end runs next

    def on_fit_end(self, trainer, pl_module) -> None:
        # After the system's on_train_end (Lightning calls it between the callbacks' on_train_end
        # and on_fit_end): only a run whose training loop ran in this process; a resumed run whose
        # checkpoint was already final has nothing new to write.
        if self.train_ended and trainer.global_step > 0:
            self.save_now(trainer)


class StageProgressBar(TQDMProgressBar):
    """One bar over all training steps (systems run one endless epoch, or many short ones),
    described by the system's current stage, e.g. 'refine 2/3'."""

    @staticmethod
    def counts_steps(trainer) -> bool:
        return trainer.max_steps is not None and trainer.max_steps > 0

    @classmethod
    def describe(cls, trainer, pl_module) -> str:
        stage = getattr(pl_module, "stage", "") or ""
        if stage:
            return stage
        return "start" if cls.counts_steps(trainer) else f"Epoch {trainer.current_epoch}"

    def init_train_tqdm(self) -> Tqdm:
        trainer = self.trainer
        if not self.counts_steps(trainer):
            return super().init_train_tqdm()
        # Created with its total, first step (a resumed run's) and stage: nothing to reset later.
        return Tqdm(
            desc=self.describe(trainer, trainer.lightning_module),
            total=trainer.max_steps,
            initial=trainer.global_step,
            position=2 * self.process_position,
            disable=self.is_disabled,
            leave=True,
            dynamic_ncols=True,
            file=sys.stdout,
            smoothing=0,
            bar_format=self.BAR_FORMAT,
        )

    def on_train_epoch_start(self, trainer, *args) -> None:
        if not self.counts_steps(trainer):
            super().on_train_epoch_start(trainer, *args)
            pl_module = args[0] if args else trainer.lightning_module
            self.train_progress_bar.set_description(self.describe(trainer, pl_module))

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if not self.counts_steps(trainer):
            super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
            self.train_progress_bar.set_description(self.describe(trainer, pl_module))
            return
        bar, n = self.train_progress_bar, trainer.global_step
        if bar is None or bar.disable or not (n % self.refresh_rate == 0 or n >= bar.total):
            return
        bar.n = n
        bar.set_postfix(self.get_metrics(trainer, pl_module), refresh=False)
        bar.set_description(self.describe(trainer, pl_module), refresh=False)
        bar.refresh()

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        if not self.counts_steps(trainer):
            super().on_train_epoch_end(trainer, pl_module)
