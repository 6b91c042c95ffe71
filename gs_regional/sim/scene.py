"""A procedural 3DGS scene whose edits are known exactly: the yardstick for the 3D part of the method.

The scene is a small figure standing on a textured ground disc in front of a striped, curved
backdrop. World frame: y up, the figure faces +z (`FRONT`), it stands on y = -0.6 and is ~1.2 tall.

    part     colour        what it is
    ground   grey check    disc of radius 3.2 at y = -0.6 (floor, gives depth below the figure)
    backdrop pastel stripes cylinder of radius 3.2 behind the rig (|azimuth| >= 35 deg)
    body     blue          ellipsoid
    head     skin          sphere on top of the body
    nose     orange        elongated ellipsoid sticking out of the face (+z)
    eyes     near black    two small spheres on the face
    arms     green         two elongated ellipsoids from the shoulders

Every surface is sampled with flat, mostly opaque Gaussians (a Fibonacci lattice mapped onto each
ellipsoid, a jittered grid on the planes) whose footprints overlap, so renders are solid. Shading
is baked into the colours (SH degree 0).

Named ground-truth edits (`make_edit`):
  recolor  the head turns red; region = the head's Gaussians; same Gaussians, new colours.
  add      a handlebar moustache made of NEW Gaussians (generation 1) below the nose whose tips
           stick out beside the head, past the figure's silhouette in the front view; region = the
           head's Gaussians (the part it is attached to, which is what an editor's mask selects);
           edited = source + the new Gaussians.
  global   a sepia colour transform of every Gaussian (background included); region = all.
  empty    an instruction about something the scene does not show ("put a hat on the cat"):
           region = none, edited = source; the right answer is to change nothing.
Each is returned as a `GroundTruth` (gs_regional.sim.truth); its `related` part (what a real
editor's relevance tends to light up too) is the body for `recolor` and `add`, none for `global`
and `empty`.

`SyntheticDataModule` (registered as `synthetic-scene`) serves renders of the source scene at
a front-biased ring of cameras, with the ground truth in `SceneData.ground_truth`.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable, Dict, List, Optional, Tuple

import torch

from gs_regional.config import parse_structured
from gs_regional.data.cameras import Camera
from gs_regional.data.datamodule import SceneDataModuleBase
from gs_regional.data.scene import SceneData, split_every
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.registry import find, register
from gs_regional.utils.rotations import covariance_to_scales_quats, rotmat_to_quat
from gs_regional.utils.sh import rgb_to_sh
from gs_regional.sim.truth import GroundTruth

FRONT = (0.0, 0.0, 1.0)  # the direction the figure faces
TARGET = (0.0, 0.0, 0.0)  # where the cameras look
GROUND_Y = -0.6
BACKDROP_RADIUS = 3.2
BACKDROP_TOP = 2.2
BACKDROP_MIN_AZIMUTH = 35.0  # degrees; the backdrop is left open in front, where the cameras are
CAMERA_RADIUS = 2.6
CAMERA_ELEVATIONS = (8.0, 24.0)  # degrees
CAMERA_AZIMUTH_SPAN = 100.0  # degrees either side of the front
CAMERA_FOV = 45.0  # degrees, vertical and horizontal (square pixels)

PART_NAMES = ["ground", "backdrop", "body", "head", "nose", "eyes", "arms"]
OBJECT_PARTS = ("body", "head", "nose", "eyes", "arms")
EDIT_NAMES = ("recolor", "add", "global", "empty")

_OBJECT_OPACITY = 0.97
_BACKGROUND_OPACITY = 0.95
_COVER = 0.7  # footprint sigma as a fraction of the sample spacing: overlapping, solid renders
_FLAT = 0.15  # thickness of a splat relative to its footprint
_LIGHT = (-0.4, 0.6, 0.7)  # baked-in shading comes from the upper front-left
_SEPIA = ((0.393, 0.769, 0.189), (0.349, 0.686, 0.168), (0.272, 0.534, 0.131))
_RED = (0.82, 0.12, 0.08)
_MOUSTACHE = (0.28, 0.16, 0.07)


@dataclass
class _Ellipsoid:
    name: str  # part label
    centre: Tuple[float, float, float]
    radii: Tuple[float, float, float]
    colour: Tuple[float, float, float]
    axis: Optional[Tuple[float, float, float]] = None  # direction of the local y axis (default: world y)


def _rotation_to(axis) -> torch.Tensor:
    """A rotation taking local +y to `axis` (double)."""
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    y = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    v = torch.linalg.cross(y, a)
    c = float(y @ a)
    if v.norm() < 1e-9:
        return torch.eye(3, dtype=torch.float64) if c > 0 else torch.diag(torch.tensor([1.0, -1.0, -1.0])).double()
    vx = torch.tensor([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + vx + vx @ vx / (1 + c)


def _figure_parts() -> List[_Ellipsoid]:
    head_c, head_r = (0.0, 0.38, 0.0), 0.2

    def on_head(dx: float, dy: float) -> Tuple[float, float, float]:
        dz = math.sqrt(head_r**2 - dx**2 - dy**2)
        return (head_c[0] + dx, head_c[1] + dy, head_c[2] + dz)

    return [
        _Ellipsoid("body", (0.0, -0.2, 0.0), (0.30, 0.40, 0.25), (0.20, 0.35, 0.78)),
        _Ellipsoid("head", head_c, (head_r,) * 3, (0.93, 0.76, 0.60)),
        _Ellipsoid("nose", (0.0, 0.355, 0.215), (0.035, 0.035, 0.07), (0.97, 0.50, 0.10)),
        _Ellipsoid("eyes", on_head(-0.075, 0.05), (0.028,) * 3, (0.07, 0.07, 0.09)),
        _Ellipsoid("eyes", on_head(0.075, 0.05), (0.028,) * 3, (0.07, 0.07, 0.09)),
        _Ellipsoid("arms", (-0.37, -0.12, 0.03), (0.065, 0.26, 0.065), (0.25, 0.65, 0.30), (-0.42, 0.9, -0.05)),
        _Ellipsoid("arms", (0.37, -0.12, 0.03), (0.065, 0.26, 0.065), (0.25, 0.65, 0.30), (0.42, 0.9, -0.05)),
    ]


def _moustache_parts() -> List[_Ellipsoid]:
    """Beads along a curve under the nose that follows the face and sweeps past the cheeks."""
    head_c, head_r = (0.0, 0.38, 0.0), 0.2
    beads = []
    for x in torch.linspace(-0.30, 0.30, 17).tolist():
        t = abs(x) / 0.30
        y = 0.295 + 0.06 * t**2  # tips curl up
        z = math.sqrt(max(head_r**2 - x**2 - (y - head_c[1]) ** 2, 0.0)) + 0.03
        r = 0.03 - 0.012 * t  # tapering
        beads.append(_Ellipsoid("moustache", (x, y, z), (r, r, r), _MOUSTACHE))
    return beads


def _fibonacci_sphere(n: int, gen: torch.Generator) -> torch.Tensor:
    """n nearly evenly spaced unit vectors, randomly rotated (double)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    r = torch.sqrt((1 - z * z).clamp_min(0))
    phi = i * math.pi * (3 - math.sqrt(5)) + float(torch.rand(1, generator=gen, dtype=torch.float64)) * 2 * math.pi
    u = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    return u @ q.T


def _ellipsoid_area(radii) -> float:
    a, b, c = radii  # Knud Thomsen's approximation, within ~1%
    p = 1.6075
    return 4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)


def _sample_ellipsoid(part: _Ellipsoid, n: int, gen: torch.Generator):
    """Points, covariances and outward normals of n flat Gaussians covering an ellipsoid.

    The lattice and flat discs are laid out on the unit sphere and pushed through the linear map
    that makes the ellipsoid, so the covering stays gap-free on elongated parts too."""
    u = _fibonacci_sphere(n, gen)
    spacing = math.sqrt(4 * math.pi / n)
    st, sn = _COVER * spacing, _FLAT * _COVER * spacing
    rot = _rotation_to(part.axis) if part.axis is not None else torch.eye(3, dtype=torch.float64)
    radii = torch.tensor(part.radii, dtype=torch.float64)
    A = rot @ torch.diag(radii)
    centre = torch.tensor(part.centre, dtype=torch.float64)
    pts = centre + u @ A.T
    uu = u[:, :, None] * u[:, None, :]
    cov_sphere = st**2 * (torch.eye(3, dtype=torch.float64) - uu) + sn**2 * uu
    cov = A @ cov_sphere @ A.T
    normals = (u / radii) @ rot.T
    normals = normals / normals.norm(dim=-1, keepdim=True)
    return pts, cov, normals


def _inside(part: _Ellipsoid, pts: torch.Tensor, margin: float = 0.995) -> torch.Tensor:
    rot = _rotation_to(part.axis) if part.axis is not None else torch.eye(3, dtype=torch.float64)
    local = (pts - torch.tensor(part.centre, dtype=torch.float64)) @ rot / torch.tensor(part.radii, dtype=torch.float64)
    return local.norm(dim=-1) < margin


def _shade(normals: torch.Tensor) -> torch.Tensor:
    light = torch.tensor(_LIGHT, dtype=torch.float64)
    light = light / light.norm()
    return 0.55 + 0.45 * (normals @ light).clamp_min(0)


def _surface(parts: List[_Ellipsoid], n_total: int, gen: torch.Generator, avoid: List[_Ellipsoid]):
    """Sample the union of `parts` with about n_total Gaussians (split by area); drop the samples
    buried inside another part of `parts` or `avoid`, which a render never shows."""
    areas = [_ellipsoid_area(p.radii) for p in parts]
    total = sum(areas)
    out = []
    for k, part in enumerate(parts):
        n = max(60, int(round(n_total * areas[k] / total)))
        pts, cov, normals = _sample_ellipsoid(part, n, gen)
        keep = torch.ones(n, dtype=torch.bool)
        for j, other in enumerate(parts + avoid):
            if j != k:
                keep &= ~_inside(other, pts)
        colour = torch.tensor(part.colour, dtype=torch.float64) * _shade(normals)[:, None]
        out.append((part.name, pts[keep], cov[keep], colour[keep]))
    return out


def _background(n: int, gen: torch.Generator):
    """Ground disc (checker) and cylindrical backdrop (pastel stripes with a vertical gradient)."""
    ground_area = math.pi * BACKDROP_RADIUS**2
    arc = 2 * math.pi - 2 * math.radians(BACKDROP_MIN_AZIMUTH)
    height = BACKDROP_TOP - GROUND_Y
    wall_area = BACKDROP_RADIUS * arc * height
    spacing = math.sqrt((ground_area + wall_area) / max(n, 1))
    st, sn = _COVER * spacing, _FLAT * _COVER * spacing

    # ground: grid over the square, cropped to the disc
    k = int(math.ceil(2 * BACKDROP_RADIUS / spacing))
    g = (torch.arange(k, dtype=torch.float64) + 0.5) * spacing - BACKDROP_RADIUS
    gx, gz = torch.meshgrid(g, g, indexing="ij")
    xz = torch.stack([gx.flatten(), gz.flatten()], -1)
    xz = xz + (torch.rand(xz.shape, generator=gen, dtype=torch.float64) - 0.5) * 0.4 * spacing
    xz = xz[xz.norm(dim=-1) < BACKDROP_RADIUS]
    ground = torch.stack([xz[:, 0], torch.full_like(xz[:, 0], GROUND_Y), xz[:, 1]], -1)
    tile = 0.5
    check = ((torch.floor(xz[:, 0] / tile) + torch.floor(xz[:, 1] / tile)) % 2)[:, None]
    ground_rgb = check * torch.tensor([0.58, 0.54, 0.46], dtype=torch.float64) + (1 - check) * torch.tensor(
        [0.36, 0.33, 0.29], dtype=torch.float64
    )
    t1 = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).expand(len(ground), 3)
    t2 = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(len(ground), 3)
    nrm = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(len(ground), 3)

    # backdrop: grid over (arc length, height) on the cylinder
    na = int(math.ceil(BACKDROP_RADIUS * arc / spacing))
    nh = int(math.ceil(height / spacing))
    a0 = math.radians(BACKDROP_MIN_AZIMUTH)
    az = a0 + (torch.arange(na, dtype=torch.float64) + 0.5) / na * arc
    hy = GROUND_Y + (torch.arange(nh, dtype=torch.float64) + 0.5) / nh * height
    A, Y = torch.meshgrid(az, hy, indexing="ij")
    A = A.flatten() + (torch.rand(A.numel(), generator=gen, dtype=torch.float64) - 0.5) * 0.4 * spacing / BACKDROP_RADIUS
    Y = Y.flatten() + (torch.rand(Y.numel(), generator=gen, dtype=torch.float64) - 0.5) * 0.4 * spacing
    wall = torch.stack([BACKDROP_RADIUS * torch.sin(A), Y, BACKDROP_RADIUS * torch.cos(A)], -1)
    palette = torch.rand(6, 3, generator=gen, dtype=torch.float64) * 0.45 + 0.45  # pastel
    stripe = torch.floor((A - a0) / math.radians(14)).long() % len(palette)
    band = (torch.sin(Y * 9.0) > 0.6).double()[:, None]  # thin horizontal bands for texture
    wall_rgb = palette[stripe] * (0.65 + 0.35 * (Y - GROUND_Y)[:, None] / height) * (1 - 0.25 * band)
    inward = -torch.stack([torch.sin(A), torch.zeros_like(A), torch.cos(A)], -1)
    w1 = torch.stack([torch.cos(A), torch.zeros_like(A), -torch.sin(A)], -1)
    w2 = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(len(wall), 3)

    pts = torch.cat([ground, wall])
    rgb = torch.cat([ground_rgb, wall_rgb])
    t1, t2, nrm = torch.cat([t1, w1]), torch.cat([t2, w2]), torch.cat([nrm, inward])
    R = torch.stack([t1, t2, nrm], -1)  # columns: the splat's axes
    R[:, :, 0] *= torch.sign(torch.linalg.det(R))[:, None]  # a proper rotation
    log_scales = torch.log(torch.tensor([st, st, sn], dtype=torch.float64)).expand(len(pts), 3)
    labels = torch.cat([torch.zeros(len(ground), dtype=torch.long), torch.ones(len(wall), dtype=torch.long)])
    return pts, rotmat_to_quat(R), log_scales.clone(), rgb, labels


@dataclass(frozen=True)
class _Arrays:
    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity: torch.Tensor
    rgb: torch.Tensor  # linear colour before the SH encoding, in [0, 1]
    labels: torch.Tensor


def _assemble(chunks) -> _Arrays:
    return _Arrays(*[torch.cat([c[i] for c in chunks]) for i in range(6)])


def _object_chunk(parts, n, gen, avoid, label_of, opacity):
    chunks = []
    for name, pts, cov, rgb in _surface(parts, n, gen, avoid):
        log_scales, quats = covariance_to_scales_quats(cov)
        # a little per-Gaussian colour variation, multiplicative so that recolouring keeps it
        rgb = rgb * (1 + 0.04 * torch.randn(len(rgb), 1, generator=gen, dtype=torch.float64))
        chunks.append(
            (pts, quats, log_scales, torch.full((len(pts),), opacity, dtype=torch.float64), rgb.clamp(0, 1),
             torch.full((len(pts),), label_of(name), dtype=torch.long))
        )
    return chunks


@lru_cache(maxsize=8)
def _scene_arrays(seed: int, n_object: int, n_background: int) -> _Arrays:
    gen = torch.Generator().manual_seed(int(seed))
    chunks = _object_chunk(_figure_parts(), n_object, gen, [], PART_NAMES.index, _OBJECT_OPACITY)
    pts, quats, log_scales, rgb, labels = _background(n_background, gen)
    rgb = (rgb * (1 + 0.04 * torch.randn(len(rgb), 1, generator=gen, dtype=torch.float64))).clamp(0, 1)
    chunks.append((pts, quats, log_scales, torch.full((len(pts),), _BACKGROUND_OPACITY, dtype=torch.float64), rgb, labels))
    return _assemble(chunks)


@lru_cache(maxsize=8)
def _moustache_arrays(seed: int, n_object: int) -> _Arrays:
    gen = torch.Generator().manual_seed(int(seed) + 7919)
    beads = _moustache_parts()
    # same surface density as the figure
    density = n_object / sum(_ellipsoid_area(p.radii) for p in _figure_parts())
    n = int(density * sum(_ellipsoid_area(b.radii) for b in beads))
    head = [p for p in _figure_parts() if p.name in ("head", "nose")]
    return _assemble(_object_chunk(beads, n, gen, head, lambda _: -1, _OBJECT_OPACITY))


def _to_model(a: _Arrays, generation: Optional[torch.Tensor] = None, mask: Optional[torch.Tensor] = None) -> GaussianModel:
    op = a.opacity.clamp(1e-4, 1 - 1e-4)
    return GaussianModel.from_tensors(
        means=a.means.float(), quats=a.quats.float(), log_scales=a.log_scales.float(),
        opacity_logits=torch.log(op / (1 - op)).float(), sh_dc=rgb_to_sh(a.rgb).float(),
        mask=mask, generation=generation,
    )


def make_scene(seed: int = 0, n_object: int = 6000, n_background: int = 4000) -> Tuple[GaussianModel, torch.Tensor, List[str]]:
    """The source scene: (GaussianModel with SH degree 0, part label per Gaussian, part names).

    Deterministic given the arguments; `part_names[label]` names a Gaussian's part."""
    if n_object < 500 or n_background < 500:
        raise ValueError(f"make_scene: n_object and n_background must be >= 500, got {n_object}, {n_background}")
    a = _scene_arrays(int(seed), int(n_object), int(n_background))
    return _to_model(a), a.labels.clone(), list(PART_NAMES)


def part_masks(seed: int = 0, n_object: int = 6000, n_background: int = 4000) -> Dict[str, torch.Tensor]:
    """The named parts of `make_scene(seed, ...)`: part name -> (N,) bool mask of its Gaussians,
    every name of PART_NAMES (both eyes are `eyes`, both arms `arms`)."""
    _, labels, names = make_scene(seed, n_object, n_background)
    return {name: labels == i for i, name in enumerate(names)}


def look_at(center, target, width: int, height: int, fov_deg: float = CAMERA_FOV, name: str = "",
            up=(0.0, 1.0, 0.0)) -> Camera:
    """An OpenCV-convention camera at `center` looking at `target`, with `up` (world +y by default)
    pointing up in the image; `up` must not be parallel to the viewing direction."""
    c = torch.as_tensor(center, dtype=torch.float64)
    fwd = torch.as_tensor(target, dtype=torch.float64) - c
    fwd = fwd / fwd.norm()
    right = torch.linalg.cross(fwd, torch.as_tensor(up, dtype=torch.float64))
    right = right / right.norm()
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])  # rows: camera axes in world coordinates
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ c
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return Camera(w2c.float(), fx=f, fy=f, cx=width / 2, cy=height / 2,
                  width=width, height=height, image_name=name)


def make_cameras(n: int = 40, width: int = 96, height: int = 96, seed: int = 0) -> Tuple[List[Camera], torch.Tensor]:
    """(cameras, front): n cameras on an arc spanning +-100 deg of azimuth around the figure's front,
    at two elevations (first all the low ones, then the high ones, each sorted by azimuth), all
    looking at the figure, with a small seeded jitter; `front` (3,) is the unit direction the figure
    faces (from the figure towards the frontal cameras)."""
    if n < 2:
        raise ValueError(f"make_cameras: need at least 2 cameras, got n={n}")
    gen = torch.Generator().manual_seed(int(seed) + 101)
    cams = []
    counts = [n - n // 2, n // 2]
    for elev, count in zip(CAMERA_ELEVATIONS, counts):
        azs = torch.linspace(-CAMERA_AZIMUTH_SPAN, CAMERA_AZIMUTH_SPAN, count, dtype=torch.float64)
        for az in azs.tolist():
            j = (torch.rand(3, generator=gen, dtype=torch.float64) - 0.5).tolist()
            a = math.radians(az + 3.0 * j[0])
            e = math.radians(elev + 2.0 * j[1])
            r = CAMERA_RADIUS * (1 + 0.04 * j[2])
            center = (r * math.cos(e) * math.sin(a), TARGET[1] + r * math.sin(e), r * math.cos(e) * math.cos(a))
            name = f"view_{len(cams):03d}_az{az:+04.0f}_el{elev:02.0f}"
            cams.append(look_at(center, TARGET, width, height, name=name))
    return cams, torch.tensor(FRONT, dtype=torch.float32)


def _sepia(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb @ torch.tensor(_SEPIA, dtype=rgb.dtype).T).clamp(0, 1)


_PROMPTS = {
    "recolor": "make his head red",
    "add": "give him a mustache",
    "global": "make it look like an old sepia photograph",
    "empty": "put a hat on the cat",
}
# A part next to the region that a real editor's relevance tends to light up too (the simulated
# editor's `leakage`); None for global edits.
_RELATED = {"recolor": "body", "add": "body", "global": None, "empty": None}


def make_edit(name: str, seed: int = 0, n_object: int = 6000, n_background: int = 4000) -> GroundTruth:
    """A named ground-truth edit of `make_scene(seed, ...)` (see the module docstring).

    The edited scene keeps the source's rows first (same order), new Gaussians follow."""
    if name not in EDIT_NAMES:
        raise ValueError(f"unknown synthetic edit '{name}'; known edits: {', '.join(EDIT_NAMES)}")
    source, labels, names = make_scene(seed, n_object, n_background)
    a = _scene_arrays(int(seed), int(n_object), int(n_background))
    head = labels == names.index("head")
    if name == "recolor":
        region = head
        rgb = a.rgb.clone()
        base = torch.tensor(_figure_parts()[1].colour, dtype=torch.float64)
        rgb[region] = (rgb[region] / base * torch.tensor(_RED, dtype=torch.float64)).clamp(0, 1)
        new_region = region.clone()
        edited = _to_model(_Arrays(a.means, a.quats, a.log_scales, a.opacity, rgb, a.labels), mask=new_region)
    elif name == "add":
        region = head
        m = _moustache_arrays(int(seed), int(n_object))
        both = _assemble([(a.means, a.quats, a.log_scales, a.opacity, a.rgb, a.labels),
                          (m.means, m.quats, m.log_scales, m.opacity, m.rgb, m.labels)])
        generation = torch.cat([torch.zeros(len(a.means), dtype=torch.long), torch.ones(len(m.means), dtype=torch.long)])
        new_region = torch.cat([region, torch.ones(len(m.means), dtype=torch.bool)])
        edited = _to_model(both, generation, mask=new_region)
    elif name == "empty":
        region = torch.zeros(len(labels), dtype=torch.bool)
        new_region = region.clone()
        edited = _to_model(a, mask=new_region)
    else:  # global
        region = torch.ones(len(labels), dtype=torch.bool)
        new_region = region.clone()
        edited = _to_model(_Arrays(a.means, a.quats, a.log_scales, a.opacity, _sepia(a.rgb), a.labels), mask=new_region)
    related = None if _RELATED[name] is None else labels == names.index(_RELATED[name])
    return GroundTruth(
        source=source, edited=edited, region=region, new_region=new_region, related=related,
        front=torch.tensor(FRONT), center=torch.tensor(TARGET), name=name, prompt=_PROMPTS[name],
    )


def render_views(model: GaussianModel, cameras: List[Camera], background=(0.0, 0.0, 0.0)) -> List[Dict[str, torch.Tensor]]:
    """rgb/depth/alpha renders of `model` at each camera (no gradients), with the project renderer."""
    renderer = find("torch-rasterizer", kind="renderers")()
    device = model.means.device
    bg = torch.as_tensor(background, dtype=torch.float32, device=device)
    with torch.no_grad():
        return [{k: v.detach() for k, v in renderer.render(model, cam.to(device), background=bg).items()
                 if k in ("rgb", "depth", "alpha")} for cam in cameras]


@lru_cache(maxsize=4)
def _cached_source_images(seed: int, n_object: int, n_background: int, n_cameras: int, width: int, height: int,
                          background: Tuple[float, ...]) -> Tuple[torch.Tensor, ...]:
    model, _, _ = make_scene(seed, n_object, n_background)
    cameras, _ = make_cameras(n_cameras, width, height, seed)
    return tuple(r["rgb"].clamp(0, 1) for r in render_views(model, cameras, background))


class _RenderedPhotos(Sequence):
    """The scene's photos, rendered from the procedural scene when first read: an edit renders
    its source itself and never reads them (a reconstruction does), so an edit run skips the
    renders of every view. Each read gives a copy: a caller cannot change the cached renders."""

    def __init__(self, count: int, render_all: Callable[[], Tuple[torch.Tensor, ...]]) -> None:
        self._count, self._render_all = count, render_all

    def __len__(self) -> int:
        return self._count

    def __getitem__(self, i):
        images = self._render_all()
        return [im.clone() for im in images[i]] if isinstance(i, slice) else images[i].clone()


@register("synthetic-scene")
class SyntheticDataModule(SceneDataModuleBase):
    """Renders of the procedural scene, with the ground-truth edit in `scene.ground_truth`.

    Loaders (from SceneDataModuleBase): train = an endless seeded stream of {"index": i} over the
    training views, val/test = the held-out views; batch_size None."""

    @dataclass
    class Config:
        seed: int = 0  # scene, cameras and the data order
        edit: str = "recolor"  # which ground-truth edit: recolor | add | global | empty
        n_cameras: int = 40
        width: int = 96
        height: int = 96
        test_every: int = 8  # hold out every n-th camera (0: no hold-out)
        n_object: int = 6000  # Gaussians on the figure
        n_background: int = 4000  # Gaussians on the ground and the backdrop
        background: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # render background

    def __init__(self, cfg=None) -> None:
        super().__init__()
        self.cfg = parse_structured(self.Config, cfg, where="data")
        if self.cfg.edit not in EDIT_NAMES:
            raise ValueError(f"data.edit: unknown synthetic edit '{self.cfg.edit}'; known: {', '.join(EDIT_NAMES)}")
        self.scene: Optional[SceneData] = None

    def setup(self, stage: Optional[str] = None) -> None:
        if self.scene is not None:
            return
        c = self.cfg
        cameras, _ = make_cameras(c.n_cameras, c.width, c.height, c.seed)
        key = (c.seed, c.n_object, c.n_background, c.n_cameras, c.width, c.height, tuple(float(v) for v in c.background))
        images = _RenderedPhotos(len(cameras), lambda: _cached_source_images(*key))
        train, test = split_every(len(cameras), c.test_every)
        truth = make_edit(c.edit, seed=c.seed, n_object=c.n_object, n_background=c.n_background)
        self.scene = SceneData(cameras=cameras, images=images, train_indices=train,
                               test_indices=test, ground_truth=truth, source=f"synthetic:{c.edit}")
