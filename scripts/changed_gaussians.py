#!/usr/bin/env python
"""Which Gaussians an edit run changed, against its known truth (gs_regional/bench/changed_gaussians.py).

    python scripts/changed_gaussians.py TRIAL_DIR [--min-change 0.02]
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.changed_gaussians import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
