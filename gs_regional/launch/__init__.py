"""What `launch.py` does (threestudio-style), importable so that tests and scripts run it in-process.

    python launch.py --config X.yaml (--train|--validate|--test|--export) [--gpu N] [key=value ...]

1. import every module and package under `custom/` (plugins register components)   plugins.py
2. read the YAML, apply the overrides (`section=null` clears a section; a `*_type`
   changed on the command line drops the keys its new type does not take)           run.py, sections.py
3. seed, read the scene (`data_type`), check the system's input files and settings,
   load and compare a `resume=` checkpoint, then build the system (`system_type`)
   with its priors: bad config, input files, prior folders or checkpoints stop here,
   before any trial dir exists and before any model is loaded (with CUDA the priors
   then load on a background thread until the first stage waits for them; weights
   that fail to load end the run there, the trial dir removed)                       run.py, checkpoints.py
4. make the trial directory `<exp_root_dir>/<name>/<tag>@<timestamp>` (or reuse the
   one of a `resume=<trial>/ckpts/last.ckpt`), locked against a second writer, with
   configs/parsed.yaml, configs/raw.yaml and cmd.txt                                 trial.py
5. run a Lightning Trainer (last.ckpt in ckpts/, written atomically, the previous one
   kept; CSV logs in csv_logs/; progress named after the system's stage: a bar on a
   terminal, a line per stage and per tenth of the steps otherwise)                  callbacks.py, checkpoints.py
6. print a summary: what ran, seconds per stage, Gaussians, key metrics, output paths summary.py

The console is quiet by default (`--verbose` shows everything; logs.py). Mistakes in the config,
the command line or the input files end with one line `error: ...` and exit code 2 (`--debug`
shows the traceback; errors.py, cli.py), a checkpoint written to a full disk included. cli.py
parses the command line and calls run.py, never the other way; both read modes.py.
"""
from gs_regional.launch.cli import build_parser, main
from gs_regional.launch.plugins import load_plugins

__all__ = ["build_parser", "main", "load_plugins"]
