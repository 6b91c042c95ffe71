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
from gs_regional.stages.localize import LOCALIZATION_FILE

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


def _run(config: Any, ply: Any, cameras: Any, prompt: Any, selection: Any, out: Any,
         overrides: Optional[Mapping[str, Any]], gpu: Any, verbose: bool, callbacks: Sequence[Any] = ()) -> Path:
    """launch.py --config <config> --train with these arguments, in this process; the trial dir."""
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
    return run_trial(args, extra, argv, callbacks=callbacks)


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
    callbacks: Sequence[Any] = (),
) -> EditResult:
    """Edit a scene as `python launch.py --config <config> --train` does, in this process, and
    return the EditResult (trial, metrics, model, selection).

    `ply` -> system.geometry.ply, `cameras` (a scene folder or camera file) -> data.source, `prompt`
    -> system.prompt, `out` -> exp_root_dir; None leaves the config's value (configs/demo.yaml's
    built-in synthetic scene needs neither ply nor cameras). `overrides` is a dict of launch.py's
    dotted keys, e.g. {"system.refine.cycles": 1, "name": "mine"}, applied after the ones above.
    `selection` (numpy or torch bool, one per source Gaussian) is the region to edit in place of
    localization's: written to <out>/selections/ and named by system.selection_file in the trial's
    config. `gpu` is launch.py's --gpu (e.g. 0). `callbacks`: more Lightning callbacks for the run
    (the studio follows and stops an edit with one). A mistake in the config, an override or an
    input file raises its typed error (ConfigError, PlyError, ...) with the one line launch.py prints.
    """
    return load_edit(_run(config, ply, cameras, prompt, selection, out, overrides, gpu, verbose, callbacks))


# What a localization-only run need not write (its trial keeps the evidence, save/localization.npz):
# the viewer formats, and a turntable and more than one scored view of an unchanged scene. The
# caller's overrides come after these.
LOCALIZE_ONLY = {"system.stop_after": "localize", "system.export.splat": False, "system.export.compressed_ply": False,
                 "system.eval.turntable_frames": 1, "system.eval.max_test_views": 1}


@dataclass
class Localized:
    """What gs_regional.localize returns: a localization-only run's evidence, from which a selection
    is re-made at any threshold without the editor (`select`), and edited (`edit`).

    `source`: the scene localization ran on (rows aligned with everything below); `scores`: each
    Gaussian's lift score (its rendering-weight vote for the relevance masks, pooled over its
    `neighbourhood`; None for a selection the caller gave); `neighbourhood`: (N, k) rows the votes
    were pooled over (None without pooling); `masks`: {view index: (H, W) bool} the per-view
    relevance masks; `selection`: the run's selection; `threshold`: the lift's threshold
    (system.localization.mask_threshold); `expand_radius`: point expansion in world units."""

    trial: Path
    source: Any  # GaussianModel
    selection: torch.Tensor = field(repr=False)
    scores: Optional[torch.Tensor] = field(repr=False, default=None)
    neighbourhood: Optional[torch.Tensor] = field(repr=False, default=None)
    masks: Dict[int, torch.Tensor] = field(repr=False, default_factory=dict)
    threshold: Optional[float] = None
    expand_radius: float = 0.0
    metrics: Dict[str, Any] = field(repr=False, default_factory=dict)
    run: Dict[str, Any] = field(repr=False, default_factory=dict)  # edit()'s arguments for the same scene

    @property
    def count(self) -> int:
        return int(self.selection.sum())

    def to(self, device: Any) -> "Localized":
        """The scene and its evidence moved to `device` (select and picking run where they are)."""
        self.source = self.source.to(device)
        for name in ("selection", "scores", "neighbourhood"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, value.to(device))
        self.masks = {k: m.to(device) for k, m in self.masks.items()}
        return self

    def select(self, threshold: Optional[float] = None) -> torch.Tensor:
        """(N,) bool: the selection re-lifted at `threshold` from the saved evidence, no editor call:
        each Gaussian whose lift score exceeds `threshold` (the lift's own rule against
        system.localization.mask_threshold, the default), then the run's point expansion. At the
        lift's threshold this is the run's selection (unless system.ablation.localize_with_truth
        replaced it). A run without scores (a given selection) returns its selection."""
        if self.scores is None:
            return self.selection.clone()
        from gs_regional.stages.localize import expand_selection

        selected = self.scores > float(self.threshold if threshold is None else threshold)
        return expand_selection(self.source.means.detach(), selected, self.expand_radius)

    def edit(self, selection: Any = None, **kwargs: Any) -> "EditResult":
        """gs_regional.edit of the same scene, config and overrides, with `selection` (default:
        this one); `kwargs` replace edit()'s arguments (prompt=..., overrides=...)."""
        args = {**self.run, **kwargs}
        overrides = {k: v for k, v in dict(args.pop("overrides", None) or {}).items() if k not in LOCALIZE_ONLY}
        return edit(selection=self.selection if selection is None else selection, overrides=overrides, **args)


def localize(
    ply: Optional[str] = None,
    cameras: Optional[str] = None,
    prompt: Optional[str] = None,
    *,
    config: Any = "configs/edit.yaml",
    out: Any = "outputs",
    overrides: Optional[Mapping[str, Any]] = None,
    gpu: Optional[Any] = None,
    verbose: bool = False,
    callbacks: Sequence[Any] = (),
) -> Localized:
    """Localization alone (`launch.py ... --train system.stop_after=localize`, in this process):
    the Localized evidence, from which `select(threshold)` re-makes the selection without the
    editor and `edit(selection)` (or gs_regional.edit(..., selection=...)) edits it. The arguments
    are gs_regional.edit's."""
    given = {**LOCALIZE_ONLY, **dict(overrides or {})}
    trial = _run(config, ply, cameras, prompt, None, out, given, gpu, verbose, callbacks)
    run = dict(ply=ply, cameras=cameras, prompt=prompt, config=config, out=out, overrides=dict(overrides or {}),
               gpu=gpu, verbose=verbose)
    loc = load_localized(trial, run)
    if gpu is not None and torch.cuda.is_available():  # on the device the run used
        loc.to(f"cuda:{str(gpu).split(',')[0].strip()}")
    return loc


def load_localized(trial: Any, run: Optional[Dict[str, Any]] = None) -> Localized:
    """The Localized of a localization run's trial dir (save/localization.npz, save/edited.ply:
    the unchanged source); a trial without the evidence is a one-line FileNotFoundError."""
    import json

    from gs_regional.geometry.gaussian_model import GaussianModel

    trial = Path(trial)
    save = trial / "save"
    path = save / LOCALIZATION_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: {trial} is not a trial of a localization that ran "
                                "(a run resumed after it, or another system)")
    source = GaussianModel.from_ply(str(save / "edited.ply"))
    device = source.means.device
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    if len(arrays["selected"]) != source.num_gaussians:
        raise ValueError(f"{path}: {len(arrays['selected']):,} rows, but {save / 'edited.ply'} has "
                         f"{source.num_gaussians:,} Gaussians")
    metrics_path = save / "metrics.json"
    masks = {}
    if "masks" in arrays:
        masks = {int(v): torch.as_tensor(m, device=device) for v, m in zip(arrays["views"], arrays["masks"])}
    return Localized(
        trial=trial, source=source, selection=torch.as_tensor(arrays["selected"], device=device),
        scores=torch.as_tensor(arrays["scores"], device=device) if "scores" in arrays else None,
        neighbourhood=torch.as_tensor(arrays["neighbourhood"], device=device).long() if "neighbourhood" in arrays else None,
        masks=masks, threshold=float(arrays["threshold"]) if "threshold" in arrays else None,
        expand_radius=float(arrays.get("expand_radius", 0.0)),
        metrics=json.loads(metrics_path.read_text()) if metrics_path.is_file() else {}, run=dict(run or {}),
    )


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
