"""The studio's state, kept in the server (not in a page): the scene, the localization's evidence,
the selection being made, and the one job (a localization or an edit) that may run at a time, on a
background thread. The page (page.py) only shows this state and calls the methods below; a page
closed and opened again shows the same state, and a closed page stops nothing.

Every method a control calls returns None, or the one-line message the page shows instead of doing
it (an empty instruction, a second edit while one runs, a selection of nothing, ...)."""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

import numpy as np
import torch
from lightning.pytorch.callbacks import Callback

from gs_regional.api import EditResult, Localized, edit, localize
from gs_regional.data.cameras import Camera
from gs_regional.geometry.ply import PlyGaussians

log = logging.getLogger(__name__)

PICK_HEIGHT = 128  # pixels: the height of the render a click is looked up in
PICK_SHARE = 0.1  # a click takes the Gaussians giving at least this share of the pixel's largest weight
PICK_KNN = 16  # neighbourhood size when the localization kept none (its own k otherwise)


def overrides_dict(overrides: Sequence[str]) -> Dict[str, str]:
    """launch.py's `key=value` overrides as gs_regional.edit's dict (a word without '=' is a ValueError)."""
    bad = [o for o in overrides if "=" not in o]
    if bad:
        raise ValueError(f"unrecognized arguments: {' '.join(bad)} (overrides are key=value)")
    return dict(o.split("=", 1) for o in overrides)


def one_line(e: BaseException) -> str:
    """An exception as the one line the page shows (launch.py's own errors are one line already)."""
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


def client_camera(position: Any, wxyz: Any, fov: float, aspect: float, height: int = PICK_HEIGHT) -> Camera:
    """A pinhole Camera of a viser client's view (OpenCV axes, `fov` vertical, in radians) at
    `height` pixels, the width from the canvas' `aspect`."""
    import viser.transforms as vtf

    c2w = np.eye(4)
    c2w[:3, :3] = vtf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix()
    c2w[:3, 3] = np.asarray(position, dtype=np.float64)
    width = max(1, int(round(height * aspect)))
    f = 0.5 * height / np.tan(0.5 * fov)
    return Camera(world_to_camera=np.linalg.inv(c2w).astype(np.float32), fx=f, fy=f, cx=width / 2, cy=height / 2,
                  width=width, height=height, image_name="studio-client")


@dataclass
class Progress:
    """What the page shows of the job now: `kind` (select, edit), `text`, finished or not."""

    kind: str = ""
    text: str = ""
    running: bool = False
    started: float = 0.0
    step: int = 0
    total: int = 0
    stage: str = ""


class StudioCallback(Callback):
    """Follows a run for the studio: the stage and step as progress, the scene after each
    refinement cycle as a preview, and Stop (the trainer stops after the step it is in; the
    system then writes its outputs as at any end of training)."""

    def __init__(self, session: "StudioSession", kind: str) -> None:
        self.session, self.kind = session, kind
        self._previewed = -1

    def on_fit_start(self, trainer, pl_module) -> None:
        self.session._progress(self.kind, "rendering the source views")

    def on_train_start(self, trainer, pl_module) -> None:
        what = "localizing (relevance maps and the lift)" if self.kind == "select" else \
            "initializing (the first view's full edit and its depth)"
        self.session._progress(self.kind, what, total=int(trainer.max_steps or 0))

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if self.session.stop_requested.is_set():
            trainer.should_stop = True

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        step, total = int(trainer.global_step), int(trainer.max_steps or 0)
        stage = str(getattr(pl_module, "stage", ""))
        self.session._progress(self.kind, f"{stage} (step {step}/{total})", step=step, total=total, stage=stage)
        per_cycle = int(getattr(getattr(pl_module.cfg, "refine", None), "iterations_per_cycle", 0) or 0)
        cycle = step // per_cycle if per_cycle else 0
        if self.kind == "edit" and per_cycle and step % per_cycle == 0 and cycle != self._previewed:
            self._previewed = cycle
            self.session._preview(pl_module.geometry.to_ply_gaussians(), cycle, int(pl_module.cfg.refine.cycles))
        if self.session.stop_requested.is_set():
            trainer.should_stop = True

    def on_train_end(self, trainer, pl_module) -> None:
        self.session._progress(self.kind, "writing the outputs")


@dataclass
class StudioSession:
    """One scene (a config and its overrides, as for an edit) and what the studio did with it."""

    config: Path
    overrides: Dict[str, str] = field(default_factory=dict)
    custom_dir: Any = None
    cfg: Any = None
    source: Optional[PlyGaussians] = None
    source_label: str = ""
    cameras: List[Camera] = field(default_factory=list)
    test_indices: List[int] = field(default_factory=list)
    load_error: Optional[str] = None
    prompt: str = ""  # the config's instruction, offered on the page
    out: Path = Path("outputs")
    gpu: Optional[str] = None  # launch.py's --gpu for the runs (and the evidence on that device)

    def __post_init__(self) -> None:
        self.lock = threading.RLock()
        self.progress = Progress()
        self.message = ""  # the last refusal or problem
        self.localized: Optional[Localized] = None
        self.threshold: Optional[float] = None
        self.lifted: Optional[torch.Tensor] = None  # the selection at the threshold
        self.added: Optional[torch.Tensor] = None  # picked on the scene: always in / never in the selection
        self.removed: Optional[torch.Tensor] = None
        self.result: Optional[EditResult] = None
        self.edit_trial: Optional[Path] = None  # the edit's trial dir, once written
        self.preview: Optional[PlyGaussians] = None  # the scene after the last finished cycle
        self.unet_evals = 0  # over the runs this session started
        self.timings: Dict[str, float] = {}
        self.stop_requested = threading.Event()
        self._job: Optional[threading.Thread] = None
        self._renderer = None
        self._neighbourhood: Optional[torch.Tensor] = None
        self.listeners: List[Callable[[str], None]] = []  # the page: called with what changed

    # ----- the scene ------------------------------------------------------------------------
    @classmethod
    def open(cls, config: Any, overrides: Sequence[str] = (), custom_dir: Any = None,
             gpu: Optional[str] = None) -> "StudioSession":
        """Read the config (a mistake in it raises its one-line ConfigError) and its scene (a scene
        that fails to load is kept as `load_error`, for the page to say)."""
        from gs_regional.config import load_config
        from gs_regional.launch.plugins import default_custom_dir, load_plugins
        from gs_regional.launch.sections import section_configs
        from gs_regional.launch.view import source_scene
        from gs_regional.registry import load_builtins

        s = cls(config=Path(config), overrides=overrides_dict(overrides), custom_dir=custom_dir, gpu=gpu)
        load_builtins()
        load_plugins(custom_dir or default_custom_dir())
        s.cfg = load_config(str(config), [f"{k}={v}" for k, v in s.overrides.items()], section_configs=section_configs)
        s.out = Path(s.cfg.exp_root_dir).resolve()
        s.prompt = str(s.cfg.system.get("prompt") or "")
        try:
            s.source, s.source_label, scene = source_scene(s.cfg, str(config))
            s.cameras, s.test_indices = list(scene.cameras), list(scene.test_indices)
        except Exception as e:  # the page says it; the server stays up
            s.load_error = f"the scene could not be loaded: {one_line(e)}"
            log.warning("studio: %s", s.load_error)
        return s

    def shown_path(self, trial: Path) -> str:
        """A trial dir as the page names it: under the exp_root_dir."""
        try:
            return str(Path(trial).relative_to(self.out))
        except ValueError:
            return str(trial)

    @property
    def n(self) -> int:
        return 0 if self.source is None else self.source.num_gaussians

    # ----- jobs -----------------------------------------------------------------------------
    @property
    def busy(self) -> bool:
        return self._job is not None and self._job.is_alive()

    def wait(self, timeout: Optional[float] = None) -> bool:
        """Wait for the running job; True when none runs any more."""
        job = self._job
        if job is not None:
            job.join(timeout)
        return not self.busy

    def _notify(self, what: str) -> None:
        for listener in list(self.listeners):
            try:
                listener(what)
            except Exception:  # a page that went away must not stop a run
                log.exception("studio: a page update failed")

    def _say(self, message: str) -> str:
        self.message = message
        self._notify("message")
        return message

    def _progress(self, kind: str, text: str, **kw: Any) -> None:
        with self.lock:
            p = self.progress
            p.kind, p.text, p.running = kind, text, True
            for k, v in kw.items():
                setattr(p, k, v)
        self._notify("progress")

    def _preview(self, scene: PlyGaussians, cycle: int, cycles: int) -> None:
        self.preview = scene
        self._notify("preview")

    def _refuse_common(self, instruction: str, what: str) -> Optional[str]:
        if self.load_error:
            return self._say(f"{what}: {self.load_error}")
        if not instruction.strip():
            return self._say(f"{what}: type an instruction first (what to change, e.g. \"give him a mustache\")")
        if self.busy:
            kind = "an edit" if self.progress.kind == "edit" else "a localization"
            return self._say(f"{what} refused: {kind} is running ({self.progress.text}); one job at a time: "
                             "wait for it or press Stop")
        return None

    def _start(self, kind: str, work: Callable[[], None]) -> None:
        self.stop_requested.clear()
        self.progress = Progress(kind=kind, text="starting", running=True, started=time.perf_counter())
        self.message = ""
        self._notify("message")

        def run() -> None:
            try:
                work()
            except Exception as e:
                log.warning("studio: %s failed: %s", kind, one_line(e), exc_info=log.isEnabledFor(logging.DEBUG))
                self.progress.text = f"{'Select region' if kind == 'select' else 'Edit'} failed"
                self._say(f"{'Select region' if kind == 'select' else 'Edit'} failed: {one_line(e)}")
            finally:
                self.progress.running = False
                self._notify("progress")

        self._job = threading.Thread(target=run, name=f"studio-{kind}", daemon=True)
        self._job.start()
        self._notify("progress")

    # ----- Select region --------------------------------------------------------------------
    def select_region(self, instruction: str) -> Optional[str]:
        """Localize `instruction` on a background thread (gs_regional.localize: a trial of its
        own); then the selection is the lift's at its threshold."""
        with self.lock:
            refused = self._refuse_common(instruction, "Select region")
            if refused:
                return refused
            # Its own trial (<tag>-select), beside the edits' (the config's tag).
            tag = {"tag": f"{self.cfg.get('tag') or 'studio'}-select"} if "tag" not in self.overrides else {}
            overrides = {**self.overrides, **tag, "system.prompt": instruction.strip()}

            def work() -> None:
                t0 = time.perf_counter()
                loc = localize(config=self.config, out=self.out, overrides=overrides, gpu=self.gpu,
                               callbacks=[StudioCallback(self, "select")])
                self.unet_evals += int(loc.metrics.get("unet_evals", 0))
                with self.lock:
                    self.localized, self.threshold = loc, loc.threshold
                    self.lifted = loc.selection.clone()
                    self.added = torch.zeros_like(loc.selection)
                    self.removed = torch.zeros_like(loc.selection)
                    self._neighbourhood = loc.neighbourhood
                    self.result = self.preview = self.edit_trial = None
                self.timings["select_seconds"] = time.perf_counter() - t0
                count = self.count
                self.progress.text = (f"Selected {count:,} of {self.n:,} Gaussians in "
                                      f"{self.timings['select_seconds']:.1f} s (trial {self.shown_path(loc.trial)})")
                if count == 0:
                    self._say(f"Nothing was selected for \"{instruction.strip()}\" at threshold "
                              f"{loc.threshold}: lower the Threshold, or change the instruction")
                self._notify("selection")

            self._start("select", work)
        return None

    @property
    def selection(self) -> Optional[torch.Tensor]:
        """(N,) bool over the source Gaussians: the lift at the threshold, with what was added on
        the scene and without what was removed."""
        if self.lifted is None:
            return None
        return (self.lifted | self.added) & ~self.removed

    @property
    def count(self) -> int:
        sel = self.selection
        return 0 if sel is None else int(sel.sum())

    def set_threshold(self, threshold: float) -> Optional[str]:
        """Re-lift from the saved evidence (Localized.select: each Gaussian's lift score against
        `threshold`), no editor call."""
        with self.lock:
            if self.localized is None:
                return self._say("Threshold: press Select region first (the threshold re-lifts its evidence)")
            if self.localized.scores is None:
                return self._say("Threshold: this selection was given, not lifted: there are no scores to threshold")
            t0 = time.perf_counter()
            self.threshold = float(threshold)
            self.lifted = self.localized.select(self.threshold)
            self.timings["threshold_seconds"] = time.perf_counter() - t0
        self._notify("selection")
        return None

    # ----- Add to / Remove from selection -----------------------------------------------------
    def neighbourhood(self) -> torch.Tensor:
        """(N, k) rows: the localization's neighbourhoods (its kNN pooling), else found once here."""
        if self._neighbourhood is None:
            from gs_regional.stages.localize import neighbourhoods

            self._neighbourhood = neighbourhoods(self.localized.source.means.detach(), PICK_KNN)
        return self._neighbourhood

    def renderer(self):
        if self._renderer is None:
            from gs_regional.renderers.select import make_renderer

            self._renderer = make_renderer(self.cfg.system.get("renderer_type", "auto"),
                                           self.cfg.system.get("renderer") or {}, self.localized.source.means.device)
        return self._renderer

    def picked(self, camera: Camera, x: float, y: float, steps: int = 1) -> torch.Tensor:
        """(N,) bool: the Gaussians the pixel at (`x`, `y`) (0..1, from the upper left) of
        `camera`'s view takes its colour from (those giving at least PICK_SHARE of its largest
        weight), grown `steps` times over the neighbourhood rows."""
        model = self.localized.source
        cam = camera.to(model.means.device)
        col = min(max(int(x * cam.width), 0), cam.width - 1)
        row = min(max(int(y * cam.height), 0), cam.height - 1)
        onehot = torch.zeros(cam.height, cam.width, device=model.means.device)
        onehot[row, col] = 1.0
        weights = self.renderer().pixel_weights(model, cam).gather(onehot)
        top = float(weights.max()) if weights.numel() else 0.0
        hit = weights >= PICK_SHARE * top if top > 1e-6 else torch.zeros_like(weights, dtype=torch.bool)
        rows = self.neighbourhood()
        for _ in range(max(int(steps), 0)):
            if not bool(hit.any()):
                break
            grown = torch.zeros_like(hit)
            grown[rows[hit].reshape(-1)] = True
            hit = hit | grown
        return hit

    def pick(self, mode: str, camera: Camera, x: float, y: float, steps: int = 1) -> Optional[str]:
        """`mode` "add" or "remove": the part under the pointer joins or leaves the selection."""
        with self.lock:
            if self.localized is None:
                return self._say("Press Select region first: a click adds to or removes from its selection")
            hit = self.picked(camera, x, y, steps)
            if not bool(hit.any()):
                return self._say("That click hit no Gaussian: click on the scene itself")
            if mode == "add":
                self.added |= hit
                self.removed &= ~hit
            else:
                self.removed |= hit
                self.added &= ~hit
            self.message = f"{'Added' if mode == 'add' else 'Removed'} {int(hit.sum()):,} Gaussians"
        self._notify("selection")
        self._notify("message")
        return None

    # ----- Edit and Stop ----------------------------------------------------------------------
    def start_edit(self, instruction: str) -> Optional[str]:
        """gs_regional.edit of the selection on a background thread: a normal trial dir whose
        config names the selection file (so `--view`, `--export` and `resume=` work on it)."""
        with self.lock:
            refused = self._refuse_common(instruction, "Edit")
            if refused:
                return refused
            selection = self.selection
            if selection is None:
                return self._say("Edit: press Select region first (or the edit has no region)")
            if not bool(selection.any()):
                return self._say("Edit: the selection is empty: lower the Threshold or add to it on the scene")
            selection = selection.cpu().numpy().copy()
            overrides = {**self.overrides, "system.prompt": instruction.strip()}
            self.result, self.preview, self.edit_trial = None, None, None

            def work() -> None:
                t0 = time.perf_counter()
                result = edit(config=self.config, selection=selection, out=self.out, overrides=overrides, gpu=self.gpu,
                              callbacks=[StudioCallback(self, "edit")])
                self.unet_evals += int(result.metrics.get("unet_evals", 0))
                self.result, self.edit_trial = result, result.trial
                self.timings["edit_seconds"] = time.perf_counter() - t0
                stopped = self.stop_requested.is_set() and self.progress.step < self.progress.total
                self.progress.text = (f"{'Stopped at step %d/%d' % (self.progress.step, self.progress.total) if stopped else 'Done'}"
                                      f" in {self.timings['edit_seconds']:.1f} s: {result.model.num_gaussians:,} "
                                      f"Gaussians; trial {self.shown_path(result.trial)}")
                self._notify("result")

            self._start("edit", work)
        return None

    def stop(self) -> Optional[str]:
        if not (self.busy and self.progress.kind == "edit"):
            return self._say("Stop: no edit is running")
        self.stop_requested.set()
        self._progress("edit", f"stopping after the current step ({self.progress.text})")
        return None

    def download(self, suffix: str) -> Path:
        """The edited scene's file `edited<suffix>` (.ply, .splat, .compressed.ply); FileNotFoundError
        says what is missing."""
        if self.edit_trial is None:
            raise FileNotFoundError("no edit yet: press Edit first")
        path = self.edit_trial / "save" / f"edited{suffix}"
        if not path.is_file():
            raise FileNotFoundError(f"{path} was not written (system.export turned that format off?)")
        return path
