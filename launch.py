#!/usr/bin/env python
"""Run a gs_regional experiment (threestudio-style).

    python launch.py --config configs/edit.yaml --train [--gpu 0] [key=value ...]
    python launch.py --config configs/edit.yaml --test resume=outputs/<name>/<trial>/ckpts/last.ckpt
    python launch.py --studio [--config configs/demo.yaml] [key=value ...]   (edit from the browser)

Plugins in custom/ beside this file are imported before the config is read. See
gs_regional/launch/ for what happens and where the outputs go.
"""
import os
import sys

if __name__ == "__main__":
    # Idle OpenMP threads must sleep, not spin: on a small shared CPU spinning threads make every
    # parallel torch op stall (10-40x slower renders). Must be set before torch is imported.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    # `python launch.py` puts this folder first on sys.path: gs_regional imports from the checkout.
    here = os.path.dirname(os.path.abspath(__file__))
    if any(a == "--studio" for a in sys.argv[1:]):  # the studio sits above launch (docs/architecture.md)
        from gs_regional.studio import main as studio_main

        sys.exit(studio_main(sys.argv[1:], custom_dir=os.path.join(here, "custom")))
    from gs_regional.launch import main

    sys.exit(main(sys.argv[1:], custom_dir=os.path.join(here, "custom")))
