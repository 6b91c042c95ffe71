"""The Lightning callbacks of a run, built on Lightning's public API only (callback hooks,
`Trainer.save_checkpoint`, documented attributes), so that a Lightning upgrade cannot break resume."""
from __future__ import annotations

import sys
from typing import Any, Dict, Optional

from lightning.pytorch.callbacks import ModelCheckpoint, TQDMProgressBar
from lightning.pytorch.callbacks.progress.tqdm_progress import Tqdm


class TrialCheckpoint(ModelCheckpoint):
    """ModelCheckpoint whose `last.ckpt` always holds the end of training.

    ModelCheckpoint writes `last.ckpt` every `every_n_train_steps` steps, and at the end of
    training only if it wrote none during the run; a run that ends between two checkpoint steps
    (5 steps, every 2) would resume from step 4. This writes the final step with the public
    `Trainer.save_checkpoint` unless a checkpoint of that step was just written.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.saved_at_step: Optional[int] = None

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: Dict[str, Any]) -> None:
        # Called for every full checkpoint the trainer writes (with save_weights_only Lightning
        # skips this hook: then the final step may be written twice, which is only redundant).
        super().on_save_checkpoint(trainer, pl_module, checkpoint)
        self.saved_at_step = trainer.global_step

    def last_checkpoint_path(self) -> str:
        return self.last_model_path or self.format_checkpoint_name({}, self.CHECKPOINT_NAME_LAST)

    def on_train_end(self, trainer, pl_module) -> None:
        super().on_train_end(trainer, pl_module)
        if (
            self.save_last
            and trainer.global_step > 0
            and self.saved_at_step != trainer.global_step
            and not trainer.fast_dev_run
        ):
            trainer.save_checkpoint(self.last_checkpoint_path(), self.save_weights_only)


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
