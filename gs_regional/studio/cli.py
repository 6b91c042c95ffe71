"""The studio's command line: `launch.py --studio [--config X.yaml] [options] [key=value ...]`.
Mistakes on the command line or in the config end with one line `error: ...` and exit code 2; a
scene that fails to load is said on the page (the server stays up)."""
from __future__ import annotations

import argparse
import sys
import time
from typing import Any, Sequence

DEFAULT_CONFIG = "configs/demo.yaml"  # the built-in synthetic scene, edited by the simulated editor


def build_parser() -> argparse.ArgumentParser:
    from gs_regional.launch.view import DEFAULT_MAX_GAUSSIANS

    p = argparse.ArgumentParser(
        prog="launch.py",
        description="Edit from the browser: python launch.py --studio [--config X.yaml] [--port 8080] [key=value ...]",
    )
    p.add_argument("--studio", action="store_true", required=True, help="serve the studio")
    p.add_argument("--config", default=DEFAULT_CONFIG,
                   help=f"the edit's YAML config, as for --train (default {DEFAULT_CONFIG}: the built-in synthetic scene)")
    p.add_argument("--port", type=int, default=8080, help="port to serve on (default 8080)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1; 0.0.0.0: every interface)")
    p.add_argument("--max-gaussians", type=int, default=DEFAULT_MAX_GAUSSIANS,
                   help=f"show a random subsample of this many Gaussians above it (default {DEFAULT_MAX_GAUSSIANS:,}; 0: all)")
    p.add_argument("--gpu", default=None, help="CUDA device index for the runs, as launch.py's --gpu (without it: the CPU)")
    p.add_argument("--custom-dir", default=None, help="plugin folder (default: custom/ beside launch.py)")
    p.add_argument("--debug", action="store_true", help="tracebacks instead of one-line errors")
    return p


def main(argv: Sequence[str], custom_dir: Any = None) -> int:
    """Serve the studio until interrupted; mistakes end with one line and exit code 2."""
    from gs_regional.api import _config_path
    from gs_regional.launch.errors import is_user_error
    from gs_regional.launch.logs import setup_logging
    from gs_regional.launch.view import serve_until_interrupted, viewer_missing

    try:
        args, extra = build_parser().parse_known_args(list(argv))
    except SystemExit as e:
        return int(e.code or 0)
    missing = viewer_missing("the studio")
    if missing:
        sys.stderr.write(f"error: {missing}\n")
        return 2
    bad = [x for x in extra if "=" not in x]
    if bad:
        sys.stderr.write(f"error: unrecognized arguments: {' '.join(bad)} (overrides are key=value)\n")
        return 2
    config = _config_path(args.config)
    if not config.is_file():
        sys.stderr.write(f"error: config file not found: {args.config}\n")
        return 2
    setup_logging(verbose=args.debug)
    from gs_regional.studio.page import serve
    from gs_regional.studio.session import StudioSession

    try:
        started = time.perf_counter()
        session = StudioSession.open(config, extra, args.custom_dir or custom_dir, gpu=args.gpu)
        studio = serve(session, host=args.host, port=args.port, max_gaussians=args.max_gaussians)
    except Exception as e:
        if args.debug or not (isinstance(e, OSError) or is_user_error(e)):
            raise
        sys.stderr.write(f"error: {e}\n")
        return 2
    print(f"studio of {config} ready in {time.perf_counter() - started:.1f} s: {studio.url}  (Ctrl+C stops it)", flush=True)
    return serve_until_interrupted(studio)
