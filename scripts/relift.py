#!/usr/bin/env python
"""Saved localizations lifted again, the edge colour test at other ratios and each case at its best
mask_threshold (gs_regional/bench/relift.py).

    python scripts/relift.py OUT_OR_TRIAL [--edge-ratios 0 0.5] [--thresholds 0.3 0.4 0.5 0.6 0.7 0.8 0.9]
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.relift import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
