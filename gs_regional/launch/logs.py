"""Console output of a run: quiet by default, everything with `--verbose` / `--debug`.

Quiet: warnings and errors of every gs_regional module, the launcher's own few lines, the
config's notes, the progress (a bar on a terminal, lines otherwise: callbacks.py) and the
end-of-run summary. Lightning's info lines (seed, GPU/TPU availability,
tips, "max_steps reached"), its model summary and known third-party warning noise are hidden.
Log lines are written with `tqdm.write`, so they never break a progress bar.
"""
from __future__ import annotations

import logging
import sys
import warnings

LIGHTNING_LOGGERS = ("lightning.pytorch", "lightning.fabric")


class _ConsoleHandler(logging.Handler):
    """Writes to whatever sys.stderr is now (it may be replaced, e.g. by test capture), above
    any progress bar."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            from tqdm import tqdm

            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:
            self.handleError(record)


class _ConsoleFormatter(logging.Formatter):
    """Info lines as they are; others prefixed 'warning: ', 'error: ', 'debug: '."""

    def __init__(self, verbose: bool) -> None:
        super().__init__("%(message)s")
        self.verbose = verbose

    def format(self, record: logging.LogRecord) -> str:
        msg = super().format(record)
        if self.verbose and record.levelno != logging.INFO:
            return f"{record.levelname.lower()} [{record.name}]: {msg}"
        return msg if record.levelno == logging.INFO else f"{record.levelname.lower()}: {msg}"


def setup_logging(verbose: bool) -> None:
    """Levels and the console handler of the `gs_regional` loggers, and Lightning's levels."""
    package = logging.getLogger("gs_regional")
    package.setLevel(logging.DEBUG if verbose else logging.WARNING)
    logging.getLogger("gs_regional.launch").setLevel(logging.DEBUG if verbose else logging.INFO)
    # The config's notes say what the command line changed (keys dropped by a `*_type` switch).
    logging.getLogger("gs_regional.config").setLevel(logging.DEBUG if verbose else logging.INFO)
    handler = next((h for h in package.handlers if isinstance(h, _ConsoleHandler)), None)
    if handler is None:
        handler = _ConsoleHandler()
        package.addHandler(handler)
    handler.setFormatter(_ConsoleFormatter(verbose))
    for name in LIGHTNING_LOGGERS:
        logging.getLogger(name).setLevel(logging.INFO if verbose else logging.WARNING)


def filter_warnings(verbose: bool) -> None:
    """Warning filters of a run; call inside `warnings.catch_warnings()`."""
    # Expected with our systems, whatever the verbosity: Lightning warns on every
    # manual-optimisation checkpoint that it holds the state after the optimizer step (exactly
    # what we resume from), and --export's predict step returns nothing.
    warnings.filterwarnings("ignore", message="Using ModelCheckpoint with manual optimization")
    warnings.filterwarnings("ignore", message="predict returned None")
    if verbose:
        return
    # The scene datamodules offer held-out views to any system; ours evaluate in their own hooks.
    warnings.filterwarnings("ignore", message=r"You passed in a `val_dataloader` but have no `validation_step`")
    # Lightning's own use of APIs its dependencies deprecate (e.g. torch's pytree LeafSpec):
    # nothing a user of gs_regional can act on.
    for category in (DeprecationWarning, FutureWarning):
        warnings.filterwarnings("ignore", category=category, module=r"lightning(\.|$)")
