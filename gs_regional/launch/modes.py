"""The modes of launch.py, shared by the command line that parses them (cli.py) and the run that
executes them (run.py): the package flows one way, cli -> run, and both read this module."""
from __future__ import annotations

import argparse

MODES = ("train", "validate", "test", "export")
EXPORT_CHOICES = ("scene", "region")
# The Lightning stage each mode runs (the argument of DataModule.setup).
STAGES = {"train": "fit", "validate": "validate", "test": "test", "export": "predict"}


def run_mode(args: argparse.Namespace) -> str:
    """The mode of parsed arguments: --train, --validate or --test, else --export."""
    return next(m for m in MODES if getattr(args, m))
