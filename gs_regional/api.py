"""Small public API for users and tests: load cameras, render, and edit (the run of launch.py)."""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence

import numpy as np

import torch

from gs_regional.data.cameras import Camera
from gs_regional.registry import find

_renderers: Dict[str, object] = {}


def load_cameras(path: str) -> List[Camera]:
    """Cameras from a scene folder or a camera file (COLMAP sparse/0, transforms.json, cameras.json)."""
    from gs_regional.data.loaders import load_cameras as _load

    return _load(path)


def render(
    model,
    camera: Camera,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    renderer: str = "torch-rasterizer",
) -> Dict[str, torch.Tensor]:
    """Render `model` from `camera`; returns rgb (H,W,3), depth (H,W), alpha (H,W) and more."""
    if renderer not in _renderers:
        _renderers[renderer] = find(renderer, kind="renderers")()
    device = model.means.device
    bg = torch.as_tensor(background, dtype=torch.float32, device=device)
    return _renderers[renderer].render(model, camera.to(device), background=bg)


ROOT = Path(__file__).resolve().parents[1]  # the checkout: launch.py, configs/


@dataclass
class EditResult:
    """What gs_regional.edit returns: the trial dir the run wrote, its save/metrics.json, the
    edited scene (save/edited.ply) and the selection over the source Gaussians (bool, one per
    source row: localization's, or the one the caller gave)."""

    trial: Path
    metrics: Dict[str, Any]
    model: Any  # GaussianModel
    selection: torch.Tensor = field(repr=False)


def _value(v: Any) -> str:
    """An override's value as launch.py's `key=value` writes it."""
    if isinstance(v, bool):
        return "true" if v else "false"
    return "null" if v is None else str(v)


def _config_path(config: Any) -> Path:
    """`config` as given, else the checkout's configs/ (edit(config="configs/demo.yaml") from anywhere)."""
    path = Path(config)
    if not path.is_file() and not path.is_absolute() and (ROOT / path).is_file():
        return ROOT / path
    return path


def _write_selection(selection: Any, out: Path) -> Path:
    """The caller's selection as <out>/selections/<content hash>.npy: a file the trial's config
    names, kept beside the trials so that the command line in the trial's cmd.txt re-runs it."""
    if isinstance(selection, torch.Tensor):
        selection = selection.detach().cpu().numpy()
    array = np.asarray(selection)  # checked where the run reads it (regional_edit.read_selection)
    folder = out / "selections"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{hashlib.sha1(array.tobytes() + str(array.shape).encode()).hexdigest()[:16]}.npy"
    if not path.is_file():
        np.save(path, array)
    return path


def edit(
    ply: Optional[str] = None,
    cameras: Optional[str] = None,
    prompt: Optional[str] = None,
    *,
    config: Any = "configs/edit.yaml",
    selection: Any = None,
    out: Any = "outputs",
    overrides: Optional[Mapping[str, Any]] = None,
    gpu: Optional[Any] = None,
    verbose: bool = False,
) -> EditResult:
    """Edit a scene as `python launch.py --config <config> --train` does, in this process, and
    return the EditResult (trial, metrics, model, selection).

    `ply` -> system.geometry.ply, `cameras` (a scene folder or camera file) -> data.source, `prompt`
    -> system.prompt, `out` -> exp_root_dir; None leaves the config's value (configs/demo.yaml's
    built-in synthetic scene needs neither ply nor cameras). `overrides` is a dict of launch.py's
    dotted keys, e.g. {"system.refine.cycles": 1, "name": "mine"}, applied after the ones above.
    `selection` (numpy or torch bool, one per source Gaussian) is the region to edit in place of
    localization's: written to <out>/selections/ and named by system.selection_file in the trial's
    config. `gpu` is launch.py's --gpu (e.g. 0). A mistake in the config, an override or an input
    file raises its typed error (ConfigError, PlyError, ...) with the one line launch.py prints.
    """
    from gs_regional.launch.cli import build_parser
    from gs_regional.launch.logs import setup_logging
    from gs_regional.launch.run import run_trial

    root = Path(out).resolve()
    given = {"exp_root_dir": str(root)}
    for key, value in (("system.geometry.ply", ply), ("data.source", cameras), ("system.prompt", prompt)):
        if value is not None:
            given[key] = str(value)
    if selection is not None:
        given["system.selection_file"] = str(_write_selection(selection, root))
    given.update(dict(overrides or {}))
    argv = ["--config", str(_config_path(config)), "--train", *(["--gpu", str(gpu)] if gpu is not None else []),
            *(["--verbose"] if verbose else []), *(f"{k}={_value(v)}" for k, v in given.items())]
    args, extra = build_parser().parse_known_args(argv)  # the same parse as launch.py's
    setup_logging(verbose=verbose)
    trial = run_trial(args, extra, argv)
    return load_edit(trial)


def load_edit(trial: Any) -> EditResult:
    """The EditResult of a finished edit's trial dir (save/metrics.json, edited.ply, edit_mask.npz)."""
    import json

    from gs_regional.geometry.gaussian_model import GaussianModel

    trial = Path(trial)
    save = trial / "save"
    metrics = json.loads((save / "metrics.json").read_text())
    model = GaussianModel.from_ply(str(save / "edited.ply"))
    with np.load(save / "edit_mask.npz") as f:
        if "source_selection" in f.files:
            selection = torch.as_tensor(f["source_selection"]).bool()
        else:  # a system that keeps no source selection: the source rows still editable at the end
            n = int(metrics.get("gaussians_before", 0)) or int(f["source_index"].max()) + 1
            selection = torch.zeros(n, dtype=torch.bool)
            rows = (f["generation"] == 0) & f["mask"].astype(bool)
            selection[torch.as_tensor(f["source_index"][rows]).long()] = True
    return EditResult(trial=trial, metrics=metrics, model=model, selection=selection)
