"""The scenes of a truth suite (the synthetic figure, the donut, the fitted face) and each drawn
case placed on its scene: anchors found on the subject, sizes in splat-truth's units, the truth's
region and added counts."""
from __future__ import annotations

import json
import os
import time
from typing import Dict, List, Optional, Sequence, Tuple

from gs_regional.bench.launching import DONUT, ROOT
from gs_regional.bench.truth.cases import FACE, FACE_CAMERAS, FACE_FIT, MIN_REGION_TO_ADDED

def scene_missing(scene: str) -> Optional[str]:
    """None when the scene's data is here, else why its cases are left out."""
    if scene == "donut" and not os.path.isfile(DONUT):
        return f"donut: {DONUT} not found"
    if scene == "face" and not os.path.isfile(os.path.join(FACE, "transforms.json")):
        return f"face: {FACE}/transforms.json not found"
    return None


WALL_LATERAL = 2.5  # the face scene: parts this many head radii off its vertical axis are the wall (it stands 4-5 behind)


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
        # where whole-part cases save their part's mask (splat-truth's `region_file`); subjects_for
        # sets it under the suite's OUT
        self.parts_dir = os.path.join(ROOT, "outputs", "truth_suite", "scenes", name.replace(":", "_"), "parts")
        self._segments = None
        self._cameras = None

    def camera_list(self):
        """The cameras a case on this subject renders (splat-truth's, from `cameras`; computed once)."""
        if self._cameras is None:
            from gs_regional.sim.splat_truth import SplatTruthDataModule

            dm = SplatTruthDataModule({"ply": self.ply, **self.cameras})
            self._cameras = dm.cameras(self.obj_center, self.obj_radius, self.up)
        return self._cameras

    def segments(self):
        """segment_parts of the splat (computed once): (N,) segment per Gaussian, 0 the largest."""
        if self._segments is None:
            from gs_regional.sim.splat_truth import segment_parts

            self._segments = segment_parts(self.model)
        return self._segments

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
        # the face: the person within WALL_LATERAL radii of the head's vertical axis, the wall behind beyond
        d = (p - self.center) / self.radius
        height = float(d @ self.up)
        if float((d - height * self.up).norm()) > WALL_LATERAL:
            return "wall"
        return "hair" if height > 0.6 else "face" if height > -0.5 else "chin" if height > -1.3 else "sweater"


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


def _truth_stats(data: Dict[str, object], visibility=None) -> Tuple[dict, object]:
    """Build the case's truth as the run will (SplatTruthDataModule): (region and added counts,
    the region mask); with `visibility` (the subject's up) also how the case's cameras see the region
    (splat_truth.part_visibility: side_view_fraction, hidden_fraction, view_fraction, views_seeing)."""
    from gs_regional.sim.splat_truth import SplatTruthDataModule, part_visibility

    dm = SplatTruthDataModule(data)
    dm.setup()
    gt = dm.scene.ground_truth
    region, added = int(gt.region.sum()), len(gt.edited) - len(gt.source)
    stats = {"region_gaussians": region, "true_added": added,
             "region_to_added": round(region / added, 2) if added else None}
    if visibility is not None:
        stats["part_gaussians"] = region
        stats.update(part_visibility(gt.source, gt.region, dm.scene.cameras, visibility))
    return stats, gt.region


def _prompt(case: dict, part: str) -> str:
    c, kind = case["color_name"], case["kind"]
    if kind == "recolor_part":
        return f"make the {part} {c}"
    if kind == "add_part":
        return f"put a {'small' if case['add_radius'] < 0.12 else 'big'} {c} ball on the {part}"
    if kind == "recolor_small":
        return f"paint {'an' if c[0] in 'aeiou' else 'a'} {c} patch on the {part}"
    if kind == "recolor_large":
        return f"make the {part} {c}" if case.get("select") != "top" else f"make the top of the donut {c}"
    return f"put a {'small' if kind == 'add_small' else 'big'} {c} ball on the {part}"


MIN_PART = 30  # a segment of a real splat with fewer Gaussians is no part a case picks
MAX_PART_SHARE = 0.9  # nor one holding more than this share of the splat


MAX_HIDDEN = 0.9  # a real splat's segment more hidden than this (inside the object) is no part a case picks
# nor one with less than this share of its rendered weight where it is most of the pixel: a colour class
# threaded through another part's Gaussians (streaks of a wall's texture, a shade of skin) shows the views
# no region of its own; its exact 2D masks are near empty and the pixels an editor paints for it are mostly
# other Gaussians (the fitted face's segments: 0.01-0.72, the donut's 0.3-0.94)
MIN_SHOWN = 0.5


def part_region(case: dict, subject: Subject, accept=None):
    """(mask of the whole part, the word the prompt calls it, a key naming it, its visibility or
    None): a named part of the procedural scene (sim.scene.part_masks), or the segment of a real
    splat (segment_parts) whose size is nearest the case's `part_size` quantile of the log sizes
    of its segments (MIN_PART Gaussians up to MAX_PART_SHARE of the splat) among those the cameras
    see (hidden_fraction <= MAX_HIDDEN) as a region of their own (shown_fraction >= MIN_SHOWN) and
    `accept(mask)` takes."""
    import torch

    from gs_regional.sim.splat_truth import part_visibility

    if subject.labels is not None:
        from gs_regional.sim.scene import part_masks

        region = part_masks(int(subject.name.split(":")[1]))[case["part"]]
        return region, case["part"], case["part"], None
    seg = subject.segments()
    counts = torch.bincount(seg[seg >= 0])
    eligible = torch.nonzero((counts >= MIN_PART) & (counts <= MAX_PART_SHARE * len(seg))).flatten()
    if not len(eligible):
        raise ValueError(f"{subject.name}: no segment of {MIN_PART} or more Gaussians")
    sizes = counts[eligible].float().log()
    target = sizes.min() + case["part_size"] * (sizes.max() - sizes.min())
    cameras = subject.camera_list()[::3]  # a third of the views
    # Nearest the drawn size first, every eligible segment if need be: most of a fitted face's
    # segments can lie hidden inside its layers or threaded through other parts.
    for j in eligible[torch.argsort((sizes - target).abs(), stable=True)].tolist():
        region = seg == j
        seen = part_visibility(subject.model, region, cameras, subject.up)
        hidden, shown = seen["hidden_fraction"], seen["shown_fraction"]  # None: no camera sees it
        if hidden is None or hidden > MAX_HIDDEN or shown < MIN_SHOWN or (accept is not None and not accept(region)):
            continue
        return region, subject.part_at(subject.model.means[region].mean(0)), f"segment{j}", seen
    raise ValueError(f"{subject.name}: none of its {len(eligible)} segments of {MIN_PART} or more Gaussians is seen "
                     f"(hidden <= {MAX_HIDDEN}, shown >= {MIN_SHOWN}) and takes the case")


_PART_CANDIDATES = 64  # an addition's resting point is looked for under this many of the part's tops


def _part_anchor(subject: Subject, region, r: float):
    """(through, landing point, direction) of an object resting on the part: seen from `add_up`
    when it can, else from the side (the four directions across `add_up`: a body whose top the
    head covers gets the object on its flank), the sides facing the subject's front (the cameras)
    first: a ball on the figure's back, which no camera of the rig sees, was drawn before its
    front was tried. Per direction, under the part's Gaussians furthest along it (nearest the
    subject's axis first among equals), the first where the object touches the part first
    (`resting_contact`); the landing point is the Gaussian it touches."""
    import torch

    from gs_regional.config import ConfigError
    from gs_regional.sim.splat_truth import OPAQUE, _horizontal_basis, resting_contact

    means = subject.model.means
    rows = torch.nonzero(region & (subject.model.opacities > OPAQUE)).flatten()
    if not len(rows):
        rows = torch.nonzero(region).flatten()
    rel = means[rows] - subject.center
    up = subject.add_up
    e1, e2 = _horizontal_basis(up)
    sides = sorted((e1, -e1, e2, -e2), key=lambda side: -float(side @ subject.front))  # (stable: ties keep order)
    for direction in (up, *sides):
        height = rel @ direction
        lateral = (rel - height[:, None] * direction).norm(dim=-1)
        for i in rows[torch.argsort(-(height - 0.3 * lateral))[:_PART_CANDIDATES]].tolist():
            through = means[i]
            try:
                _, row = resting_contact(subject.model, through, direction, r)
            except ConfigError:
                continue
            if bool(region[row]):
                return through, means[row], direction
    raise ValueError(f"no point of the part is seen from above or from the side ({subject.name})")


def _resolve_part(case: dict, subject: Subject) -> Tuple[str, List[str], dict]:
    """A whole-part case: the part's mask saved for splat-truth (`region_file`); a recolour of
    the whole part, or an object resting on it with the part as its region."""
    import torch

    r = case.get("add_radius", 0.0) * subject.radius

    def restable(region) -> bool:  # an addition needs a point of the part to rest on
        try:
            _part_anchor(subject, region, r)
            return True
        except ValueError:
            return False

    region, part, key, _ = part_region(case, subject, restable if case["kind"] == "add_part" else None)
    os.makedirs(subject.parts_dir, exist_ok=True)
    path = os.path.join(subject.parts_dir, f"{key}.pt")
    torch.save(region.clone(), path)
    data: Dict[str, object] = {"ply": subject.ply, "front": subject.front.tolist(), "seed": case["run_seed"],
                               "color": case["color"], "region_file": path}
    data.update(subject.cameras)
    facts: dict = {"part_key": key}
    if case["kind"] == "recolor_part":
        data.update(edit="recolor", select="file", up=subject.up.tolist())
    else:
        through, p, direction = _part_anchor(subject, region, r)
        data.update(edit="add", up=subject.add_up.tolist(), anchor=subject.to_object(through),
                    add_radius=round(r / subject.obj_radius, 5), add_count=case["add_count"])
        if not torch.equal(direction, subject.add_up):  # on the part's side
            data["add_direction"] = [round(float(v), 6) for v in direction]
        facts["anchor_world"] = [round(float(v), 4) for v in p]
    data["prompt"] = _prompt(case, part)
    stats, _ = _truth_stats(data, visibility=subject.up)
    facts.update(stats, part=part, prompt=data["prompt"])
    overrides = ["data_type=splat-truth"]
    for k, v in data.items():
        overrides.append(f"data.{k}={json.dumps(v) if isinstance(v, (list, str)) else v}")
    return "configs/donut_add.yaml", overrides, facts


def resolve(case: dict, subject: Optional[Subject], s: dict) -> Tuple[str, List[str], dict]:
    """(config, overrides, facts) of a drawn case against its scene: anchors found on the subject,
    sizes in splat-truth's units, the truth's region and added counts."""
    if case.get("select") == "part":
        return _resolve_part(case, subject)
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
        from gs_regional.sim.splat_truth import resting_contact

        data["edit"] = "add"
        r = case["add_radius"] * subject.radius
        through, _, scale = _anchor(subject, case, subject.add_up, r)
        p = subject.model.means[resting_contact(subject.model, through, subject.add_up, r)[1]]  # what it rests on
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
    for scene, subject in subjects.items():
        subject.parts_dir = os.path.join(out, "scenes", scene.replace(":", "_"), "parts")
    return subjects, missing
