"""Reading what a launch.py run wrote into its trial directory (shared by the system tests)."""
import glob
import json
import os

import numpy as np
from plyfile import PlyData


def trial_of(tmp, name):
    """The newest trial dir of experiment `name` under the exp_root_dir `tmp`."""
    trials = sorted(glob.glob(os.path.join(tmp, name, "*")), key=os.path.getmtime)
    assert trials, f"no trial dir under {tmp}/{name}"
    return trials[-1]


def metrics_of(trial):
    with open(os.path.join(trial, "save", "metrics.json")) as f:
        return json.load(f)


def ply_arrays(path):
    """Every vertex property of a PLY as a numpy array."""
    v = PlyData.read(str(path))["vertex"].data
    return {name: np.asarray(v[name]) for name in v.dtype.names}
