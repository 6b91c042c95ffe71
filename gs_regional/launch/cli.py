"""The command line of `launch.py`: arguments, logging, and mistakes turned into one line
`error: ...` with exit code 2 (`--debug` shows the traceback instead). It parses; run.py executes
(cli imports run, never the other way; what both need is in modes.py)."""
from __future__ import annotations

import argparse
import sys
from typing import Any, List, Optional, Sequence

from gs_regional.launch.errors import is_user_error
from gs_regional.launch.logs import setup_logging
from gs_regional.launch.modes import EXPORT_CHOICES, MODES


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="launch.py",
        description="Run a gs_regional experiment: python launch.py --config X.yaml --train [key=value ...]",
        epilog="View an edit run in the browser: python launch.py --view TRIAL_DIR [--port 8080]; edit from the "
               "browser: python launch.py --studio [--config X.yaml] (both need the 'viewer' extra; "
               "--view --help and --studio --help list their options)",
    )
    p.add_argument("--config", required=True, help="YAML experiment config")
    mode = p.add_mutually_exclusive_group()
    helps = {
        "train": "train (resume=<ckpt> continues a run)",
        "validate": "run the validation loop (on resume=<ckpt>)",
        "test": "run the test loop (on resume=<ckpt>)",
    }
    for m in MODES[:-1]:
        mode.add_argument(f"--{m}", action="store_true", help=helps[m])
    # --export alone is a mode; `--train --export region` trains and also writes the region's files.
    p.add_argument("--export", nargs="?", const="scene", choices=EXPORT_CHOICES, default=None,
                   help="alone: load resume=<ckpt> and call the system's on_export(); 'region' also writes "
                        "the edited region's Gaussians alone (system.export.region=true), with --export or --train")
    p.add_argument("--gpu", default=None, help="CUDA device index (e.g. 0); a list (0,1,2,3) shares the edit over "
                                               "those GPUs; without it the run uses the CPU")
    p.add_argument("--custom-dir", default=None, help="plugin folder (default: custom/ beside launch.py)")
    p.add_argument("--verbose", action="store_true",
                   help="show every log line, Lightning's messages and model summary, and all warnings")
    p.add_argument("--debug", action="store_true", help="--verbose, and tracebacks instead of one-line errors")
    return p


def _explicit_export(argv: Sequence[str]) -> List[str]:
    """A bare `--export` made `--export=scene`, so that argparse never takes the `key=value` after
    it as the optional word (`--export region`)."""
    return [
        "--export=scene" if tok == "--export" and (i + 1 == len(argv) or argv[i + 1] not in EXPORT_CHOICES) else tok
        for i, tok in enumerate(argv)
    ]


def main(argv: Optional[Sequence[str]] = None, custom_dir: Any = None) -> int:
    """Run launch.py with `argv` (default: sys.argv[1:]); returns the exit code.

    `custom_dir` is the default plugin folder (launch.py passes the one beside itself).
    Mistakes in the config, command line or input files print `error: ...` and return 2;
    other errors propagate with their traceback.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a == "--view" or a.startswith("--view=") for a in argv):
        from gs_regional.launch.view import main as view_main  # viser only when viewing

        return view_main(argv, custom_dir)
    parser = build_parser()
    try:
        args, extra = parser.parse_known_args(_explicit_export(argv))
    except SystemExit as e:  # argparse already printed the usage and the error
        return int(e.code or 0)
    if not any(getattr(args, m) for m in MODES):
        parser.print_usage(sys.stderr)
        sys.stderr.write("error: one of the arguments --train --validate --test --export is required\n")
        return 2
    if args.export is not None and (args.validate or args.test):
        parser.print_usage(sys.stderr)
        sys.stderr.write("error: --export goes alone or with --train\n")
        return 2
    bad = [x for x in extra if "=" not in x]
    if bad:
        parser.print_usage(sys.stderr)
        sys.stderr.write(f"error: unrecognized arguments: {' '.join(bad)} (overrides are key=value)\n")
        return 2
    from gs_regional.launch.run import run  # imports Lightning: after the quick argument checks

    setup_logging(verbose=args.verbose or args.debug)  # after Lightning's import sets its own levels

    try:
        return run(args, extra, argv, custom_dir)
    except Exception as e:
        if args.debug or not is_user_error(e):
            raise
        sys.stderr.write(f"error: {e}\n")
        return 2
