#!/usr/bin/env python
"""The Gaussians an edit adds against its quality over the densification and pruning knobs
(gs_regional/bench/compactness.py; --help says what it runs and writes).

    python scripts/compactness.py [--quick] [--out outputs/compactness] [--edits add donut_add] [--replot]
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.compactness import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
