"""`python launch.py --studio [--config X.yaml] [--port 8080] [--host 127.0.0.1] [key=value ...]`:
edit from the browser (docs/studio.md). One page: an instruction, Select region (localization
alone, its selection highlighted with the views' relevance maps), a Threshold that re-lifts the
selection from the saved evidence, clicks on the scene that add to or remove from it, Edit and
Stop, before/after, the metrics and the downloads. The state lives in the server
(session.py: StudioSession); the page (page.py) shows it. Needs the `viewer` extra (viser).

Each run is a normal trial of launch.py (gs_regional.localize / gs_regional.edit in this
process): `--view`, `--export` and `resume=` work on it, and its cmd.txt re-runs it.
"""
from gs_regional.studio.cli import build_parser, main

__all__ = ["build_parser", "main"]
