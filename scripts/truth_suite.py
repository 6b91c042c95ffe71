#!/usr/bin/env python
"""A truth suite that cannot be memorized: known edits drawn at random from a seed it prints
(gs_regional/bench/truth/; --help says what it draws, runs and reports).

    python scripts/truth_suite.py [--seed N] [--cases 24] [--quick] [--out outputs/truth_suite] [key=value ...]
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.truth.cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
