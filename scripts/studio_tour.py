#!/usr/bin/env python
"""Drive the studio in headless Chromium through its steps, time them and keep a screenshot of each
(gs_regional/studio/tour.py; --help says what it runs and writes).

    python scripts/studio_tour.py [--config configs/demo.yaml] [--edit] [--screenshot docs/studio.png] [key=value ...]
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.studio.tour import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
