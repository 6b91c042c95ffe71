"""The cases of a truth suite: a pure function of (seed, number of cases, quick), no data read;
the budget every case runs at; what a case's record holds and the figures read from it."""
from __future__ import annotations

import colorsys
import math
import os
import random
from typing import List, Optional, Sequence, Tuple

from gs_regional.bench import sweeps
from gs_regional.bench.launching import SHARED_DATA

FACE = os.path.join(SHARED_DATA, "face")
JSON_NAME, PNG_NAME = "truth_suite.json", "truth_suite.png"

KINDS = ("recolor_small", "recolor_large", "add_small", "add_large")
# Whole-part cases (--parts K), drawn after the KINDS cases from a stream of their own.
PART_KINDS = ("recolor_part", "add_part")
# The procedural scene's named parts (gs_regional.sim.scene.PART_NAMES) a whole-part case picks
# from: every part is recoloured; objects rest on the parts with a top to rest on.
SYNTHETIC_PARTS = {"recolor_part": ("body", "head", "nose", "eyes", "arms", "ground", "backdrop"),
                   "add_part": ("body", "head", "nose", "arms", "ground")}
PART_SCENE_SHARES = (("synthetic", 0.5), ("donut", 0.25), ("face", 0.25))  # of the whole-part cases
N_SYNTHETIC_SEEDS = 6  # scene seeds of the synthetic scene drawn per run (>= 5)
NATIVE_SHARE = 0.25  # synthetic large recolours / larger additions drawn as the scene's own edits

MIN_REGION_TO_ADDED = 1.0  # an addition's region holds at least the object's own Gaussian count

# Kept in every record; a key metrics.json lacks (e.g. mask_iou_seen of an older run) is None.
# The override of a localize-only run (--localize-only): every run ends after localization.
LOCALIZE_ONLY = "system.stop_after=localize"

METRIC_KEYS = (
    "psnr_region_vs_true_edit", "psnr_region_source_vs_true_edit", "psnr_outside_vs_true_edit",
    "psnr_outside_source_vs_true_edit", "psnr_far_outside_vs_true_edit", "outside_error_near_footprint",
    "psnr_vs_true_edit", "psnr_source_vs_true_edit", "psnr_unedited", "ssim_region_vs_true_edit",
    "mask_iou", "mask_iou_seen", "mask_iou_exact_masks", "mask_precision", "mask_recall",
    "mask_precision_exact_masks", "mask_recall_exact_masks", "view_agreement",
    "edit_coverage", "edit_coverage_views", "footprint_fraction", "gaussians_before", "gaussians_added", "gaussians_pruned",
    "gaussians_after", "true_gaussians_added", "source_deleted", "unet_evals", "seconds", "seconds_total",
    "stopped", "warnings", "count_selected", "count_recolour_declined", "count_recolour_taken", "count_recolour_distinct",
    "count_unedited_cycles", "count_cycle_views_moved", "recolour_done", "recolour_left_unselected", "recolour_left_declined", "recolour_left_taken",
    "added_cover", "added_cover_outside", "refined_as",
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


def draw(seed: int, n_cases: int = 24, quick: bool = False, parts: int = 0) -> List[dict]:
    """The cases of one suite: pure function of (seed, n_cases, quick, parts), no data read. Each
    case is a dict: id, scene, kind, native (the synthetic scene's own edit), run seed, colour and
    the drawn sizes and anchors (in subject radii; resolved against the splat when it runs).
    `parts` whole-part cases follow the n_cases (`draw_parts`); the first n_cases do not depend
    on it."""
    cases = _draw_kinds(seed, n_cases, quick)
    return cases + draw_parts(seed, parts, quick, first=len(cases) + 1, synthetic_seeds=[
        int(c["scene"].split(":")[1]) for c in cases if c["scene"].startswith("synthetic:")])


def draw_parts(seed: int, n: int, quick: bool = False, first: int = 25, synthetic_seeds: Sequence[int] = ()) -> List[dict]:
    """`n` whole-part cases (ids c<first>...), from a random stream of their own (seeded by
    "<seed>:parts", so the suite's other cases stay as drawn): kinds alternating recolour / add
    from a random start; scenes synthetic (half; the draw's own scene seeds when given), donut and
    face (a quarter each; synthetic only when quick). A synthetic case names one of the
    procedural scene's parts (SYNTHETIC_PARTS); a donut or face case draws `part_size`, a
    quantile in [0, 1] of the log of the segments' sizes (resolved against `segment_parts` of the
    splat: from the smallest segment kept to the largest)."""
    if n <= 0:
        return []
    rng = random.Random(f"{int(seed)}:parts")
    seeds = list(dict.fromkeys(synthetic_seeds)) or rng.sample(range(100_000), N_SYNTHETIC_SEEDS)
    start = rng.randrange(len(PART_KINDS))
    cases = []
    for i in range(n):
        kind = PART_KINDS[(start + i) % len(PART_KINDS)]
        u = rng.random()
        family = "synthetic" if quick else next(f for f, acc in _cumulative(PART_SCENE_SHARES) if u < acc)
        scene = f"synthetic:{rng.choice(seeds)}" if family == "synthetic" else family
        rgb, colour = _colour(rng)
        case = {"id": f"c{first + i:02d}", "scene": scene, "kind": kind, "run_seed": rng.randrange(100_000),
                "color": rgb, "color_name": colour, "native": False, "select": "part"}
        if family == "synthetic":
            case["part"] = rng.choice(SYNTHETIC_PARTS[kind])
        else:
            case["part_size"] = round(rng.random(), 4)
        if kind == "add_part":
            case.update(add_radius=round(rng.uniform(0.06, 0.25), 4), add_count=rng.randint(100, 600))
        cases.append(case)
    return cases


def _cumulative(shares):
    acc = 0.0
    for name, share in shares:
        acc += share
        yield name, acc if name != shares[-1][0] else 1.0


def _draw_kinds(seed: int, n_cases: int, quick: bool) -> List[dict]:
    """The n_cases cases of KINDS (the suite's first cases)."""
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


# ---------------------------------------------------------------------------------------- records
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
