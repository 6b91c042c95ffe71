#!/usr/bin/env python
"""Where each method breaks: each failure mode of the simulated editor and depth swept from none
to beyond realistic (gs_regional/bench/stability.py; --help says what it runs and writes).

    python scripts/stability.py [--quick] [--out outputs/stability]
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.stability import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
