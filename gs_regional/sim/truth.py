"""A known edit of a scene (`GroundTruth`) and what the simulated priors need to use one.

Any data module may provide a ground truth as `SceneData.ground_truth` (the synthetic scene does;
so could a real splat with a known edit). Systems score against it, and hand it to every prior
that has `attach_ground_truth` (the simulated editor and depth). A simulator never builds a truth
of its own: used without one, it fails at its first call saying what to do.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import torch

from gs_regional.config import ConfigError
from gs_regional.data.cameras import Camera
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.utils.sh import rgb_to_sh


@dataclass
class GroundTruth:
    """The true answer of one edit of one scene.

    Per-Gaussian masks are indexed by ROW of the model they refer to: `region` and `related` by
    row of `source` (the rows a system starts from, before any densification), `new_region` by row
    of `edited`."""

    source: GaussianModel  # the scene before the edit
    edited: GaussianModel  # the scene after the true edit
    region: torch.Tensor  # (len(source),) bool: the Gaussians the edit is about (what an editor should select)
    new_region: torch.Tensor  # (len(edited),) bool: the edited scene's region, including Gaussians the edit adds
    front: torch.Tensor  # (3,) unit direction the edited object faces: views far from it are side views
    center: torch.Tensor  # (3,) the point `front` is measured from (where the views look)
    related: Optional[torch.Tensor] = None  # (len(source),) bool: should not change but looks related; None: no such part
    name: str = ""  # short name of the edit, e.g. "add"
    prompt: str = ""  # an instruction asking for this edit

    def __post_init__(self) -> None:
        def mask(value, rows: int, what: str, model: str) -> torch.Tensor:
            value = torch.as_tensor(value)
            if value.dtype != torch.bool or value.shape != (rows,):
                raise ValueError(
                    f"GroundTruth.{what} must be a bool tensor with one entry per {model} Gaussian "
                    f"({rows}), got {value.dtype} of shape {tuple(value.shape)}"
                )
            return value

        self.region = mask(self.region, len(self.source), "region", "source")
        self.new_region = mask(self.new_region, len(self.edited), "new_region", "edited")
        if self.related is not None:
            self.related = mask(self.related, len(self.source), "related", "source")
        for what in ("front", "center"):
            value = torch.as_tensor(getattr(self, what), dtype=torch.float32)
            if value.shape != (3,):
                raise ValueError(f"GroundTruth.{what} must be a 3-vector, got shape {tuple(value.shape)}")
            setattr(self, what, value)


def camera_key(camera: Camera) -> Tuple:
    """A hashable identity of a camera (pose rounded to 1e-5, intrinsics, size)."""
    pose = tuple(round(float(v), 5) for v in camera.world_to_camera.detach().cpu().flatten())
    intr = tuple(round(float(v), 4) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    return pose + intr + (int(camera.width), int(camera.height))


def camera_seed(camera: Camera) -> int:
    """A stable 31-bit integer per camera, for per-view randomness: the same across processes,
    resolutions and CPUs. Named cameras (every loader and the synthetic scene name theirs) are
    keyed by name alone. Never by float bits: a pose computed on another CPU differs in the last
    bit, which flips a rounded digit now and then and with it the whole hash, so that view drew
    other noise on another machine (the demo's mask IoU moved by 0.04). An unnamed camera falls
    back to its pose rounded to 1e-3, coarse enough that such a flip is rare."""
    if camera.image_name:
        key = ("name", camera.image_name)
    else:
        key = ("pose",) + tuple(round(float(v), 3) + 0.0 for v in camera.world_to_camera.detach().cpu().flatten())
    return zlib.crc32(repr(key).encode()) & 0x7FFFFFFF


def camera_for_image(camera: Camera, height: int, width: int, who: str) -> Camera:
    """`camera` resized to an image of height x width (same aspect), or a clear error."""
    if not isinstance(camera, Camera):
        raise TypeError(f"{who}: cameras must be gs_regional Camera objects, got {type(camera).__name__}")
    if (camera.width, camera.height) == (width, height):
        return camera
    scaled = camera.scaled(width / camera.width)
    if (scaled.width, scaled.height) != (width, height):
        raise ValueError(
            f"{who}: image is {width}x{height} but camera '{camera.image_name}' is "
            f"{camera.width}x{camera.height} (a different aspect ratio)"
        )
    return scaled


class TruthRenderer:
    """Renders of a `GroundTruth` at any camera, cached per camera.

    Shared by the simulated editor and the simulated depth estimator."""

    def __init__(self, truth: GroundTruth, renderer: str = "torch-rasterizer", background=(0.0, 0.0, 0.0),
                 max_cached: int = 512) -> None:
        from gs_regional.registry import find

        if not isinstance(truth, GroundTruth):
            raise TypeError(f"TruthRenderer needs a GroundTruth, got {type(truth).__name__}")
        self.truth = truth
        self.renderer_name = renderer
        self.renderer = find(renderer, kind="renderers")()
        self.background = torch.as_tensor(list(background), dtype=torch.float32)
        self.max_cached = int(max_cached)
        self._cache: Dict[Tuple, Dict[str, torch.Tensor]] = {}

    def _remember(self, key, value):
        if len(self._cache) >= self.max_cached:
            self._cache.pop(next(iter(self._cache)))  # drop the oldest
        self._cache[key] = value
        return value

    def views(self, camera: Camera) -> Dict[str, torch.Tensor]:
        """{src_rgb, src_depth, src_alpha, edit_rgb, edit_depth, edit_alpha} on the CPU."""
        key = ("views",) + camera_key(camera)
        if key in self._cache:
            return self._cache[key]
        out = {}
        with torch.no_grad():
            for tag, model in (("src", self.truth.source), ("edit", self.truth.edited)):
                cam = camera.to(model.means.device)
                r = self.renderer.render(model, cam, background=self.background.to(model.means.device))
                out[f"{tag}_rgb"] = r["rgb"].detach().float().clamp(0, 1).cpu()
                out[f"{tag}_depth"] = r["depth"].detach().float().cpu()
                out[f"{tag}_alpha"] = r["alpha"].detach().float().cpu()
        return self._remember(key, out)

    def region_maps(self, camera: Camera) -> torch.Tensor:
        """(H, W, 2): the rendered weight of the true region and of the related part of the
        source scene (accumulated alpha-compositing weights, in [0, 1])."""
        key = ("region",) + camera_key(camera)
        if key in self._cache:
            return self._cache[key]
        src = self.truth.source
        feats = torch.zeros(len(src), 2)
        feats[:, 0] = self.truth.region.float()
        if self.truth.related is not None:
            feats[:, 1] = self.truth.related.float()
        feats = feats.to(src.means.device)
        cam = camera.to(src.means.device)
        with torch.no_grad():
            try:
                maps = self.renderer.render(src, cam, override_color=feats)["rgb"][..., :2]
            except (TypeError, NotImplementedError):
                # a renderer without per-Gaussian features: encode them as colours of a copy
                maps = self._render_as_colours(src, cam, feats)
        return self._remember(key, maps.detach().float().clamp(0, 1).cpu())

    def _render_as_colours(self, src: GaussianModel, cam: Camera, feats: torch.Tensor) -> torch.Tensor:
        rgb = torch.cat([feats, torch.zeros(len(src), 1, device=feats.device)], 1)
        copy = GaussianModel.from_tensors(
            means=src.means.detach(), quats=src.quats.detach(), log_scales=src.log_scales.detach(),
            opacity_logits=src.opacity_logits.detach(), sh_dc=rgb_to_sh(rgb),
        )
        black = torch.zeros(3, device=src.means.device)
        return self.renderer.render(copy, cam, background=black)["rgb"][..., :2]


class GroundTruthConsumer:
    """Mixin of the simulated priors: they render a known answer, which must be handed over with
    `attach_ground_truth` (systems do it with `SceneData.ground_truth`). The component's config
    must have `renderer`, `background` and `max_cached_views` (how the truth is rendered)."""

    _truth_renderer: Optional[TruthRenderer] = None

    def attach_ground_truth(self, truth: GroundTruth, shared: Optional[dict] = None) -> None:
        """`shared`: a dict handed to every simulator of one system: those that render the truth
        alike (renderer, background, cache size) share one `TruthRenderer`, so a view the editor
        rendered is not rendered again for the depth estimator."""
        if not isinstance(truth, GroundTruth):
            raise TypeError(f"{self.registered_name}.attach_ground_truth needs a GroundTruth, got {type(truth).__name__}")
        key = (id(truth), self.cfg.renderer, tuple(float(v) for v in self.cfg.background), int(self.cfg.max_cached_views))
        shared = {} if shared is None else shared
        if key not in shared:
            shared[key] = TruthRenderer(truth, self.cfg.renderer, self.cfg.background, self.cfg.max_cached_views)
        self._truth_renderer = shared[key]

    @property
    def truth_renderer(self) -> TruthRenderer:
        if self._truth_renderer is None:
            raise ConfigError(
                f"{self.registered_name} is a simulator: it renders the known answer of a scene, and none was "
                f"attached. Use a data module that provides a ground truth (e.g. data_type: synthetic-scene; "
                f"the system hands it over), or call attach_ground_truth(truth) when using it directly."
            )
        return self._truth_renderer

    @property
    def ground_truth(self) -> GroundTruth:
        return self.truth_renderer.truth
