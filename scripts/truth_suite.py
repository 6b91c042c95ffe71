#!/usr/bin/env python
"""A truth suite that cannot be memorized: known edits drawn at random from a seed it prints.

    python scripts/truth_suite.py [--seed N] [--cases 24] [--quick] [--out outputs/truth_suite] [key=value ...]
    make truth-suite [SEED=N]

Each run draws `--cases` (default 24) known edits from a fresh random seed, printed first (`--seed N`
redraws the same cases), and runs each one as a full launch.py run (scripts/bench_edit.py `run`:
`regional-edit` with the `simulated-editor` and `simulated-depth` at their default failure modes),
read back from its save/metrics.json.

Scenes (every case a `splat-truth` edit of a trained splat, gs_regional/sim/splat_truth.py, unless
said otherwise):
  synthetic:<k>  the procedural scene `make_scene(k)` (figure, ground and backdrop; y up, facing +z)
                 written as a PLY with its own 24 cameras (cameras.json), for 6 scene seeds k drawn
                 at random; a quarter of its large recolours and larger additions are instead the
                 scene's own edits (`synthetic-scene`: the head turned red, the moustache).
  donut          ../shared/data/donut/donut.ply (z up; an orbit of 24 cameras).
  face           a splat fitted to ../shared/data/face with configs/reconstruct.yaml (64², 24 cameras,
                 400 steps), once: cached as OUT/face_fit/ and reused while its settings match
                 (delete the folder to refit); edited from 24 of its own cameras at 64².
The shared data is ../shared/data beside the checkout or $GS_REGIONAL_DATA; scenes whose data is
missing are named on stdout and their cases left out, the others run.

Kinds (24 cases: 4 on the donut, 4 on the face, one of each kind; 16 on the synthetic scenes, 4 of
each kind), sizes in radii of the scene's subject (the figure, the donut, the head):
  recolor_small  the Gaussians within 0.12-0.25 of a point on the subject's visible surface
  recolor_large  the donut's top 30-60 % (the icing side); elsewhere a ball of 0.45-0.7 radii
  add_small      a sphere of radius 0.06-0.10 (100-200 Gaussians) resting on the subject (seen from up)
  add_large      a sphere of radius 0.15-0.25 (300-600 Gaussians)
An addition's selected region (what the editor's relevance lights up and localization should find:
the part the object sits on) is the splat's Gaussians within 1.2-8 sphere radii of it (log-uniform;
widened by 1.25x steps while it holds fewer Gaussians than the object, as where a ball barely
touches a sparse surface), so from about the object's own size up to tens of times its Gaussian
count (`region_to_added` in each record). Colours, anchors and run seeds are random too; the prompt names the part.

Per case it records the footprint PSNR against the truth and what doing nothing scores there
(gain = the difference), the PSNR outside the footprint, of the unedited region, mask IoU,
Gaussians added against the truth's, source Gaussians deleted, UNet evaluations and seconds.
Writes OUT/truth_suite.json (seed, settings, one record per case), OUT/truth_suite.png (per-case
gain and outside-footprint PSNR, each sorted, with the targets drawn), and prints the distribution
and which cases miss which target:
  every case gain > 0 dB; median gain >= +6 dB (recolours >= +10 dB); outside the footprint
  >= 45 dB every case, median >= 50 dB; unedited region >= 50 dB; median mask IoU >= 0.9; no
  stopped run (every case has a real edit: a stop is a false safe stop); no source Gaussian
  deleted; Gaussians added <= 2x the truth's (a recolour: fewer than 1 % of its region).

Budget (the default, full): 24 cameras at 64², localization on 8 views, 3 refinement cycles x 60
iterations with 6 views each, 2 turntable frames, no checkpoints: 24 cases in about 17 min on one
core of this 2-core CPU (seed 26164 at the nineteenth session's code, --threads 1: a donut case
about 2 min, a face case 45 s, a synthetic one 22 s), inside 30 min; two halves side by side
(--only) take about half that. Seed 159258 at the fifth session's code: 675 s on both cores.
--quick (a test runs it; about 15 s): 3 cases on synthetic scenes only, 16 cameras at 48², one
refinement cycle of 10 iterations.
--replot redraws the chart and the distribution from OUT/truth_suite.json without running.
--only c03,c17 and --kind recolor|add re-run part of a draw, each case as in the whole draw (into
outputs/truth_suite/part unless --out is given). `system.localization.min_view_agreement=1.01`
stops every run right after localization: a draw's mask IoU in about 2 minutes. --size 128 runs
the draw at 128² views instead of 64² (the face photos scaled alike).
--repeats R runs each case R times (run seeds +0..+R-1: the editor's draws, the views, the
densification samples; the scene and the truth stay) and reports each case's median run with its
range: one run of a case differs from the next seed's by several dB outside the footprint
(docs/results.md), more than most changes between two codes. --compare BEFORE sets a run (or
--replot) against another run of the draw case by case, a difference inside both runs' ranges
marked `~`.
"""
from __future__ import annotations

import argparse
import colorsys
import json
import math
import os
import random
import statistics
import sys
import time
from typing import Dict, List, Optional, Sequence, Tuple

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import sweeps  # noqa: E402
from bench_edit import ROOT, run  # noqa: E402

SHARED_DATA = sweeps.SHARED_DATA
DONUT = os.path.join(SHARED_DATA, "donut", "donut.ply")
FACE = os.path.join(SHARED_DATA, "face")
JSON_NAME, PNG_NAME = "truth_suite.json", "truth_suite.png"

KINDS = ("recolor_small", "recolor_large", "add_small", "add_large")
N_SYNTHETIC_SEEDS = 6  # scene seeds of the synthetic scene drawn per run (>= 5)
NATIVE_SHARE = 0.25  # synthetic large recolours / larger additions drawn as the scene's own edits

# Kept in every record; a key metrics.json lacks (e.g. mask_iou_seen of an older run) is None.
MIN_REGION_TO_ADDED = 1.0  # an addition's region holds at least the object's own Gaussian count

METRIC_KEYS = (
    "psnr_region_vs_true_edit", "psnr_region_source_vs_true_edit", "psnr_outside_vs_true_edit",
    "psnr_outside_source_vs_true_edit", "psnr_vs_true_edit", "psnr_source_vs_true_edit", "psnr_unedited",
    "ssim_region_vs_true_edit", "mask_iou", "mask_iou_seen", "mask_iou_exact_masks", "mask_precision", "mask_recall", "view_agreement",
    "edit_coverage", "edit_coverage_views", "footprint_fraction", "gaussians_before", "gaussians_added", "gaussians_pruned",
    "gaussians_after", "true_gaussians_added", "source_deleted", "unet_evals", "seconds", "seconds_total",
    "stopped", "warnings", "count_selected", "count_recolour_declined", "count_recolour_taken", "count_recolour_distinct",
)

# The face fit (configs/reconstruct.yaml), cached in OUT/face_fit while these settings match.
FACE_FIT = ["data.downscale=8", "data.max_cameras=24", "system.max_steps=400", "system.densify.start=100",
            "system.densify.stop=300", "system.densify.every=100", "system.sh_degree_every=100",
            "checkpoint.every_n_train_steps=1000000"]
FACE_DOWNSCALE, FACE_CAMERAS = 8.0, 24


# ------------------------------------------------------------------------------------------ budget
def settings(quick: bool, size: Optional[int] = None) -> dict:
    """Scene size and the regional edit's budget of every case; `size` (px) replaces the views'
    side (64; 48 when quick), the face photos scaled to match."""
    if quick:
        s = {"n_cameras": 16, "size": 48, "budget": sweeps.regional_budget(1, 10, 3) + ["system.localization.max_views=6"]}
    else:
        s = {"n_cameras": 24, "size": 64, "budget": sweeps.regional_budget(3, 60, 6)}
    s["size"] = size or s["size"]
    s["face_downscale"] = FACE_DOWNSCALE * 64 / s["size"]
    return s


COMMON = ["system.eval.turntable_frames=2", "checkpoint.every_n_train_steps=1000000"]


# -------------------------------------------------------------------------------------------- draw
def _loguniform(rng: random.Random, lo: float, hi: float) -> float:
    return math.exp(rng.uniform(math.log(lo), math.log(hi)))


_HUES = ((15, "red"), (40, "orange"), (70, "yellow"), (160, "green"), (200, "cyan"), (255, "blue"),
         (290, "purple"), (335, "pink"), (360, "red"))


def _colour(rng: random.Random) -> Tuple[List[float], str]:
    """A saturated random colour and its name."""
    h, s, v = rng.uniform(0, 360), rng.uniform(0.6, 1.0), rng.uniform(0.55, 0.95)
    rgb = [round(c, 3) for c in colorsys.hsv_to_rgb(h / 360, s, v)]
    return rgb, next(name for top, name in _HUES if h < top)


def _offset(rng: random.Random, lo: float, hi: float) -> List[float]:
    """A point of the annulus lo <= r <= hi, uniform in area (2D, in subject radii)."""
    r = math.sqrt(rng.uniform(lo * lo, hi * hi))
    a = rng.uniform(0, 2 * math.pi)
    return [round(r * math.cos(a), 4), round(r * math.sin(a), 4)]


# Where anchors are drawn, in subject radii from its centre, in the plane across the direction the
# surface point is looked for (recolour: `front`; addition: `Subject.add_up`), per scene family.
ANCHOR_RANGES = {
    "synthetic": {"recolor": (0.0, 0.55), "add": (0.0, 0.5)},
    "donut": {"recolor": (0.45, 0.8), "add": (0.45, 0.8)},  # on the ring, not in the hole
    "face": {"recolor": (0.0, 0.45), "add": (0.0, 0.45)},
}


def _scene_slots(rng: random.Random, n: int, quick: bool) -> List[Tuple[str, str]]:
    """(scene, kind) of each case: the real scenes get n // 6 cases each (one of each kind, as far
    as they go), the synthetic ones the rest, kinds balanced, scene seeds round-robin."""
    slots: List[Tuple[str, str]] = []
    n_real = 0 if quick else n // 6
    for scene in ("donut", "face"):
        kinds = list(KINDS)
        rng.shuffle(kinds)
        slots += [(scene, kinds[i % len(KINDS)]) for i in range(n_real)]
    n_syn = n - len(slots)
    seeds = rng.sample(range(100_000), min(N_SYNTHETIC_SEEDS, max(n_syn, 1)))
    start = rng.randrange(len(KINDS))
    kinds = [KINDS[(start + i) % len(KINDS)] for i in range(n_syn)]
    rng.shuffle(kinds)
    slots += [(f"synthetic:{seeds[i % len(seeds)]}", k) for i, k in enumerate(kinds)]
    rng.shuffle(slots)
    return slots


def draw(seed: int, n_cases: int = 24, quick: bool = False) -> List[dict]:
    """The cases of one suite: pure function of (seed, n_cases, quick), no data read. Each case is
    a dict: id, scene, kind, native (the synthetic scene's own edit), run seed, colour and the
    drawn sizes and anchors (in subject radii; resolved against the splat when it runs)."""
    rng = random.Random(int(seed))
    cases = []
    for i, (scene, kind) in enumerate(_scene_slots(rng, n_cases, quick)):
        family = scene.split(":")[0]
        rgb, colour = _colour(rng)
        case = {"id": f"c{i + 1:02d}", "scene": scene, "kind": kind, "run_seed": rng.randrange(100_000),
                "color": rgb, "color_name": colour, "native": False}
        native_draw = rng.random()
        if family == "synthetic" and kind in ("recolor_large", "add_large") and native_draw < NATIVE_SHARE:
            case["native"] = True
        elif kind == "recolor_small":
            case.update(select="ball", ball_radius=round(rng.uniform(0.12, 0.25), 4),
                        offset=_offset(rng, *ANCHOR_RANGES[family]["recolor"]))
        elif kind == "recolor_large":
            if family == "donut":
                case.update(select="top", top_fraction=round(rng.uniform(0.3, 0.6), 4))
            else:
                case.update(select="ball", ball_radius=round(rng.uniform(0.45, 0.7), 4),
                            offset=_offset(rng, *ANCHOR_RANGES[family]["recolor"]))
        else:
            small = kind == "add_small"
            case.update(add_radius=round(rng.uniform(0.06, 0.10) if small else rng.uniform(0.15, 0.25), 4),
                        add_count=rng.randint(100, 200) if small else rng.randint(300, 600),
                        region_radius=round(_loguniform(rng, 1.2, 8.0), 3),
                        offset=_offset(rng, *ANCHOR_RANGES[family]["add"]))
        cases.append(case)
    return cases


# ----------------------------------------------------------------------------------------- scenes
def scene_missing(scene: str) -> Optional[str]:
    """None when the scene's data is here, else why its cases are left out."""
    if scene == "donut" and not os.path.isfile(DONUT):
        return f"donut: {DONUT} not found"
    if scene == "face" and not os.path.isfile(os.path.join(FACE, "transforms.json")):
        return f"face: {FACE}/transforms.json not found"
    return None


class Subject:
    """A scene as the draw's numbers are resolved against it: the splat (`ply`), its cameras
    (splat-truth's data keys), `up`, `front`, the subject's centre and radius (world units) and the object frame
    of splat-truth (positions in its overrides are relative to it)."""

    def __init__(self, name: str, ply: str, cameras: Dict[str, object], up, front, center, radius: float,
                 labels=None, part_names=None, add_on_front: bool = False):
        import torch

        from gs_regional.geometry.gaussian_model import GaussianModel
        from gs_regional.sim.splat_truth import object_frame

        self.name, self.ply, self.cameras = name, ply, cameras
        self.model = GaussianModel.from_ply(ply).requires_grad_(False)
        self.up = torch.as_tensor(up, dtype=torch.float32)
        self.up = self.up / self.up.norm()
        self.front = torch.as_tensor(front, dtype=torch.float32)
        self.front = self.front / self.front.norm()
        self.center = torch.as_tensor(center, dtype=torch.float32)
        self.radius = float(radius)
        self.labels, self.part_names = labels, part_names
        # splat-truth's `up` of an addition: the object rests on the surface seen from it
        self.add_up = self.front if add_on_front else self.up
        self.obj_center, self.obj_radius = object_frame(self.model)

    def to_object(self, p) -> List[float]:
        """A world point as splat-truth's `anchor` (object radii from the object centre)."""
        return [round(float(v), 5) for v in (p - self.obj_center) / self.obj_radius]

    def in_plane(self, normal, offset: Sequence[float]):
        """centre + offset (subject radii) in the plane across `normal`."""
        from gs_regional.sim.splat_truth import _horizontal_basis

        e1, e2 = _horizontal_basis(normal)
        return self.center + self.radius * (offset[0] * e1 + offset[1] * e2)

    def on_subject(self, p) -> bool:
        """Whether world point p lies on the subject: within 1.3 radii of its centre, on a surface
        (8 or more Gaussians within 0.15 radii: not a lone floater), and on the synthetic scene the
        nearest Gaussian is the figure's (not the ground's)."""
        if float((p - self.center).norm()) > 1.3 * self.radius:
            return False
        if int(((self.model.means - p).norm(dim=-1) < 0.15 * self.radius).sum()) < 8:
            return False
        if self.labels is None:
            return True
        nearest = int((self.model.means - p).norm(dim=-1).argmin())
        return int(self.labels[nearest]) >= self.part_names.index("body")

    _PART_WORDS = {"body": "body", "head": "head", "nose": "nose", "eyes": "eyes", "arms": "arm"}

    def main_part(self, region) -> Optional[str]:
        """The figure's part with the most Gaussians in `region` (synthetic scenes), or None."""
        import torch

        labels = self.labels[region]
        labels = labels[labels >= self.part_names.index("body")]
        if not len(labels):
            return None
        part = self.part_names[int(torch.bincount(labels).argmax())]
        return self._PART_WORDS.get(part, part)

    def part_at(self, p) -> str:
        """What the instruction calls the part at world point p."""
        if self.name.startswith("synthetic"):
            d = (self.model.means - p).norm(dim=-1)
            figure = self.labels >= self.part_names.index("body")
            d[~figure] = float("inf")
            part = self.part_names[int(self.labels[int(d.argmin())])]
            return {**self._PART_WORDS, "eyes": "face"}.get(part, part)
        if self.name == "donut":
            return "icing" if float((p - self.center) @ self.up) > -0.1 * self.radius else "dough"
        height = float((p - self.center) @ self.up) / self.radius
        return "hair" if height > 0.6 else "face" if height > -0.5 else "chin"


def synthetic_subject(out: str, seed: int, n_cameras: int, size: int) -> Subject:
    """make_scene(seed) written as OUT/scenes/synthetic_<seed>/point_cloud.ply with its own cameras
    (make_cameras) as cameras_<n>_<size>.json; the subject is the figure."""
    from gs_regional.data.loaders import save_cameras_json
    from gs_regional.sim.scene import FRONT, make_cameras, make_scene
    from gs_regional.sim.splat_truth import object_frame

    folder = os.path.join(out, "scenes", f"synthetic_{seed}")
    os.makedirs(folder, exist_ok=True)
    ply = os.path.join(folder, "point_cloud.ply")
    model, labels, names = make_scene(seed)
    if not os.path.isfile(ply):
        model.save_ply(ply)
    cams = os.path.join(folder, f"cameras_{n_cameras}_{size}.json")
    if not os.path.isfile(cams):
        save_cameras_json(make_cameras(n_cameras, size, size, seed)[0], cams)
    center, radius = object_frame(model.select(labels >= names.index("body")))
    return Subject(f"synthetic:{seed}", ply, {"cameras": cams}, up=[0.0, 1.0, 0.0], front=list(FRONT),
                   center=center, radius=radius, labels=labels, part_names=names)


def donut_subject(n_cameras: int, size: int) -> Subject:
    from gs_regional.geometry.gaussian_model import GaussianModel
    from gs_regional.sim.splat_truth import object_frame

    center, radius = object_frame(GaussianModel.from_ply(DONUT))
    cams = {"n_cameras": n_cameras, "width": size, "height": size, "elevations": [10.0, 30.0]}
    return Subject("donut", DONUT, cams, up=[0.0, 0.0, 1.0], front=[0.0, 0.0, 1.0], center=center, radius=radius)


def fit_face(out: str) -> str:
    """The splat fitted to the face scene (FACE_FIT), cached in OUT/face_fit: reused when present
    with the same settings. Returns the PLY."""
    from gs_regional.launch import main

    folder = os.path.join(out, "face_fit")
    ply = os.path.join(folder, "reconstruct", "face", "save", "reconstructed.ply")
    stamp = os.path.join(folder, "settings.json")
    want = {"source": os.path.abspath(FACE), "overrides": FACE_FIT}
    if os.path.isfile(ply) and os.path.isfile(stamp):
        with open(stamp) as f:
            if json.load(f) == want:
                print(f"face: reusing the cached fit {ply} (delete {folder} to refit)", flush=True)
                return ply
    print(f"face: fitting a splat to {FACE} (configs/reconstruct.yaml {' '.join(FACE_FIT)}); "
          f"cached in {folder}", flush=True)
    t0 = time.perf_counter()
    argv = ["--config", os.path.join(ROOT, "configs", "reconstruct.yaml"), "--train", f"data.source={FACE}",
            f"exp_root_dir={folder}", "tag=face", "use_timestamp=false", "trainer.enable_progress_bar=false", *FACE_FIT]
    if main(argv, custom_dir=os.path.join(ROOT, "custom")) != 0:
        raise SystemExit("face: the fit failed")
    with open(stamp, "w") as f:
        json.dump(want, f)
    print(f"face: fitted in {time.perf_counter() - t0:.1f} s", flush=True)
    return ply


def face_subject(out: str, n_cameras: int, downscale: float) -> Subject:
    """The fitted face splat; up = the cameras' mean up, the subject = the head: centred behind the
    surface point the cameras look at (median of their centre pixels' rendered depth), radius 0.2x
    the cameras' mean distance to it; front = towards the mean camera. Objects are added on the
    face as the cameras see it (splat-truth's `up` = front): the fitted hair is too sparse."""
    import torch

    from gs_regional.data.loaders import load_cameras
    from gs_regional.geometry.gaussian_model import GaussianModel
    from gs_regional.registry import find

    ply = fit_face(out)
    model = GaussianModel.from_ply(ply).requires_grad_(False)
    cams = load_cameras(FACE)
    step = len(cams) / n_cameras
    cams = [cams[int(i * step)].scaled(1.0 / downscale) for i in range(n_cameras)]
    renderer = find("torch-rasterizer", kind="renderers")()
    points = []
    with torch.no_grad():
        for cam in cams:
            depth = renderer.render(model, cam)["depth"].reshape(cam.height, cam.width)
            v, u = cam.height // 2, cam.width // 2
            z = float(depth[v, u])
            p_cam = torch.tensor([(u + 0.5 - cam.cx) / cam.fx * z, (v + 0.5 - cam.cy) / cam.fy * z, z, 1.0], dtype=torch.float64)
            points.append((torch.linalg.inv(cam.world_to_camera.double()) @ p_cam)[:3].float())
    surface = torch.stack(points).median(0).values
    centers = torch.stack([c.center.float() for c in cams])
    up = -torch.stack([c.world_to_camera[1, :3].float() for c in cams]).mean(0)  # OpenCV: y points down
    up = up / up.norm()
    front = centers.mean(0) - surface
    front = front - (front @ up) * up
    front = front / front.norm()
    radius = 0.2 * float((centers - surface).norm(dim=-1).mean())
    center = surface - 0.5 * radius * front
    cam_data = {"cameras": FACE, "downscale": float(downscale), "max_cameras": n_cameras}
    return Subject("face", ply, cam_data, up=up.tolist(), front=front.tolist(), center=center, radius=radius,
                   add_on_front=True)


# ---------------------------------------------------------------------------------------- resolve
_SCALES = (1.0, 0.7, 1.3, 0.45, 0.2, 0.0)  # tried in turn when a drawn anchor misses the subject


def _anchor(subject, case, direction, width):
    """(through, landing point, scale): the case's offset on the subject's plane across
    `direction`, shrunk by _SCALES until a line along `direction` lands on the subject."""
    for scale in _SCALES:
        through = subject.in_plane(direction, [scale * x for x in case["offset"]])
        p = _landing(subject, through, direction, width)
        if p is not None:
            return through, p, scale
    raise ValueError(f"{case['id']}: no surface on the {subject.name} subject near {case['offset']}")


def _landing(subject: Subject, through, direction, width: float):
    """splat-truth's surface point along `direction` through `through` (whole splat), or None when
    it misses or lands off the subject (Subject.on_subject)."""
    from gs_regional.config import ConfigError
    from gs_regional.sim.splat_truth import surface_point

    try:
        p = surface_point(subject.model, through, direction, width)
    except ConfigError:
        return None
    return p if subject.on_subject(p) else None


def _truth_stats(data: Dict[str, object]) -> Tuple[dict, object]:
    """Build the case's truth as the run will (SplatTruthDataModule): (region and added counts,
    the region mask)."""
    from gs_regional.sim.splat_truth import SplatTruthDataModule

    dm = SplatTruthDataModule(data)
    dm.setup()
    gt = dm.scene.ground_truth
    region, added = int(gt.region.sum()), len(gt.edited) - len(gt.source)
    return {"region_gaussians": region, "true_added": added,
            "region_to_added": round(region / added, 2) if added else None}, gt.region


def _prompt(case: dict, part: str) -> str:
    c, kind = case["color_name"], case["kind"]
    if kind == "recolor_small":
        return f"paint {'an' if c[0] in 'aeiou' else 'a'} {c} patch on the {part}"
    if kind == "recolor_large":
        return f"make the {part} {c}" if case.get("select") != "top" else f"make the top of the donut {c}"
    return f"put a {'small' if kind == 'add_small' else 'big'} {c} ball on the {part}"


def resolve(case: dict, subject: Optional[Subject], s: dict) -> Tuple[str, List[str], dict]:
    """(config, overrides, facts) of a drawn case against its scene: anchors found on the subject,
    sizes in splat-truth's units, the truth's region and added counts."""
    if case["native"]:  # the synthetic scene's own edit (make_edit), rendered by synthetic-scene
        from gs_regional.sim.scene import make_edit

        seed = int(case["scene"].split(":")[1])
        edit = "recolor" if case["kind"] == "recolor_large" else "add"
        gt = make_edit(edit, seed=seed)
        added = len(gt.edited) - len(gt.source)
        facts = {"region_gaussians": int(gt.region.sum()), "true_added": added, "prompt": gt.prompt, "part": "head",
                 "region_to_added": round(int(gt.region.sum()) / added, 2) if added else None}
        overrides = [f"data.edit={edit}", f"data.seed={seed}", f"data.n_cameras={s['n_cameras']}",
                     f"data.width={s['size']}", f"data.height={s['size']}", f"system.prompt={gt.prompt}"]
        return "configs/demo.yaml", overrides, facts
    family = case["scene"].split(":")[0]
    up = subject.add_up if case["kind"].startswith("add") else subject.up
    data: Dict[str, object] = {"ply": subject.ply, "up": up.tolist(), "front": subject.front.tolist(),
                               "seed": case["run_seed"], "color": case["color"]}
    data.update(subject.cameras)
    facts: dict = {}
    if case["kind"].startswith("recolor"):
        data["edit"] = "recolor"
        data["select"] = case["select"]
        if case["select"] == "top":
            data["top_fraction"] = case["top_fraction"]
            part = "icing"
        else:
            width = max(case["ball_radius"] * subject.radius * 0.5, 0.02 * subject.radius)
            _, p, scale = _anchor(subject, case, subject.front, width)
            data["anchor"] = subject.to_object(p)
            data["ball_radius"] = round(case["ball_radius"] * subject.radius / subject.obj_radius, 5)
            facts.update(anchor_world=[round(float(v), 4) for v in p], anchor_scale=scale)
            part = subject.part_at(p)
    else:
        data["edit"] = "add"
        r = case["add_radius"] * subject.radius
        through, p, scale = _anchor(subject, case, subject.add_up, r)
        data.update(anchor=subject.to_object(through), add_radius=round(r / subject.obj_radius, 5),
                    add_count=case["add_count"], region_radius=case["region_radius"])
        facts.update(anchor_world=[round(float(v), 4) for v in p], anchor_scale=scale)
        part = subject.part_at(p)
    if family == "donut" and case["kind"] != "recolor_large":
        part = "icing" if part == "icing" else "donut"
    stats, region = _truth_stats(data)
    while case["kind"].startswith("add") and stats["region_to_added"] < MIN_REGION_TO_ADDED and data["region_radius"] < 64:
        # A ball barely touching a sparse surface selects a Gaussian or two, not the part it is
        # put on: widen the region until it holds about the object's own count.
        data["region_radius"] = round(data["region_radius"] * 1.25, 3)
        stats, region = _truth_stats(data)
    if case["kind"].startswith("recolor") and subject.labels is not None:
        part = subject.main_part(region) or part
    data["prompt"] = _prompt(case, part)
    facts.update(stats, part=part, prompt=data["prompt"])
    overrides = ["data_type=splat-truth"]
    for k, v in data.items():
        overrides.append(f"data.{k}={json.dumps(v) if isinstance(v, (list, str)) else v}")
    return "configs/donut_add.yaml", overrides, facts


# -------------------------------------------------------------------------------------------- run
# The figures a case with --repeats reports as the median over its runs (each run's own in `repeats`).
REPEAT_KEYS = ("gain", "psnr_region_vs_true_edit", "psnr_outside_vs_true_edit", "psnr_vs_true_edit",
               "psnr_unedited", "mask_iou", "mask_iou_seen", "gaussians_added", "source_deleted", "unet_evals",
               "seconds_total")
REPEAT_SEED_STEP = 1  # run j of a case uses its run seed + j (run 0 is the draw's own run)


def run_case(case: dict, subject: Optional[Subject], s: dict, runs_dir: str, repeats: int = 1) -> dict:
    """Resolve and run one case; its record (an `error` instead of metrics when it failed).

    With `repeats` > 1 the case runs that many times, the run seed shifted by REPEAT_SEED_STEP each
    time (the editor's draws, the views, the densification samples change; the scene and the truth
    do not): the record holds run 0's metrics with the REPEAT_KEYS replaced by their median over the
    runs, `stopped` set when any run stopped, and each run's REPEAT_KEYS in `repeats`. One run of a
    case differs from another seed's by several dB outside the footprint (docs/results.md), so a
    per-case difference between two codes means little below that spread."""
    rec = dict(case)
    try:
        config, overrides, facts = resolve(case, subject, s)
    except Exception as e:  # a draw that cannot be placed is reported, the suite goes on
        return {**rec, **{k: None for k in METRIC_KEYS}, "error": f"resolve: {e}"}
    tail = [f"tag={case['kind']}"] + s["budget"] + COMMON
    rec.update(facts, config=config, overrides=overrides + [f"seed={case['run_seed']}"] + tail)
    base = run_seed(rec)  # a `seed=` override of the whole suite replaces the case's own
    name = f"{case['id']}_{case['scene'].replace(':', '')}"
    t0 = time.perf_counter()
    runs = []
    for j in range(repeats):
        seed = base + j * REPEAT_SEED_STEP
        try:
            m = run(runs_dir, name + (f"_r{j}" if j else ""), config, *overrides, *tail, f"seed={seed}")
        except (SystemExit, Exception) as e:
            return {**rec, **{k: None for k in METRIC_KEYS}, "error": (str(e) or type(e).__name__) + (f" (run {j}, seed {seed})" if j else ""),
                    "wall_seconds": round(time.perf_counter() - t0, 2)}
        m["gain"] = gain(m)
        runs.append((seed, m))
    m = runs[0][1]
    rec.update({k: m.get(k) for k in METRIC_KEYS})
    rec["gain"] = m["gain"]
    rec["trial"] = m["trial"]
    if repeats > 1:
        rec["repeats"] = [{"run_seed": seed, "stopped": r.get("stopped"), "trial": r["trial"],
                           **{k: r.get(k) for k in REPEAT_KEYS}} for seed, r in runs]
        for k in REPEAT_KEYS:
            vals = [r.get(k) for _, r in runs]
            rec[k] = statistics.median(vals) if all(v is not None for v in vals) else None
        stops = [r["stopped"] for _, r in runs if r.get("stopped")]
        rec["stopped"] = f"{stops[0]} ({len(stops)} of {repeats} runs)" if stops else None
    rec["wall_seconds"] = round(time.perf_counter() - t0, 2)
    return rec


def run_seed(r: dict) -> int:
    """The seed a case's (first) run used: the last `seed=` of its overrides (the suite's own
    overrides come after the case's run seed), else its drawn run seed."""
    seeds = [o.split("=", 1)[1] for o in r.get("overrides") or [] if o.startswith("seed=")]
    return int(seeds[-1]) if seeds else int(r["run_seed"])


def spread(r: dict, key: str) -> Optional[Tuple[float, float]]:
    """(min, max) of `key` over a case's --repeats runs; None for a single run."""
    vals = [x.get(key) for x in r.get("repeats") or []]
    vals = [v for v in vals if v is not None]
    return (min(vals), max(vals)) if len(vals) > 1 else None


def gain(r: dict) -> Optional[float]:
    a, b = r.get("psnr_region_vs_true_edit"), r.get("psnr_region_source_vs_true_edit")
    return None if a is None or b is None else a - b


def subjects_for(cases: Sequence[dict], out: str, s: dict) -> Tuple[Dict[str, Subject], List[str]]:
    """The scenes the cases need, prepared (synthetic PLYs written, the face fitted); and the
    scenes left out with why."""
    subjects, missing = {}, []
    for scene in dict.fromkeys(c["scene"] for c in cases if not c["native"]):
        why = scene_missing(scene)
        if why:
            missing.append(why)
            continue
        if scene.startswith("synthetic"):
            subjects[scene] = synthetic_subject(out, int(scene.split(":")[1]), s["n_cameras"], s["size"])
        elif scene == "donut":
            subjects[scene] = donut_subject(s["n_cameras"], s["size"])
        else:
            try:
                subjects[scene] = face_subject(out, FACE_CAMERAS if s["n_cameras"] >= FACE_CAMERAS else s["n_cameras"],
                                               s["face_downscale"])
            except (SystemExit, Exception) as e:
                missing.append(f"face: no fitted splat ({e})")
    return subjects, missing


def resolve_only(seed: int, n_cases: int, quick: bool, out: str, size: Optional[int] = None) -> int:
    """Place every drawn case on its scene and print what would run."""
    s = settings(quick, size)
    cases = draw(seed, n_cases, quick)
    subjects, missing = subjects_for(cases, out, s)
    for why in missing:
        print(f"LEFT OUT: {why}")
    for case in cases:
        if not case["native"] and case["scene"] not in subjects:
            continue
        try:
            config, overrides, facts = resolve(case, subjects.get(case["scene"]), s)
            print(case["id"], case["kind"], case["scene"], json.dumps(facts))
        except Exception as e:
            print(case["id"], case["kind"], case["scene"], f"FAILED: {e}")
    return 0


def select_cases(cases: Sequence[dict], only: Sequence[str] = (), kinds: Sequence[str] = (), seed: int = 0) -> List[dict]:
    """The cases named in `only` (all when empty) of the `kinds` given ("recolor", "add"; all
    when empty), in the draw's order: a subset of a draw re-runs exactly as in the whole draw."""
    unknown = sorted(set(only) - {c["id"] for c in cases})
    if unknown:
        raise SystemExit(f"--only: no case {', '.join(unknown)} in draw {seed} (its cases: "
                         f"{cases[0]['id']}..{cases[-1]['id']})")
    return [c for c in cases if (not only or c["id"] in only) and (not kinds or c["kind"].split("_")[0] in kinds)]


def run_suite(seed: int, n_cases: int, quick: bool, out: str, overrides: Sequence[str] = (),
              only: Sequence[str] = (), kinds: Sequence[str] = (), size: Optional[int] = None,
              repeats: int = 1) -> dict:
    """Run the draw's cases (those named in `only`, of the `kinds` given, when given) and write
    the JSON after each."""
    s = settings(quick, size)
    s["budget"] = s["budget"] + list(overrides)  # every case's launch.py overrides
    cases = select_cases(draw(seed, n_cases, quick), only, kinds, seed)
    os.makedirs(out, exist_ok=True)
    t0 = time.perf_counter()
    subjects, missing = subjects_for(cases, out, s)
    if missing:
        print("\n" + "!" * 100)
        for why in missing:
            print(f"!! LEFT OUT: {why}: its cases do not run (set GS_REGIONAL_DATA to the folder holding "
                  "donut/ and face/)")
        print("!" * 100 + "\n", flush=True)
    payload = {"seed": seed, "quick": quick, "n_cases": n_cases, "only": list(only), "kinds": list(kinds), "repeats": repeats,
               "settings": {**s, "common": COMMON},
               "shared_data": SHARED_DATA, "left_out": missing, "records": []}
    runs_dir = os.path.join(out, "runs")
    todo = [c for c in cases if c["native"] or c["scene"] in subjects]
    skipped = [c for c in cases if c not in todo]
    for i, case in enumerate(todo):
        print(f"[{i + 1}/{len(todo)}] {case['id']} {case['kind']} on {case['scene']}"
              f"{' (its own edit)' if case['native'] else ''}", flush=True)
        rec = run_case(case, subjects.get(case["scene"]), s, runs_dir, repeats)
        rec.setdefault("gain", gain(rec))
        if rec.get("error"):
            print(f"error: {case['id']} failed: {rec['error']}", flush=True)
        else:
            over = f" (median of {repeats} runs)" if repeats > 1 else ""
            print(f"    {rec['prompt']!r}: gain {sweeps.fmt(rec['gain'])} dB, outside "
                  f"{sweeps.fmt(rec['psnr_outside_vs_true_edit'])} dB, IoU {sweeps.fmt(rec['mask_iou'])}{over}, "
                  f"{rec['wall_seconds']:.1f} s", flush=True)
        payload["records"].append(rec)
        sweeps.write_json(os.path.join(out, JSON_NAME), payload)
    payload["skipped_cases"] = [c["id"] for c in skipped]
    payload["wall_seconds"] = round(time.perf_counter() - t0, 1)
    sweeps.write_json(os.path.join(out, JSON_NAME), payload)
    return payload


# ---------------------------------------------------------------------------------------- targets
def _ratio_added(r: dict) -> Optional[float]:
    if r.get("gaussians_added") is None:
        return None
    if r["kind"].startswith("add"):
        return r["gaussians_added"] / max(r.get("true_added") or r.get("true_gaussians_added") or 1, 1)
    return r["gaussians_added"] / max(r.get("region_gaussians") or 1, 1)


MET_WORDS = {True: "ok", False: "FAIL", None: "n/a"}


def targets(records: Sequence[dict]) -> List[Tuple[str, Optional[bool], str, List[str]]]:
    """(target, met, the figure, failing case ids) of each target; met is None where no case is of
    the kind it is about."""
    ok = [r for r in records if not r.get("error")]
    failed_runs = [r["id"] for r in records if r.get("error")]

    def per_case(name, test):
        bad = [r["id"] for r in ok if not test(r)] + failed_runs
        return (name, not bad, f"{len(ok) - len(bad) + len(failed_runs)}/{len(records)} cases", bad)

    def median_of(name, values, limit):
        vals = [v for v in values if v is not None]
        if not vals:  # e.g. the recolours' target of a run of the additions alone
            return (name, None, "no such case", [])
        med = statistics.median(vals)
        return (name, med >= limit, f"median {sweeps.fmt(med)}", [])

    g = lambda r: r["gain"] if r.get("gain") is not None else float("-inf")  # noqa: E731
    recolours = [r for r in ok if r["kind"].startswith("recolor")]
    return [
        per_case("gain > 0 dB, every case", lambda r: g(r) > 0),
        median_of("median gain >= +6 dB", [r["gain"] for r in ok], 6.0),
        median_of("median gain of the recolours >= +10 dB", [r["gain"] for r in recolours], 10.0),
        per_case("outside-footprint PSNR >= 45 dB, every case", lambda r: (r["psnr_outside_vs_true_edit"] or 0) >= 45),
        median_of("median outside-footprint PSNR >= 50 dB", [r["psnr_outside_vs_true_edit"] for r in ok], 50.0),
        per_case("unedited PSNR >= 50 dB, every case", lambda r: (r["psnr_unedited"] or 0) >= 50),
        median_of("median mask IoU >= 0.9", [r["mask_iou"] for r in ok], 0.9),
        per_case("no stopped run", lambda r: not r.get("stopped")),
        per_case("no source Gaussian deleted", lambda r: r.get("source_deleted") == 0),
        per_case("Gaussians added <= 2x the truth's (a recolour: < 1 % of its region)",
                 lambda r: _ratio_added(r) is not None and (_ratio_added(r) <= 2.0 if r["kind"].startswith("add")
                                                            else _ratio_added(r) < 0.01)),
    ]


DISTRIBUTION = (
    ("gain (dB)", gain),
    ("footprint PSNR vs truth (dB)", lambda r: r.get("psnr_region_vs_true_edit")),
    ("footprint PSNR doing nothing (dB)", lambda r: r.get("psnr_region_source_vs_true_edit")),
    ("outside-footprint PSNR (dB)", lambda r: r.get("psnr_outside_vs_true_edit")),
    ("unedited PSNR (dB)", lambda r: r.get("psnr_unedited")),
    ("mask IoU", lambda r: r.get("mask_iou")),
    ("mask IoU (seen)", lambda r: r.get("mask_iou_seen")),
    ("mask IoU from exact 2D masks", lambda r: r.get("mask_iou_exact_masks")),
    ("added / truth's added (adds)", lambda r: _ratio_added(r) if r["kind"].startswith("add") else None),
    ("added / region (recolours)", lambda r: _ratio_added(r) if r["kind"].startswith("recolor") else None),
    ("region / true added (adds)", lambda r: r.get("region_to_added") if r["kind"].startswith("add") else None),
    ("source Gaussians deleted", lambda r: r.get("source_deleted")),
    ("UNet evaluations", lambda r: r.get("unet_evals")),
    ("seconds (all stages)", lambda r: r.get("seconds_total")),
    ("wall seconds", lambda r: r.get("wall_seconds")),
)


def seed_spreads(records: Sequence[dict]) -> Dict[str, List[float]]:
    """Per figure (gain, outside), each repeated case's max - min over its runs."""
    out = {}
    for name, key in (("gain", "gain"), ("outside", "psnr_outside_vs_true_edit")):
        v = [sp[1] - sp[0] for sp in (spread(r, key) for r in records if not r.get("error")) if sp]
        if v:
            out[name] = v
    return out


def print_report(payload: dict) -> List[Tuple[str, bool, str, List[str]]]:
    records = payload["records"]
    print(f"\ntruth suite: seed {payload['seed']} ({len(records)} cases"
          f"{', quick' if payload.get('quick') else ''}; rerun this draw with --seed {payload['seed']})")
    if payload.get("left_out"):
        print("LEFT OUT: " + "; ".join(payload["left_out"]))
    print("\n| case | kind | scene | prompt | gain dB | outside dB | unedited dB | IoU | added (truth) | s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in records:
        head = f"| {r['id']} | {r['kind']} | {r['scene']}{' (own edit)' if r.get('native') else ''} | {r.get('prompt', '')} |"
        if r.get("error"):
            print(f"{head} failed: {r['error']} | | | | | |")
            continue
        truth = r.get("true_added") if r["kind"].startswith("add") else f"region {r.get('region_gaussians')}"
        stop = f" STOPPED ({r['stopped']})" if r.get("stopped") else ""
        rng = lambda key: "" if spread(r, key) is None else " ({} to {})".format(*map(sweeps.fmt, spread(r, key)))  # noqa: E731
        print(f"{head} {sweeps.fmt(r['gain'])}{rng('gain')}{stop} | {sweeps.fmt(r['psnr_outside_vs_true_edit'])}"
              f"{rng('psnr_outside_vs_true_edit')} | "
              f"{sweeps.fmt(r['psnr_unedited'])} | {sweeps.fmt(r['mask_iou'])} | {r['gaussians_added']} ({truth}) | "
              f"{sweeps.fmt(r.get('wall_seconds'))} |")
    print("\n| metric | n | min | median | max |")
    print("| --- | --- | --- | --- | --- |")
    for name, f in DISTRIBUTION:
        vals = [f(r) for r in records if not r.get("error")]
        vals = [float(v) for v in vals if v is not None]
        if vals:
            print(f"| {name} | {len(vals)} | {min(vals):.3g} | {statistics.median(vals):.3g} | {max(vals):.3g} |")
    spreads = seed_spreads(records)
    if spreads:
        print(f"\n{payload.get('repeats')} runs a case (run seeds +0..+{payload.get('repeats', 1) - 1}): each figure above is "
              "their median, the range in brackets; " + "; ".join(
                  f"{name} spread (max - min) median {statistics.median(v):.2f}, max {max(v):.2f} dB"
                  for name, v in spreads.items()))
    result = targets(records)
    print("\ntargets" + (" (on each case's median run)" if spreads else "") + ":")
    for name, met, figure, bad in result:
        print(f"  [{MET_WORDS[met]}] {name}: {figure}" + (f"; missed by {', '.join(bad)}" if bad else ""))
    return result


def chart(payload: dict, path: str) -> None:
    """Per-case gain and outside-footprint PSNR, each sorted, coloured by kind, targets drawn."""
    plt = sweeps.pyplot()
    records = [r for r in payload["records"] if not r.get("error")]
    colors = dict(zip(KINDS, ("tab:orange", "tab:red", "tab:blue", "tab:purple")))
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8))
    panels = ((axes[0], "gain", "gain in the footprint vs doing nothing (dB)",
               ((0.0, "every case > 0"), (6.0, "median >= +6"), (10.0, "median of the recolours >= +10"))),
              (axes[1], "psnr_outside_vs_true_edit", "PSNR outside the footprint (dB)",
               ((45.0, "every case >= 45"), (50.0, "median >= 50"))))
    for ax, key, label, lines in panels:
        rows = sorted((r for r in records if r.get(key) is not None), key=lambda r: r[key])
        xs = range(len(rows))
        ax.bar(xs, [r[key] for r in rows], color=[colors[r["kind"]] for r in rows],
               edgecolor=["black" if r.get("stopped") else "none" for r in rows])
        ranges = [spread(r, key) for r in rows]
        if any(ranges):  # --repeats: each bar is a case's median run, the whisker its runs' range
            ax.errorbar(list(xs), [r[key] for r in rows], fmt="none", ecolor="black", elinewidth=0.8, capsize=2,
                        yerr=[[r[key] - (sp or (r[key],))[0] for r, sp in zip(rows, ranges)],
                              [(sp or (0, r[key]))[1] - r[key] for r, sp in zip(rows, ranges)]])
        stopped = [(x, r[key]) for x, r in zip(xs, rows) if r.get("stopped")]
        if stopped:  # a stop leaves the source: gain 0, invisible as a bar
            ax.scatter(*zip(*stopped), marker="x", color="black", zorder=4, s=40)
        ax.set_xticks(list(xs))
        ax.set_xticklabels([r["id"] for r in rows], rotation=90, fontsize=7)
        for y, text in lines:
            ax.axhline(y, color="black", ls="--" if "median" in text else "-", lw=1)
            ax.text(0, y, f" target: {text}", va="bottom", fontsize=8)
        if rows:
            med = statistics.median(r[key] for r in rows)
            ax.axhline(med, color="tab:green", lw=1.5, alpha=0.8)
            ax.text(len(rows) - 1, med, f"median {med:.1f}", va="bottom", ha="right", color="tab:green", fontsize=8)
        if key != "gain" and rows:  # PSNRs: from a little below the lowest target or value
            ax.set_ylim(min(40.0, rows[0][key] - 3), max(55.0, rows[-1][key] + 3))
        ax.set_ylabel(label)
        ax.set_xlabel("case (sorted)")
        ax.grid(axis="y", alpha=0.3)
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in colors.values()]
    handles.append(plt.Line2D([], [], marker="x", color="black", ls=""))
    axes[0].legend(handles, list(colors) + ["stopped (source kept)"], fontsize=8, loc="upper left",
                   bbox_to_anchor=(0, 0.9))
    runs = payload.get("repeats", 1)
    fig.suptitle(f"truth suite, seed {payload['seed']}: {len(records)} known edits (simulated editor and depth)"
                 + (f"; each bar the median of {runs} runs (run seeds), the whisker their range" if runs > 1 else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def load_payload(path: str, option: str = "--compare") -> dict:
    """A suite's JSON, given as the file or the folder holding it (`option` names it in the error)."""
    path = path if path.endswith(".json") else os.path.join(path, JSON_NAME)
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError) as e:
        raise SystemExit(f"{option}: cannot read the truth suite's JSON {path}: {e}")


def paired_differences(before: Dict[str, dict], after: Dict[str, dict], ids: Sequence[str], key: str) -> List[float]:
    """after - before of `key` over the runs of the same case at the same run seed (--repeats, or
    single runs: `run_seed`), leaving out runs that stopped at either."""
    out = []
    for i in ids:
        runs = lambda r: r.get("repeats") or [{**r, "run_seed": run_seed(r)}]  # noqa: E731
        x = {u.get("run_seed"): u for u in runs(before[i])}
        for v in runs(after[i]):
            u = x.get(v.get("run_seed"))
            if u is not None and not u.get("stopped") and not v.get("stopped") \
                    and u.get(key) is not None and v.get(key) is not None:
                out.append(v[key] - u[key])
    return out


def compare_report(before: dict, after: dict, names: Tuple[str, str] = ("before", "after")) -> List[dict]:
    """Print, for the cases both runs hold, the gain and the outside PSNR before -> after, and the
    two distributions; returns one row per shared case. A difference inside both runs' seed
    spreads (--repeats) is marked `~`: one seed's run says nothing about it."""
    if before.get("seed") != after.get("seed"):
        print(f"note: the runs are of different draws ({before.get('seed')} and {after.get('seed')}): "
              "cases of the same id are different edits")
    b = {r["id"]: r for r in before["records"] if not r.get("error")}
    a = {r["id"]: r for r in after["records"] if not r.get("error")}
    shared = [i for i in a if i in b]
    print(f"\n{names[0]} -> {names[1]}, {len(shared)} cases in both")
    print("| case | kind | gain dB | outside dB | UNet |")
    print("| --- | --- | --- | --- | --- |")
    rows = []
    for i in shared:
        x, y = b[i], a[i]
        row = {"id": i}
        cells = []
        for key in ("gain", "psnr_outside_vs_true_edit"):
            u, v = x.get(key), y.get(key)
            if u is None or v is None:
                cells.append(f"{sweeps.fmt(u)} -> {sweeps.fmt(v)}")
                continue
            su, sv = spread(x, key), spread(y, key)
            noise = su is not None and sv is not None and su[0] <= sv[1] and sv[0] <= su[1]
            row[key] = v - u
            cells.append(f"{u:.2f} -> {v:.2f} ({v - u:+.2f}{' ~' if noise else ''})")
        rows.append(row)
        print(f"| {i} | {y['kind']} | {cells[0]} | {cells[1]} | {x.get('unet_evals')} -> {y.get('unet_evals')} |")
    print("\n| figure | " + " | ".join(names) + " |")
    print("| --- | --- | --- |")
    for name, f in (("gain min / median (dB)", lambda rs: [r["gain"] for r in rs]),
                    ("outside min / median (dB)", lambda rs: [r["psnr_outside_vs_true_edit"] for r in rs]),
                    ("UNet evaluations min / median", lambda rs: [r["unet_evals"] for r in rs])):
        cols = []
        for rs in ([b[i] for i in shared], [a[i] for i in shared]):
            vals = [v for v in f(rs) if v is not None]
            cols.append(f"{min(vals):.2f} / {statistics.median(vals):.2f}" if vals else "-")
        print(f"| {name} | " + " | ".join(cols) + " |")
    for key, label in (("gain", "gain"), ("psnr_outside_vs_true_edit", "outside")):
        d = paired_differences(b, a, shared, key)
        if d:
            print(f"paired runs (the same run seed at both, neither stopped), {label}: {len(d)} runs, better in "
                  f"{sum(v > 0 for v in d)}, worse by more than 0.3 dB in {sum(v < -0.3 for v in d)}, median "
                  f"difference {statistics.median(d):+.2f} dB")
    for rs, name in (([b[i] for i in shared], names[0]), ([a[i] for i in shared], names[1])):
        met = targets(rs)
        print(f"{name}: " + "; ".join(f"{MET_WORDS[ok]} {t.split(',')[0]} ({fig})" for t, ok, fig, _ in met if ok is not None))
    if shared and not (before.get("repeats", 1) > 1 and after.get("repeats", 1) > 1):
        print("(single runs: a case's run at another seed differs by several dB outside the footprint; "
              "compare --repeats runs to tell a change from noise)")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=None, help="the draw's seed (default: a fresh one, printed)")
    ap.add_argument("--cases", type=int, default=None, help="cases to draw (default 24; 3 with --quick)")
    ap.add_argument("--quick", action="store_true", help="3 cases on synthetic scenes at tiny budgets (the test's mode)")
    ap.add_argument("--out", default=None,
                    help=f"folder for {JSON_NAME}, {PNG_NAME}, the scenes, the face fit and the runs (default "
                         "outputs/truth_suite; with --only or --kind outputs/truth_suite/part, so that a whole "
                         "draw's results are not overwritten)")
    ap.add_argument("--size", type=int, default=None, metavar="PX",
                    help="the views' side in pixels (default 64; 48 with --quick): the same draw at another resolution")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: the cores this process may use)")
    ap.add_argument("--replot", action="store_true", help=f"no runs: the chart and the distribution of OUT/{JSON_NAME}")
    ap.add_argument("--draw-only", action="store_true", help="print the drawn cases and stop")
    ap.add_argument("--resolve-only", action="store_true",
                    help="prepare the scenes and place every drawn case on its splat (anchors, truth counts), no runs")
    ap.add_argument("--strict", action="store_true", help="exit 1 when a target is missed")
    ap.add_argument("--repeats", type=int, default=1, metavar="R",
                    help="run each case R times with run seeds +0..+R-1 and report each case's median run and the "
                         "range (default 1; R times the time)")
    ap.add_argument("--compare", default=None, metavar="BEFORE",
                    help="after the run (or with --replot), print each case's gain and outside PSNR against "
                         "another run of the draw (its truth_suite.json or folder), e.g. the code before a change")
    # One value each, so that the overrides after them stay overrides.
    ap.add_argument("--only", default="", metavar="IDS", help="run only these cases of the draw, e.g. c03,c17")
    ap.add_argument("--kind", default=None, choices=["recolor", "add"],
                    help="run only the recolours or the additions of the draw")
    ap.add_argument("overrides", nargs="*", help="launch.py overrides (key=value) for every case, e.g. an ablation: "
                    "system.localize_with_truth=true")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats {args.repeats}: need at least 1 run a case")
    only, kinds = [i.strip() for i in args.only.split(",") if i.strip()], [args.kind] if args.kind else []
    if args.out is None:
        args.out = os.path.join(ROOT, "outputs", "truth_suite", *(["part"] if only or kinds else []))
    if args.replot:
        payload = load_payload(args.out, "--replot")
    else:
        seed = args.seed if args.seed is not None else random.SystemRandom().randrange(1_000_000)
        n = args.cases or (3 if args.quick else 24)
        print(f"truth suite seed: {seed} ({n} cases{', quick' if args.quick else ''}; "
              f"rerun this draw with --seed {seed})", flush=True)
        if args.draw_only:
            for c in draw(seed, n, args.quick):
                print(json.dumps(c))
            return 0
        import torch

        if args.resolve_only:
            return resolve_only(seed, n, args.quick, args.out, args.size)
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        torch.set_num_threads(max(1, min(args.threads or cores, cores)))
        payload = run_suite(seed, n, args.quick, args.out, args.overrides, only, kinds, args.size, args.repeats)
    chart(payload, os.path.join(args.out, PNG_NAME))
    result = print_report(payload)
    if args.compare:
        compare_report(load_payload(args.compare), payload, (args.compare, args.out))
    if "wall_seconds" in payload:
        print(f"\nwall time {payload['wall_seconds']:.0f} s; {os.path.join(args.out, JSON_NAME)}, "
              f"{os.path.join(args.out, PNG_NAME)}")
    return 1 if args.strict and any(met is False for _, met, _, _ in result) else 0


if __name__ == "__main__":
    sys.exit(main())
