"""Known edits of ANY trained splat: the yardstick of the synthetic scene, on real scenes.

`splat-truth` (`SplatTruthDataModule`) loads a trained INRIA-layout PLY (never copied), takes its
cameras from any camera source the data package reads (`data.cameras`) or generates an orbit
around the splat, and builds a known edit from the splat itself, as a `GroundTruth`:

  recolor  a part picked by a spatial rule is recoloured to `color` (its shading kept as a
           luminance factor; view-dependent SH of the part dropped); geometry unchanged.
           Rules (`select`): `top`, the upper `top_fraction` of the object along `up` (the icing
           side of a donut); `ball`, the Gaussians within `ball_radius` of `anchor`; `file`, the
           Gaussians a saved mask names (`region_file`: a whole part, e.g. a `segment_parts`
           segment or a named part of the procedural scene).
           `related`: what lies just outside the part (the band below it / a shell around it).
  add      a new compact object (a "cherry": a sphere of `add_count` small, opaque, flat Gaussians
           of one colour, shaded from above) resting on the surface seen from `up` at `anchor`
           (from `add_direction` when given: on a part whose top is covered, on its side).
           `region` = the splat's Gaussians within `region_radius` sphere radii of it (the part
           it sits on, what an editor's mask selects); `new_region` = those and the new rows.
           `related`: the shell out to twice that radius. With `region_file` the region is
           the part the file names instead (the whole part the object rests on).

Positions (`anchor`, radii, the orbit radius) are in units of the OBJECT RADIUS from the OBJECT
CENTRE: half the diagonal and the middle of the box spanned by the 2%-98% quantiles of the
opaque Gaussians' positions (robust to floaters), so one config fits splats of any scale.
`front` (the direction the edit faces, what the simulated editor's side-view misses are measured
from) defaults to `up`. Everything is deterministic given the config (`seed`).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple

import torch

from gs_regional.config import ConfigError, parse_structured
from gs_regional.data.cameras import Camera
from gs_regional.data.datamodule import SceneDataModuleBase
from gs_regional.data.loaders import load_cameras
from gs_regional.data.scene import SceneData, split_every
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.geometry.neighbors import connected_components, knn, quantile_box
from gs_regional.registry import register
from gs_regional.sim.scene import _Ellipsoid, _sample_ellipsoid, look_at
from gs_regional.sim.truth import GroundTruth
from gs_regional.utils.rotations import covariance_to_scales_quats
from gs_regional.utils.sh import rgb_to_sh, sh_to_rgb

EDIT_NAMES = ("recolor", "add")
SELECT_RULES = ("top", "ball", "file")
OPAQUE = 0.5  # Gaussians above this opacity define the object's extent and its surface
_LUMA = (0.299, 0.587, 0.114)


def _unit(v, what: str) -> torch.Tensor:
    v = torch.as_tensor(v, dtype=torch.float32).reshape(-1)
    if v.shape != (3,) or float(v.norm()) < 1e-9:
        raise ConfigError(f"{what} must be a non-zero 3-vector, got {v.tolist()}")
    return v / v.norm()


def object_frame(model: GaussianModel) -> Tuple[torch.Tensor, float]:
    """(centre (3,), radius) of the object: middle and half diagonal of the 2%-98% quantile box
    of the opaque Gaussians' positions (all Gaussians if none is opaque)."""
    means = model.means.detach()
    opaque = model.opacities.detach() > OPAQUE
    pts = means[opaque] if int(opaque.sum()) >= 10 else means
    lo, hi = quantile_box(pts, 0.02)
    return ((lo + hi) / 2).float(), float((hi - lo).norm() / 2)


def _horizontal_basis(up: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors spanning the plane perpendicular to `up` (the first from the world axis
    least aligned with it), so that (e1, e2, up) is right-handed."""
    axis = torch.zeros(3)
    axis[int(up.abs().argmin())] = 1.0
    e1 = axis - (axis @ up) * up
    e1 = e1 / e1.norm()
    return e1, torch.linalg.cross(up, e1)


def orbit_cameras(center: torch.Tensor, distance: float, up: torch.Tensor, n: int, elevations: Sequence[float],
                  azimuth_span: float, width: int, height: int, fov_deg: float) -> List[Camera]:
    """n cameras on rings at `elevations` (degrees above the plane perpendicular to `up`), split
    evenly between the rings (first ring first), at evenly spaced azimuths over `azimuth_span`
    degrees (360: a full orbit), `distance` from `center` and looking at it, `up` up."""
    if n < 2 or not elevations:
        raise ConfigError(f"orbit cameras: need n >= 2 and at least one elevation, got n={n}, {list(elevations)}")
    if any(abs(e) >= 89.0 for e in elevations):
        raise ConfigError(f"orbit cameras: elevations must be within (-89, 89) degrees, got {list(elevations)}")
    e1, e2 = _horizontal_basis(up)
    rings = len(elevations)
    counts = [n // rings + (1 if k < n % rings else 0) for k in range(rings)]
    full = azimuth_span >= 360.0
    cams = []
    for elev, count in zip(elevations, counts):
        if full:
            azs = [360.0 * k / count for k in range(count)]
        else:
            azs = torch.linspace(-azimuth_span / 2, azimuth_span / 2, count).tolist() if count > 1 else [0.0]
        e = math.radians(elev)
        for az in azs:
            a = math.radians(az)
            d = math.cos(e) * (math.cos(a) * e1 + math.sin(a) * e2) + math.sin(e) * up
            name = f"orbit_{len(cams):03d}_az{az:+04.0f}_el{elev:+03.0f}"
            cams.append(look_at(center + distance * d, center, width, height, fov_deg=fov_deg, name=name, up=up))
    return cams


# ------------------------------------------------------------------------------------- selections
def select_top(model: GaussianModel, up: torch.Tensor, fraction: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """(region, related): Gaussians in the upper `fraction` of the object's height along `up`
    (2%-98% quantiles of the opaque Gaussians), and the band of half that height just below."""
    if not 0 < fraction < 1:
        raise ConfigError(f"data.top_fraction must be in (0, 1), got {fraction}")
    height = model.means.detach() @ up
    opaque = model.opacities.detach() > OPAQUE
    ref = height[opaque] if int(opaque.sum()) >= 10 else height
    lo, hi = (float(x[0]) for x in quantile_box(ref[:, None], 0.02))
    cut = hi - fraction * (hi - lo)
    region = height > cut
    related = (height <= cut) & (height > cut - 0.5 * fraction * (hi - lo))
    return region, related


def select_ball(model: GaussianModel, center: torch.Tensor, radius: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """(region, related): Gaussians within `radius` of `center`, and the shell out to twice it."""
    dist = (model.means.detach() - center).norm(dim=-1)
    return dist <= radius, (dist > radius) & (dist <= 2 * radius)


def load_region(path: str, n: int) -> torch.Tensor:
    """The (n,) bool mask saved at `path` (torch.save of a bool mask or of row indices)."""
    if not os.path.isfile(path):
        raise ConfigError(f"data.region_file does not exist: {path}")
    m = torch.as_tensor(torch.load(path, map_location="cpu"))
    if m.dtype == torch.bool:
        if m.shape != (n,):
            raise ConfigError(f"data.region_file {path}: a mask of {tuple(m.shape)} rows for a splat of {n}")
        return m.clone()
    region = torch.zeros(n, dtype=torch.bool)
    region[m.long()] = True
    return region


def select_file(model: GaussianModel, path: str) -> Tuple[torch.Tensor, torch.Tensor]:
    """(region, related): the part saved at `path`, and the Gaussians around it within half the
    part's own radius of its centre's reach (its neighbours, as an editor's spill lights them)."""
    region = load_region(path, len(model))
    means = model.means.detach()
    if not bool(region.any()):
        return region, torch.zeros_like(region)
    c = means[region].mean(0)
    reach = float((means[region] - c).norm(dim=-1).max())
    return region, ((means - c).norm(dim=-1) <= 1.5 * reach) & ~region


# ------------------------------------------------------------------------------------- whole parts
def _colour_classes(rgb: torch.Tensor, n_classes: int, iters: int = 20) -> torch.Tensor:
    """(N,) class of each colour: k-means in RGB, started from colours spread along the luma
    order (deterministic)."""
    luma = rgb @ torch.tensor(_LUMA)
    order = torch.argsort(luma, stable=True)
    k = min(n_classes, len(rgb))
    centres = rgb[order[((torch.arange(k) + 0.5) / k * len(rgb)).long()]].clone()
    cls = torch.zeros(len(rgb), dtype=torch.long)
    for _ in range(iters):
        d = (rgb[:, None, :] - centres[None]).pow(2).sum(-1)  # (N, k): k is a handful
        cls = d.argmin(1)
        sums = torch.zeros_like(centres).index_add_(0, cls, rgb)
        counts = torch.bincount(cls, minlength=k).clamp_min(1)[:, None].float()
        centres = torch.where(counts > 0, sums / counts, centres)
    return cls


def segment_parts(model: GaussianModel, k: int = 8, n_colours: int = 5, smooth: int = 2, reach: float = 6.0,
                  colour_tol: float = 0.15, min_opacity: float = 0.1) -> torch.Tensor:
    """Parts of a splat found from the splat itself: connected regions of similar colour and
    position. (N,) long label per Gaussian, 0 for the largest segment, 1 the next, ...; -1 for
    Gaussians below `min_opacity` (no part).

    Each Gaussian's base colour (SH DC as RGB) is averaged with those of its `k` nearest
    neighbours within `colour_tol` of it (`smooth` rounds: a trained splat's per-Gaussian colour
    noise is not a boundary, a change of colour larger than the tolerance is) and quantised
    into `n_colours` classes (k-means); edges join each Gaussian to those of its `k` nearest
    neighbours (geometry.neighbors.knn: exact, no all-pairs matrix) of the same class within
    `reach` times the median nearest-neighbour distance; a segment is a connected component of
    that graph (`connected_components`)."""
    n = len(model)
    keep = model.opacities.detach() >= min_opacity
    idx = torch.nonzero(keep).flatten()
    labels = torch.full((n,), -1, dtype=torch.long)
    if len(idx) < 2:
        labels[idx] = 0
        return labels
    means = model.means.detach().float()[idx]
    rgb = sh_to_rgb(model.sh_dc.detach().float()[idx]).clamp(0, 1)
    d2, nb = knn(means, k)
    for _ in range(smooth):  # bilateral: only neighbours of a similar colour, so boundaries stay sharp
        w = ((rgb[nb] - rgb[:, None]).norm(dim=-1) <= colour_tol).float()[..., None]
        rgb = (rgb + (rgb[nb] * w).sum(1)) / (1 + w.sum(1))
    cls = _colour_classes(rgb, n_colours)
    kk = nb.shape[1]
    spacing = float(d2[:, 0].clamp_min(0).sqrt().median())
    src = torch.arange(len(idx)).repeat_interleave(kk)
    dst = nb.flatten()
    ok = (d2.flatten().clamp_min(0).sqrt() <= reach * max(spacing, 1e-12)) & (cls[src] == cls[dst])
    comp = connected_components(len(idx), src[ok], dst[ok])
    _, inverse, counts = torch.unique(comp, return_inverse=True, return_counts=True)
    order = torch.argsort(-counts, stable=True)  # largest first
    rank = torch.empty_like(order)
    rank[order] = torch.arange(len(order))
    labels[idx] = rank[inverse]
    return labels


def part_visibility(model: GaussianModel, region: torch.Tensor, cameras: Sequence[Camera], up: torch.Tensor,
                    side_elevation: float = 20.0) -> dict:
    """How the cameras see a part (`region`):
    - `views_seeing`: the cameras where the part covers at least one pixel's worth of weight;
    - `side_view_fraction`: of those, the fraction whose elevation over the part's centre (along
      `up`) is below `side_elevation` degrees: they see it from the side or from below;
    - `hidden_fraction`: 1 - the part's rendered weight in the whole scene / its alpha rendered
      alone, over all cameras: how much of it other Gaussians hide;
    - `view_fraction`: the median, over the cameras that see it, of the fraction of the image the
      part covers in the scene (weight summed over pixels / pixels);
    - `shown_fraction`: of the part's rendered weight in the scene, the share in pixels where it is
      more than half of the colour: near 1 for a part the views show as a region of its own, near 0
      for a colour class threaded through another part's Gaussians (no pixel is mostly it)."""
    from gs_regional.metrics.region import render_selection
    from gs_regional.registry import find

    renderer = find("torch-rasterizer", kind="renderers")()
    part_only = model.select(region)
    whole = torch.ones(len(part_only), dtype=torch.bool)
    centre = model.means.detach()[region].mean(0)
    seen_w, alone_w, shown_w, side, fractions = 0.0, 0.0, 0.0, [], []
    with torch.no_grad():
        for cam in cameras:
            cover = render_selection(model, renderer, cam, region)  # in the scene
            w = float(cover.sum())
            a = float(render_selection(part_only, renderer, cam, whole).sum())  # alone
            seen_w, alone_w, shown_w = seen_w + w, alone_w + a, shown_w + float(cover[cover > 0.5].sum())
            if w >= 1.0:
                d = cam.center.float() - centre
                elev = math.degrees(math.asin(max(-1.0, min(1.0, float(d @ up) / max(float(d.norm()), 1e-12)))))
                side.append(elev < side_elevation)
                fractions.append(w / (cam.width * cam.height))
    fractions.sort()
    return {"views_seeing": len(side), "views": len(cameras),
            "side_view_fraction": round(sum(side) / len(side), 3) if side else None,
            "hidden_fraction": round(1.0 - seen_w / alone_w, 3) if alone_w > 0 else None,
            "view_fraction": round(fractions[len(fractions) // 2], 4) if fractions else None,
            "shown_fraction": round(shown_w / seen_w, 3) if seen_w > 0 else None}


# ------------------------------------------------------------------------------------------ edits
def recolor(source: GaussianModel, region: torch.Tensor, color: Sequence[float]) -> GaussianModel:
    """`source` with the Gaussians of `region` recoloured to `color`: each keeps its luminance
    relative to the region's median (its shading and texture), view-dependent SH set to zero."""
    rgb = sh_to_rgb(source.sh_dc.detach()).clamp(0, 1)
    luma = rgb @ torch.tensor(_LUMA)
    ref = float(luma[region].median()) if bool(region.any()) else 1.0
    new = rgb.clone()
    new[region] = (torch.tensor(color, dtype=torch.float32) * (luma[region] / max(ref, 1e-3))[:, None]).clamp(0, 1)
    sh_dc = source.sh_dc.detach().clone()
    sh_dc[region] = rgb_to_sh(new[region])
    sh_rest = source.sh_rest.detach().clone()
    sh_rest[region] = 0
    return GaussianModel.from_tensors(
        means=source.means.detach(), quats=source.quats.detach(), log_scales=source.log_scales.detach(),
        opacity_logits=source.opacity_logits.detach(), sh_dc=sh_dc, sh_rest=sh_rest, mask=region,
    )


def _along_line(model: GaussianModel, through: torch.Tensor, direction: torch.Tensor, width: float):
    """(along, lateral, near): each Gaussian's position along the line through `through` along
    `direction` and its distance from it; `near`, the opaque ones within `width` of it (at least
    one, else the anchor is off the object)."""
    means = model.means.detach()
    rel = means - through
    along = rel @ direction
    lateral = (rel - along[:, None] * direction).norm(dim=-1)
    near = (lateral <= width) & (model.opacities.detach() > OPAQUE)
    if not bool(near.any()):
        raise ConfigError(
            f"splat-truth add: no opaque Gaussian within {width:.4g} of the line through the anchor "
            f"{through.tolist()} along {direction.tolist()}; move data.anchor onto the object"
        )
    return along, lateral, near


def surface_point(model: GaussianModel, through: torch.Tensor, direction: torch.Tensor, width: float) -> torch.Tensor:
    """Where the line through `through` along `direction` leaves the object on the `direction`
    side: the outermost opaque Gaussian within `width` of the line, projected onto the line."""
    along, _, near = _along_line(model, through, direction, width)
    return through + float(along[near].max()) * direction


def resting_contact(model: GaussianModel, through: torch.Tensor, direction: torch.Tensor, r: float) -> Tuple[float, int]:
    """(height, row): a sphere of radius `r` centred on the line through `through`, lowered along
    -`direction` onto the opaque Gaussians, first touches Gaussian `row` with its centre `height`
    along the line. On a dome whose top lies off the line the sphere touches the slope (a sphere
    set at the top's height floats beside it)."""
    along, lateral, near = _along_line(model, through, direction, r)
    touch = torch.where(near, along + (r * r - lateral.clamp_max(r) ** 2).sqrt(), torch.full_like(along, -float("inf")))
    row = int(touch.argmax())
    return float(touch[row]), row


def sphere_gaussians(center: torch.Tensor, radius: float, count: int, color: Sequence[float], light: torch.Tensor,
                     seed: int, sh_degree: int) -> GaussianModel:
    """A sphere of `count` flat, opaque Gaussians tangent to its surface (the synthetic scene's
    covering), of one colour shaded from `light` (0.7 in the shadow, 1.0 facing it)."""
    gen = torch.Generator().manual_seed(int(seed) + 4241)
    part = _Ellipsoid("cherry", tuple(center.tolist()), (radius,) * 3, tuple(color))
    pts, cov, normals = _sample_ellipsoid(part, int(count), gen)
    log_scales, quats = covariance_to_scales_quats(cov)
    shade = 0.7 + 0.3 * (normals.float() @ light).clamp_min(0)
    rgb = (torch.tensor(color, dtype=torch.float32) * shade[:, None]).clamp(0, 1)
    k1 = (sh_degree + 1) ** 2 - 1
    opacity = 0.99
    return GaussianModel.from_tensors(
        means=pts.float(), quats=quats.float(), log_scales=log_scales.float(),
        opacity_logits=torch.full((len(pts),), math.log(opacity / (1 - opacity))), sh_dc=rgb_to_sh(rgb),
        sh_rest=torch.zeros(len(pts), k1, 3),
    )


def with_added(source: GaussianModel, added: GaussianModel, region: torch.Tensor) -> Tuple[GaussianModel, torch.Tensor]:
    """(edited, new_region): the source rows first (same order), the added ones after them
    (generation 1); new_region marks `region` and every added row."""
    n = len(added)
    new_region = torch.cat([region, torch.ones(n, dtype=torch.bool)])
    cat = lambda name: torch.cat([getattr(source, name).detach(), getattr(added, name).detach()])  # noqa: E731
    edited = GaussianModel.from_tensors(
        means=cat("means"), quats=cat("quats"), log_scales=cat("log_scales"), opacity_logits=cat("opacity_logits"),
        sh_dc=cat("sh_dc"), sh_rest=cat("sh_rest"), mask=new_region,
        generation=torch.cat([torch.zeros(len(source), dtype=torch.long), torch.ones(n, dtype=torch.long)]),
    )
    return edited, new_region


_DEFAULT_COLOR = {"recolor": [0.36, 0.20, 0.11], "add": [0.80, 0.04, 0.09]}  # chocolate; cherry red
_DEFAULT_PROMPT = {"recolor": "make the top chocolate brown", "add": "put a cherry on top"}


@register("splat-truth")
class SplatTruthDataModule(SceneDataModuleBase):
    """A trained splat, cameras around it and a known edit of it in `scene.ground_truth`.

    Loaders (from SceneDataModuleBase): train = an endless seeded stream of {"index": i} over the
    training views, val/test = the held-out views. `scene.images` is None: edit systems render
    the splat themselves."""

    @dataclass
    class Config:
        ply: str = ""  # the trained scene (INRIA layout); read, never copied
        edit: str = "recolor"  # recolor | add
        prompt: str = ""  # the instruction the truth answers ("" = a default per edit)
        seed: int = 0
        up: List[float] = field(default_factory=lambda: [0.0, 0.0, 1.0])  # the object's up axis (world)
        front: Optional[List[float]] = None  # the direction the edit faces (None = up)
        test_every: int = 8  # hold out every n-th camera (0: no hold-out)
        # Cameras: from a camera source, or an orbit around the object when empty.
        cameras: str = ""  # COLMAP sparse/0, transforms.json or cameras.json (any format load_cameras reads)
        downscale: float = 1.0  # loaded cameras: 4 = images and intrinsics 4x smaller
        max_cameras: int = 0  # loaded cameras: 0 = all; else an evenly spread subset
        n_cameras: int = 40  # orbit
        elevations: List[float] = field(default_factory=lambda: [10.0, 30.0])  # orbit rings, degrees above the up-plane
        azimuth_span: float = 360.0  # orbit, degrees (360: all around)
        radius: float = 2.6  # orbit distance, in object radii
        width: int = 96  # orbit image size
        height: int = 96
        fov: float = 45.0  # orbit, degrees
        # The edit (positions and sizes in object radii from the object centre).
        color: Optional[List[float]] = None  # new colour (recolor) / the new object's colour (add); None = default
        select: str = "top"  # recolor: top | ball | file
        region_file: str = ""  # recolor `file` / add: a saved mask of the part (torch.save; bool or indices)
        top_fraction: float = 0.5  # recolor top: upper fraction of the object's height
        ball_radius: float = 0.35  # recolor ball
        anchor: List[float] = field(default_factory=lambda: [0.62, 0.0, 0.0])  # ball centre / where the add sits
        add_radius: float = 0.12  # add: the sphere's radius
        add_count: int = 400  # add: Gaussians on the sphere
        add_sink: float = 0.25  # add: fraction of its radius the sphere sinks into the surface
        add_direction: Optional[List[float]] = None  # add: the side of the surface it rests on (None = up)
        region_radius: float = 2.0  # add: region = splat Gaussians within this many sphere radii of it

    def __init__(self, cfg=None) -> None:
        super().__init__()
        self.cfg = parse_structured(self.Config, cfg, where="data")
        c = self.cfg
        if not c.ply:
            raise ConfigError("data.ply is not set: give the trained splat (data.ply=path/to/point_cloud.ply)")
        if not os.path.isfile(c.ply):
            raise ConfigError(f"data.ply does not exist: {c.ply}")
        if c.edit not in EDIT_NAMES:
            raise ConfigError(f"data.edit: unknown splat edit '{c.edit}'; known: {', '.join(EDIT_NAMES)}")
        if c.select not in SELECT_RULES:
            raise ConfigError(f"data.select: unknown rule '{c.select}'; known: {', '.join(SELECT_RULES)}")
        if c.select == "file" and c.edit == "recolor" and not c.region_file:
            raise ConfigError("data.select=file needs data.region_file (a saved mask of the part)")
        if c.cameras and not os.path.exists(c.cameras):
            raise ConfigError(f"data.cameras does not exist: {c.cameras}")
        if c.downscale <= 0:
            raise ConfigError(f"data.downscale must be > 0, got {c.downscale}")
        self.scene: Optional[SceneData] = None

    def cameras(self, center: torch.Tensor, radius: float, up: torch.Tensor) -> List[Camera]:
        c = self.cfg
        if not c.cameras:
            return orbit_cameras(center, c.radius * radius, up, c.n_cameras, c.elevations, c.azimuth_span,
                                 c.width, c.height, c.fov)
        cams = load_cameras(c.cameras)
        if c.max_cameras and len(cams) > c.max_cameras:
            step = len(cams) / c.max_cameras
            cams = [cams[int(i * step)] for i in range(c.max_cameras)]
        return [cam.scaled(1.0 / c.downscale) for cam in cams] if c.downscale != 1.0 else cams

    def ground_truth(self, source: GaussianModel, center: torch.Tensor, radius: float, up: torch.Tensor) -> GroundTruth:
        c = self.cfg
        color = list(c.color) if c.color is not None else _DEFAULT_COLOR[c.edit]
        if len(color) != 3:
            raise ConfigError(f"data.color must be an RGB triple in [0, 1], got {color}")
        anchor = center + radius * torch.as_tensor(c.anchor, dtype=torch.float32)
        if c.edit == "recolor":
            if c.select == "top":
                region, related = select_top(source, up, c.top_fraction)
            elif c.select == "file":
                region, related = select_file(source, c.region_file)
            else:
                region, related = select_ball(source, anchor, c.ball_radius * radius)
            if not bool(region.any()):
                raise ConfigError(f"splat-truth recolor: the '{c.select}' rule selects no Gaussian; widen it")
            edited, new_region = recolor(source, region, color), region.clone()
        else:
            r = c.add_radius * radius
            side = up if c.add_direction is None else _unit(c.add_direction, "data.add_direction")
            height, _ = resting_contact(source, anchor, side, r)
            sphere_center = anchor + (height - c.add_sink * r) * side
            added = sphere_gaussians(sphere_center, r, c.add_count, color, up, c.seed, source.sh_degree)
            region, related = select_ball(source, sphere_center, c.region_radius * r)
            if c.region_file:  # the whole part the object rests on
                region, related = select_file(source, c.region_file)
            edited, new_region = with_added(source, added, region)
        front = _unit(c.front, "data.front") if c.front is not None else up
        return GroundTruth(
            source=source, edited=edited, region=region, new_region=new_region, related=related,
            front=front, center=center, name=c.edit, prompt=c.prompt or _DEFAULT_PROMPT[c.edit],
        )

    def setup(self, stage: Optional[str] = None) -> None:
        if self.scene is not None:
            return
        c = self.cfg
        source = GaussianModel.from_ply(c.ply).requires_grad_(False)
        up = _unit(c.up, "data.up")
        center, radius = object_frame(source)
        cameras = self.cameras(center, radius, up)
        train, test = split_every(len(cameras), c.test_every)
        self.scene = SceneData(cameras=cameras, images=None, train_indices=train, test_indices=test,
                               ground_truth=self.ground_truth(source, center, radius, up),
                               source=f"splat-truth:{c.edit}:{c.ply}")
