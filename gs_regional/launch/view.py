"""`python launch.py --view TRIAL_DIR [--port 8080]`: a web viewer of an edit run (viser).

The page shows the edited scene (`save/edited.ply`) and the source scene it was made from (the
PLY of `system.geometry.ply` in the trial's `configs/parsed.yaml`, or the scene its data module
rebuilds, e.g. the synthetic figure), with

  - a before/after toggle between the edited and the source scene;
  - the edit mask highlighted on demand (`save/edit_mask.npz`, row-aligned with edited.ply; older
    trials: the rows of `ckpts/last.ckpt`);
  - the training cameras as frustums (held-out cameras in another colour);
  - the prompt, the Gaussian counts and the key metrics of `save/metrics.json` in the side panel.

Scenes above `--max-gaussians` are shown as a random subsample of that size (the page says so),
so that a browser without a GPU stays responsive. Needs the `viewer` extra (viser).
"""
from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from gs_regional.data.cameras import Camera
from gs_regional.geometry.ply import PlyGaussians, read_ply
from gs_regional.launch.summary import KEY_METRICS, read_metrics
from gs_regional.launch.summary import _gaussians as gaussian_counts, _is_number as is_number
from gs_regional.utils.rotations import quat_to_rotmat
from gs_regional.utils.sh import sh_to_rgb

log = logging.getLogger(__name__)

DEFAULT_PORT = 8080
DEFAULT_MAX_GAUSSIANS = 500_000  # per scene: fine for a browser with a GPU; a software-rendered one needs far fewer
EDIT_MASK_FILE = "edit_mask.npz"
MASK_COLOUR = np.array([1.0, 0.0, 1.0], dtype=np.float32)  # magenta: absent from most scenes
MASK_TINT = 0.65  # how much of a highlighted Gaussian's colour is the mask colour
SCENES = ("edited", "source")
FRUSTUM_SIZE = 0.04  # of the camera rig's radius: a rig of hundreds of cameras stays legible
TRAIN_FRUSTUM_COLOUR = (40, 120, 255)
TEST_FRUSTUM_COLOUR = (255, 150, 0)
VIEWER_EXTRA_HINT = "pip install 'gs_regional[viewer]'"


class ViewError(ValueError):
    """A trial the viewer cannot show; the message says what is missing."""


# ----- what a trial holds --------------------------------------------------------------------
@dataclass
class Splats:
    """Gaussians as viser draws them (N rows, float32): centres, 3x3 covariances, colours, opacities."""

    centers: np.ndarray  # (N, 3)
    covariances: np.ndarray  # (N, 3, 3)
    rgbs: np.ndarray  # (N, 3) in [0, 1]
    opacities: np.ndarray  # (N, 1) in [0, 1]
    mask: Optional[np.ndarray] = None  # (N,) bool: rows the edit selected or added
    total: int = 0  # Gaussians in the scene before subsampling

    @property
    def shown(self) -> int:
        return len(self.centers)

    def highlighted_rgbs(self) -> np.ndarray:
        return tinted(self.rgbs, self.mask)


def tinted(rgbs: np.ndarray, mask: Optional[np.ndarray]) -> np.ndarray:
    """`rgbs` (N, 3) with the rows of `mask` (N,) bool tinted in the mask colour (a copy)."""
    rgbs = rgbs.copy()
    if mask is not None:
        rgbs[mask] = (1 - MASK_TINT) * rgbs[mask] + MASK_TINT * MASK_COLOUR
    return rgbs


def subsample_rows(n: int, cap: int, seed: int = 0) -> Optional[np.ndarray]:
    """Sorted random rows to show of `n`, or None when all `n` fit under `cap`."""
    if cap <= 0 or n <= cap:
        return None
    return np.sort(np.random.default_rng(seed).choice(n, size=cap, replace=False))


def to_splats(g: PlyGaussians, mask: Optional[np.ndarray], cap: int) -> Splats:
    """Display arrays of a PLY scene (degree-0 colour), subsampled to `cap` rows if larger."""
    rows = subsample_rows(g.num_gaussians, cap)

    def take(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a if rows is None else a[rows], dtype=np.float32))

    rotations = quat_to_rotmat(take(g.quats))
    variances = torch.exp(2 * take(g.log_scales))
    covariances = (rotations * variances[:, None, :]) @ rotations.transpose(1, 2)  # R diag(s^2) R^T
    return Splats(
        centers=take(g.means).numpy(),
        covariances=covariances.numpy(),
        rgbs=sh_to_rgb(take(g.sh_dc)).clamp(0, 1).numpy(),
        opacities=torch.sigmoid(take(g.opacity_logits)).reshape(-1, 1).numpy(),
        mask=None if mask is None else (mask if rows is None else mask[rows]),
        total=g.num_gaussians,
    )


@dataclass
class Trial:
    path: Path
    edited: PlyGaussians
    source: PlyGaussians
    source_label: str  # where the source scene comes from, for the page
    cameras: List[Camera]
    test_indices: List[int]
    edited_mask: Optional[np.ndarray]  # (N_edited,) bool: selected or added by the edit
    source_mask: Optional[np.ndarray]  # (N_source,) bool: the source rows the edit selected
    mask_note: str  # where the mask comes from, or why there is none
    metrics: Dict[str, Any] = field(default_factory=dict)
    prompt: str = ""


def _data_config_without_photos(data_cls: Any, data_cfg: Any) -> Any:
    """The data section with photo loading off where the module has that switch (the viewer
    needs the cameras only)."""
    from omegaconf import OmegaConf

    config = getattr(data_cls, "Config", None)
    if config is not None and is_dataclass(config) and "load_images" in {f.name for f in fields(config)}:
        data_cfg = OmegaConf.merge(data_cfg, {"load_images": False})
    return data_cfg


def read_edit_rows(trial: Path, n_edited: int) -> Tuple[Optional[Dict[str, np.ndarray]], str]:
    """(mask, generation, source_index) rows of edited.ply, and where they come from; from
    save/edit_mask.npz also a recolour's `gate_blend` (over the source's rows) where it has one."""
    path = trial / "save" / EDIT_MASK_FILE
    if path.is_file():
        with np.load(path) as f:
            rows = {k: f[k] for k in ("mask", "generation", "source_index")}
            if "gate_blend" in f:
                rows["gate_blend"] = f["gate_blend"]
        where = f"save/{EDIT_MASK_FILE}"
    else:
        ckpt = trial / "ckpts" / "last.ckpt"
        if not ckpt.is_file():
            return None, f"no edit mask: this trial has neither save/{EDIT_MASK_FILE} nor ckpts/last.ckpt"
        state = torch.load(ckpt, map_location="cpu", weights_only=True)["state_dict"]  # tensors only, no pickled code
        names = {"mask": "geometry.mask", "generation": "geometry.generation", "source_index": "geometry.source_index"}
        if not all(v in state for v in names.values()):
            return None, f"no edit mask: {ckpt} holds no per-Gaussian mask"
        rows = {k: state[v].numpy() for k, v in names.items()}
        where = "ckpts/last.ckpt"
    if len(rows["mask"]) != n_edited:
        return None, f"no edit mask: {where} has {len(rows['mask']):,} rows, edited.ply {n_edited:,}"
    return rows, where


def source_scene(cfg: Any, where: str) -> Tuple[PlyGaussians, str, Any]:
    """(source scene, where it comes from, the data module's scene: cameras, test_indices) of a
    loaded config: the PLY of system.geometry.ply, or the scene the data module rebuilds (the
    synthetic figure); ViewError names `where` when there is neither. Photos are not read."""
    from gs_regional.registry import find

    data_cls = find(cfg.data_type, kind="data", key="data_type")
    datamodule = data_cls(_data_config_without_photos(data_cls, cfg.data))
    datamodule.setup("fit")
    scene = datamodule.scene
    source_ply = (cfg.system.get("geometry") or {}).get("ply")
    if source_ply:
        return read_ply(source_ply), str(source_ply), scene
    if scene.ground_truth is not None:
        return scene.ground_truth.source.to_ply_gaussians(), f"{scene.source} (rebuilt from the config)", scene
    raise ViewError(f"{where}: no source scene: system.geometry.ply is not set and data '{cfg.data_type}' has none")


def load_trial(trial_dir: Any, custom_dir: Any = None) -> Trial:
    """Read everything the page shows from a trial dir; ViewError says what is missing."""
    from gs_regional.config import load_config
    from gs_regional.launch.plugins import default_custom_dir, load_plugins
    from gs_regional.registry import load_builtins

    trial = Path(trial_dir)
    if not trial.is_dir():
        raise ViewError(f"trial dir not found: {trial}")
    parsed, edited_ply = trial / "configs" / "parsed.yaml", trial / "save" / "edited.ply"
    if not parsed.is_file():
        raise ViewError(f"{trial} is not a trial dir: it has no configs/parsed.yaml")
    if not edited_ply.is_file():
        raise ViewError(f"{trial} has no save/edited.ply: the viewer shows finished edit runs")
    load_builtins()
    load_plugins(custom_dir or default_custom_dir())
    cfg = load_config(str(parsed))
    edited = read_ply(edited_ply)
    source, source_label, scene = source_scene(cfg, str(parsed))

    rows, mask_note = read_edit_rows(trial, edited.num_gaussians)
    edited_mask = source_mask = None
    if rows is not None:
        edited_mask = rows["mask"].astype(bool) | (rows["generation"] > 0)
        selected = rows["source_index"][rows["mask"].astype(bool) & (rows["source_index"] >= 0)]
        source_mask = np.zeros(source.num_gaussians, dtype=bool)
        source_mask[selected[selected < source.num_gaussians]] = True
        mask_note = (f"{int(edited_mask.sum()):,} Gaussians selected or added by the edit "
                     f"({int(source_mask.sum()):,} of the source); from {mask_note}")
    metrics = read_metrics(trial)
    return Trial(
        path=trial, edited=edited, source=source, source_label=source_label,
        cameras=scene.cameras, test_indices=list(scene.test_indices),
        edited_mask=edited_mask, source_mask=source_mask, mask_note=mask_note,
        metrics=metrics, prompt=str(metrics.get("prompt") or cfg.system.get("prompt") or ""),
    )


# ----- the page ------------------------------------------------------------------------------
def _up_direction(cameras: Sequence[Camera]) -> np.ndarray:
    """The scene's up: the mean of the cameras' up vectors (-y of OpenCV cameras)."""
    ups = np.stack([-c.camera_to_world[:3, 1].numpy() for c in cameras])
    up = ups.mean(0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-6 else np.array([0.0, -1.0, 0.0])


def _frontal_camera(cameras: Sequence[Camera]) -> Camera:
    """The camera nearest the mean viewing direction (the rig's most typical view)."""
    forwards = np.stack([c.camera_to_world[:3, 2].numpy() for c in cameras])
    mean = forwards.mean(0)
    return cameras[int(np.argmax(forwards @ mean))]


def _look_at(camera: Camera, centers: np.ndarray) -> np.ndarray:
    """The point on `camera`'s optical axis at the median depth of the Gaussians in front of it."""
    c2w = camera.camera_to_world.numpy()
    origin, forward = c2w[:3, 3], c2w[:3, 2]
    depth = (centers - origin) @ forward
    depth = depth[depth > 0]
    return origin + forward * (float(np.median(depth)) if len(depth) else 1.0)


def metrics_markdown(m: Dict[str, Any], prompt: str) -> str:
    """The metrics panel: the prompt, the Gaussian counts and the key metrics of metrics.json `m`."""
    lines = [f"**Prompt:** {prompt or '(none)'}", ""]
    counts = gaussian_counts(m)
    if counts:
        lines.append(f"**Gaussians:** {counts}")
        lines.append("")
    shown = [(label, fmt.format(m[key])) for label, key, fmt in KEY_METRICS if is_number(m.get(key))]
    if shown:
        lines += ["| metric | value |", "| --- | --- |"] + [f"| {label} | {value} |" for label, value in shown]
    elif not m:
        lines.append("(no save/metrics.json)")
    return "\n".join(lines)


@dataclass
class Viewer:
    """A running viewer; `stop()` ends it."""

    server: Any
    url: str
    splats: Dict[str, Splats]  # "edited", "source": what the page shows now

    def stop(self) -> None:
        self.server.stop()


def _sampling_note(splats: Dict[str, Splats]) -> str:
    lines = []
    for name, s in splats.items():
        if s.shown < s.total:
            lines.append(f"**Subsampled:** the {name} scene shows a random {s.shown:,} of its {s.total:,} Gaussians")
        else:
            lines.append(f"The {name} scene: all {s.total:,} Gaussians")
    lines.append("Slow to turn? Show fewer Gaussians (`--max-gaussians` sets the start).")
    return "\n\n".join(lines)


def rig_radius(cameras: Sequence[Camera]) -> float:
    centers = np.stack([c.center.numpy() for c in cameras])
    return float(np.linalg.norm(centers - centers.mean(0), axis=1).max()) or 1.0


def set_initial_view(server: Any, cameras: Sequence[Camera], points: np.ndarray) -> None:
    """The scene's up direction and the page's first view: the most frontal camera's, from just
    in front of its own frustum (not from behind the rig: scenes are often enclosed, e.g. rooms or
    the synthetic backdrop), looking at the median depth of `points` (N, 3)."""
    up = _up_direction(cameras)
    front = _frontal_camera(cameras)
    server.scene.set_up_direction(tuple(float(v) for v in up))
    target = _look_at(front, points)
    origin = front.camera_to_world[:3, 3].numpy()
    position = origin + (target - origin) / np.linalg.norm(target - origin) * 1.5 * FRUSTUM_SIZE * rig_radius(cameras)
    server.initial_camera.position = tuple(float(v) for v in position)
    server.initial_camera.look_at = tuple(float(v) for v in target)
    server.initial_camera.up = tuple(float(v) for v in up)
    server.initial_camera.fov = 2 * math.atan(front.height / (2 * front.fy))


def add_frustums(server: Any, cameras: Sequence[Camera], test: Any) -> List[Any]:
    """The cameras as frustums (held-out ones, indices in `test`, in another colour)."""
    import viser.transforms as vtf

    radius = rig_radius(cameras)
    frustums = []
    for i, cam in enumerate(cameras):
        c2w = cam.camera_to_world.numpy()
        frustums.append(server.scene.add_camera_frustum(
            f"/cameras/{'test' if i in test else 'train'}_{i:04d}",
            fov=2 * math.atan(cam.height / (2 * cam.fy)), aspect=cam.width / cam.height, scale=FRUSTUM_SIZE * radius,
            thickness=0.002 * radius, color=TEST_FRUSTUM_COLOUR if i in test else TRAIN_FRUSTUM_COLOUR,
            wxyz=vtf.SO3.from_matrix(c2w[:3, :3]).wxyz, position=c2w[:3, 3]))
    return frustums


def serve(trial: Trial, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
          max_gaussians: int = DEFAULT_MAX_GAUSSIANS) -> Viewer:
    """Start the viser server for `trial` (in its own threads) and build the page."""
    import viser

    scenes = {"edited": (trial.edited, trial.edited_mask), "source": (trial.source, trial.source_mask)}
    splats = {name: to_splats(g, mask, max_gaussians) for name, (g, mask) in scenes.items()}
    server = viser.ViserServer(host=host, port=port, label=f"gs_regional: {trial.path.name}", verbose=False)
    set_initial_view(server, trial.cameras, splats["edited"].centers)
    nodes = {
        name: server.scene.add_gaussian_splats(
            f"/{name}", centers=s.centers, covariances=s.covariances, rgbs=s.rgbs, opacities=s.opacities,
            visible=name == "edited")
        for name, s in splats.items()
    }
    test = set(trial.test_indices)
    frustums = add_frustums(server, trial.cameras, test)

    gui = server.gui
    gui.add_markdown(f"**Trial:** `{trial.path}`")
    scene_choice = gui.add_button_group("Scene", SCENES)
    showing = gui.add_markdown("Showing: **edited**")
    highlight = gui.add_checkbox("Highlight edit mask", initial_value=False, disabled=trial.edited_mask is None)
    gui.add_markdown(trial.mask_note)
    show_cameras = gui.add_checkbox("Cameras", initial_value=True)
    gui.add_markdown(f"{len(trial.cameras) - len(test)} training cameras (blue), {len(test)} held out (orange)")
    gui.add_markdown(metrics_markdown(trial.metrics, trial.prompt))
    gui.add_markdown(f"Source: `{trial.source_label}`")
    largest = max(s.total for s in splats.values())
    shown = gui.add_number("Gaussians shown", initial_value=max(s.shown for s in splats.values()),
                           min=min(1000, largest), max=largest, step=1000, hint="per scene, a random subsample")
    sampling = gui.add_markdown(_sampling_note(splats))

    def colours(s: Splats) -> np.ndarray:
        return s.highlighted_rgbs() if highlight.value else s.rgbs

    @scene_choice.on_click
    def _(_event) -> None:
        for name, node in nodes.items():
            node.visible = name == scene_choice.value
        showing.content = f"Showing: **{scene_choice.value}**"

    @highlight.on_update
    def _(_event) -> None:
        for name, s in splats.items():
            nodes[name].rgbs = colours(s)

    @show_cameras.on_update
    def _(_event) -> None:
        for f in frustums:
            f.visible = show_cameras.value

    @shown.on_update
    def _(_event) -> None:
        for name, (g, mask) in scenes.items():
            s = splats[name] = to_splats(g, mask, int(shown.value))
            nodes[name].set_gaussians(s.centers, s.covariances, colours(s), s.opacities)
        sampling.content = _sampling_note(splats)

    shown_host = "localhost" if host in ("127.0.0.1", "0.0.0.0", "localhost") else host
    return Viewer(server=server, url=f"http://{shown_host}:{server.get_port()}", splats=splats)


# ----- command line --------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="launch.py --view",
        description="Serve a web viewer of an edit run: python launch.py --view TRIAL_DIR [--port 8080]",
    )
    p.add_argument("--view", required=True, metavar="TRIAL_DIR", help="trial dir of an edit run (outputs/<name>/<tag>@<time>)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port to serve on (default {DEFAULT_PORT})")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: every interface)")
    p.add_argument("--max-gaussians", type=int, default=DEFAULT_MAX_GAUSSIANS,
                   help=f"show a random subsample of this many Gaussians per scene above it (default {DEFAULT_MAX_GAUSSIANS:,}; 0: all)")
    p.add_argument("--custom-dir", default=None, help="plugin folder (default: custom/ beside launch.py)")
    p.add_argument("--debug", action="store_true", help="tracebacks instead of one-line errors")
    return p


def viewer_missing(what: str = "the viewer") -> Optional[str]:
    """None if the `viewer` extra imports, else the one-line reason (`what` needs it)."""
    try:
        import viser  # noqa: F401
    except ImportError as e:
        return f"{what} needs the 'viewer' extra ({VIEWER_EXTRA_HINT}): {e}"
    return None


def main(argv: Sequence[str], custom_dir: Any = None) -> int:
    """`launch.py --view ...`: serve until interrupted; mistakes end with one line and exit code 2."""
    from gs_regional.launch.errors import is_user_error
    from gs_regional.launch.logs import setup_logging

    try:
        args = build_parser().parse_args(list(argv))
    except SystemExit as e:
        return int(e.code or 0)
    missing = viewer_missing()
    if missing:
        sys.stderr.write(f"error: {missing}\n")
        return 2
    setup_logging(verbose=args.debug)
    try:
        started = time.perf_counter()
        trial = load_trial(args.view, args.custom_dir or custom_dir)
        viewer = serve(trial, host=args.host, port=args.port, max_gaussians=args.max_gaussians)
    except Exception as e:
        if args.debug or not (isinstance(e, (ViewError, OSError)) or is_user_error(e)):
            raise
        sys.stderr.write(f"error: {e}\n")
        return 2
    print(f"viewer of {trial.path} ready in {time.perf_counter() - started:.1f} s: {viewer.url}  (Ctrl+C stops it)", flush=True)
    return serve_until_interrupted(viewer)


def serve_until_interrupted(server: Any) -> int:
    """Keep a started server (its `stop()` ends it) running until Ctrl+C; exit code 0."""
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    return 0
