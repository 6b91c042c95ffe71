"""The Lightning callbacks of a run, built on Lightning's public API only (callback hooks,
`Trainer.save_checkpoint`, documented attributes), so that a Lightning upgrade cannot break resume.

Progress: a bar on a terminal (`StageProgressBar`), whole lines anywhere else (`StageProgressLines`:
a log file or CI would get every carriage-return redraw of a bar); `progress_callback` picks one."""
from __future__ import annotations

import sys
import time
from typing import Any, Dict, Optional, TextIO

from lightning.pytorch.callbacks import Callback, ModelCheckpoint, ProgressBar, TQDMProgressBar
from lightning.pytorch.callbacks.progress.tqdm_progress import Tqdm


class FitStartClock(Callback):
    """When Lightning's fit reached the system's `on_fit_start` (callbacks' hooks run first): the
    time from `trainer.fit` to here is Lightning's set-up (strategy, device moves, the system's
    `setup`)."""

    def __init__(self) -> None:
        self.at: Optional[float] = None

    def on_fit_start(self, trainer, pl_module) -> None:
        self.at = time.perf_counter()


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


def counts_steps(trainer) -> bool:
    """Whether progress is counted in steps of `max_steps` (else in batches of each epoch)."""
    return trainer.max_steps is not None and trainer.max_steps > 0


def describe(trainer, pl_module) -> str:
    """The system's current stage (e.g. 'refine 2/3'), or what stands for it before the first."""
    stage = getattr(pl_module, "stage", "") or ""
    if stage:
        return stage
    return "start" if counts_steps(trainer) else f"Epoch {trainer.current_epoch}"


def progress_callback(stream: Optional[TextIO] = None) -> ProgressBar:
    """The progress display for `stream` (default: sys.stdout, where both write): a bar on a
    terminal, lines elsewhere."""
    stream = sys.stdout if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    return StageProgressBar() if callable(isatty) and isatty() else StageProgressLines()


class StageProgressBar(TQDMProgressBar):
    """One bar over all training steps (systems run one endless epoch, or many short ones),
    described by the system's current stage, e.g. 'refine 2/3'."""

    counts_steps = staticmethod(counts_steps)
    describe = staticmethod(describe)

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


class StageProgressLines(ProgressBar):
    """Progress as whole lines on sys.stdout, for output that is not a terminal (a log file, CI):
    a line when the system's stage changes and one at each tenth of the run's steps (of the
    batches of an epoch, or of a validation, test or --export loop), e.g.

        refine 2/3: 12/30 steps (40%), 00:21

    and never a carriage return. The stage is read at step boundaries and at each checkpoint (a
    system checkpoints the end of a stage inside a step, `save_stage_checkpoint`, and the last
    checkpoint follows its outputs): a stage that begins and ends inside one step without a
    checkpoint has no line of its own."""

    PARTS = 10  # lines per loop, besides the stage changes

    def __init__(self) -> None:
        super().__init__()
        self._enabled = True
        self._started = time.monotonic()
        self._stage: Optional[str] = None  # the stage of the last training line
        self._part = -1  # the last tenth of the training loop written
        self._batches = 0  # batches done in this epoch (runs without max_steps)
        self._eval_part = -1

    # ----- Lightning's ProgressBar interface
    @property
    def is_enabled(self) -> bool:
        return self._enabled

    def disable(self) -> None:
        self._enabled = False

    def enable(self) -> None:
        self._enabled = True

    def _write(self, text: str) -> None:
        if self._enabled:
            print(text, file=sys.stdout, flush=True)  # sys.stdout as it is now (test capture replaces it)

    def _line(self, what: str, done: int, total: Any, unit: str) -> str:
        elapsed = Tqdm.format_interval(time.monotonic() - self._started)
        if total is None or total == float("inf") or total <= 0:
            return f"{what}: {done} {unit}, {elapsed}"
        return f"{what}: {done}/{int(total)} {unit} ({100 * done // int(total)}%), {elapsed}"

    @staticmethod
    def _tenth(done: int, total: Any) -> int:
        if total is None or total == float("inf") or total <= 0:
            return -1
        return min(StageProgressLines.PARTS, done * StageProgressLines.PARTS // int(total))

    # ----- training
    def _train_report(self, trainer, pl_module, force: bool = False) -> None:
        if counts_steps(trainer):
            done, total, unit = trainer.global_step, trainer.max_steps, "steps"
        else:
            done, total, unit = self._batches, self.total_train_batches, "batches"
        stage, part = describe(trainer, pl_module), self._tenth(done, total)
        if force or stage != self._stage or part > self._part:
            self._write(self._line(stage, done, total, unit))
            self._stage, self._part = stage, max(part, self._part)

    def on_train_start(self, trainer, pl_module) -> None:
        self._started = time.monotonic()
        self._stage, self._part = None, -1
        self._train_report(trainer, pl_module, force=True)  # a resumed run starts at its step and stage

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        if not counts_steps(trainer):  # each epoch counts its own batches
            self._batches, self._part = 0, -1

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._train_report(trainer, pl_module)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self._batches = batch_idx + 1
        self._train_report(trainer, pl_module)

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: Dict[str, Any]) -> None:
        if trainer.training:  # e.g. a stage that ended inside a step
            self._train_report(trainer, pl_module)

    # ----- validation, test, --export (predict)
    # Loops by their description and the ProgressBar property that counts their batches.
    _EVAL = {"validation": ("validation_description", "total_val_batches_current_dataloader"),
             "test": ("test_description", "total_test_batches_current_dataloader"),
             "predict": ("predict_description", "total_predict_batches_current_dataloader")}

    def _eval_report(self, loop: str, done: int, dataloader_idx: int) -> None:
        """A line when a loop (or its next dataloader) starts, then at each tenth of its batches."""
        description, total_name = self._EVAL[loop]
        if self.has_dataloader_changed(dataloader_idx):  # also selects the dataloader whose total is read
            self._eval_part = -1
        total = getattr(self, total_name)
        part = self._tenth(done, total)  # -1 for an unknown total: the start line only
        if (done == 0 and self._eval_part == -1) or part > self._eval_part:
            self._eval_part = max(part, 0)
            self._write(self._line(getattr(self, description), done, total, "batches"))

    def on_validation_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0) -> None:
        if not trainer.sanity_checking:
            self._eval_report("validation", batch_idx, dataloader_idx)

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        if not trainer.sanity_checking:
            self._eval_report("validation", batch_idx + 1, dataloader_idx)

    def on_validation_end(self, trainer, pl_module) -> None:
        self.reset_dataloader_idx_tracker()

    def on_test_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0) -> None:
        self._eval_report("test", batch_idx, dataloader_idx)

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self._eval_report("test", batch_idx + 1, dataloader_idx)

    def on_test_end(self, trainer, pl_module) -> None:
        self.reset_dataloader_idx_tracker()

    def on_predict_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0) -> None:
        self._eval_report("predict", batch_idx, dataloader_idx)

    def on_predict_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self._eval_report("predict", batch_idx + 1, dataloader_idx)

    def on_predict_end(self, trainer, pl_module) -> None:
        self.reset_dataloader_idx_tracker()
