"""The studio's page (viser): the controls of docs/studio.md over a StudioSession. Every control
and scene node belongs to the server, so every open page (and one opened later) shows the same
state; the work runs on the session's threads, never in a page's callback."""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Optional

import numpy as np

from gs_regional.launch.view import (
    DEFAULT_MAX_GAUSSIANS, Splats, add_frustums, metrics_markdown, set_initial_view, subsample_rows, tinted, to_splats,
)
from gs_regional.studio.session import StudioSession, client_camera, one_line

log = logging.getLogger(__name__)

DEFAULT_PORT = 8080
DOWNLOADS = (".ply", ".splat", ".compressed.ply")
RELEVANCE_COLUMNS = 4  # relevance maps per row in the panel
RELEVANCE_MIN_HEIGHT = 96  # pixels: smaller views are enlarged to this


def relevance_grid(trial: Path, columns: int = RELEVANCE_COLUMNS) -> Optional[np.ndarray]:
    """The views' relevance masks over their renders (the run's save/localize/mask2d_*.png) as one
    image, `columns` to a row; None when the run wrote none."""
    import imageio.v3 as iio

    from gs_regional.utils.visualize import make_grid

    paths = sorted((trial / "save" / "localize").glob("mask2d_*.png"))
    if not paths:
        return None
    images = [iio.imread(p)[..., :3] for p in paths]
    scale = max(1, RELEVANCE_MIN_HEIGHT // max(images[0].shape[0], 1))  # small views shown larger, pixel for pixel
    images = [np.repeat(np.repeat(im, scale, 0), scale, 1) for im in images]
    return make_grid([images[i:i + columns] for i in range(0, len(images), columns)], margin=2)


@dataclass
class Studio:
    """A running studio; `stop()` ends the server (a running job ends with the process)."""

    server: Any
    url: str
    session: StudioSession
    page: "Page"

    def stop(self) -> None:
        self.page.close()
        self.server.stop()


class Page:
    """The controls and scene nodes, and how each follows the session."""

    def __init__(self, server: Any, session: StudioSession, max_gaussians: int) -> None:
        self.server, self.session, self.cap = server, session, max_gaussians
        s, gui = session, server.gui
        self.rows: Optional[np.ndarray] = None  # the source rows shown (None: all)
        self.splats: Dict[str, Splats] = {}
        self.nodes: Dict[str, Any] = {}
        self.scene_shown = "Before"
        self.pick_mode: Optional[str] = None
        self._relevance_of: Optional[Path] = None  # the localization whose relevance maps are shown
        self._clicked: Optional[float] = None  # when Select region was pressed (for shown_times)
        self.shown_times: Dict[str, float] = {}  # seconds from a control to its highlight on the page

        gui.add_markdown("**gs_regional studio**" + (f": `{s.source_label}`" if s.source_label else ""))
        self.instruction = gui.add_text("Instruction", initial_value=s.prompt, hint="what to change, e.g. give him a mustache")
        self.select_button = gui.add_button("Select region", hint="localize the instruction (no edit yet)")
        self.status = gui.add_markdown(self._status_text())
        self.message = gui.add_markdown("")
        self.threshold = gui.add_slider("Threshold", min=0.0, max=1.0, step=0.01, initial_value=0.5, disabled=True,
                                        hint="re-lift the selection from the localization's evidence (no editor call)")
        self.count = gui.add_markdown("**Selected:** nothing yet")
        self.add_button = gui.add_button("Add to selection", disabled=True, hint="then click on the scene")
        self.remove_button = gui.add_button("Remove from selection", disabled=True, hint="then click on the scene")
        self.pick_off = gui.add_button("Stop picking", disabled=True)
        self.pick_note = gui.add_markdown("")
        self.brush = gui.add_slider("Brush (neighbour steps)", min=0, max=6, step=1, initial_value=1,
                                    hint="how far a click grows over the neighbouring Gaussians")
        self.highlight = gui.add_checkbox("Highlight selection", initial_value=True)
        self.relevance = gui.add_image(np.full((8, 8, 3), 255, np.uint8), label="Relevance maps", visible=False)
        self.edit_button = gui.add_button("Edit", disabled=True, hint="edit the selected region")
        self.stop_button = gui.add_button("Stop", disabled=True, hint="end the edit after its current step; its outputs are written")
        self.before_after = gui.add_button_group("Before / after", ("Before", "After"))
        self.showing = gui.add_markdown("Showing: **before**")
        self.metrics = gui.add_markdown("")
        self.downloads = {suffix: gui.add_button(f"Download {suffix}", disabled=True) for suffix in DOWNLOADS}
        self.show_cameras = gui.add_checkbox("Cameras", initial_value=True)

        self.frustums = []
        if s.source is not None:
            self.rows = subsample_rows(s.n, max_gaussians)
            source = self.splats["source"] = to_splats(s.source, None, max_gaussians)
            set_initial_view(server, s.cameras, source.centers)
            self.nodes["source"] = server.scene.add_gaussian_splats(
                "/source", centers=source.centers, covariances=source.covariances, rgbs=source.rgbs,
                opacities=source.opacities)
            self.frustums = add_frustums(server, s.cameras, set(s.test_indices))
        else:
            self.select_button.disabled = True
        if s.load_error:
            self.message.content = f"**Problem:** {s.load_error}"
        self._bind()
        s.listeners.append(self.on_session)
        server.scene.on_click()(self._on_click)
        self.closed = threading.Event()
        threading.Thread(target=self._tick, name="studio-clock", daemon=True).start()

    def _tick(self) -> None:
        """The running job's seconds on the page, once a second."""
        while not self.closed.wait(1.0):
            if self.session.progress.running:
                self.status.content = self._status_text()

    def close(self) -> None:
        self.closed.set()
        if self.on_session in self.session.listeners:
            self.session.listeners.remove(self.on_session)

    # ----- the controls -----------------------------------------------------------------------
    def _safe(self, what: str, action: Callable[[Any], None]) -> Callable[[Any], None]:
        """`action` as a control's callback: an unexpected failure is a line on the page (and the
        log), never a dead control."""

        def run(event: Any) -> None:
            try:
                action(event)
            except Exception as e:
                log.warning("studio: %s failed", what, exc_info=True)
                self.session._say(f"{what} failed: {one_line(e)}")

        return run

    def _bind(self) -> None:
        s = self.session

        def select(event) -> None:
            self._clicked = time.perf_counter()
            s.select_region(self.instruction.value)

        def threshold(event) -> None:
            if s.localized is None or s.threshold is not None and abs(s.threshold - self.threshold.value) < 1e-9:
                return
            t0 = time.perf_counter()
            if s.set_threshold(self.threshold.value) is None:
                self.shown_times["threshold_seconds"] = time.perf_counter() - t0

        def show_cameras(event) -> None:
            for f in self.frustums:
                f.visible = self.show_cameras.value

        self.select_button.on_click(self._safe("Select region", select))
        self.threshold.on_update(self._safe("Threshold", threshold))
        self.add_button.on_click(self._safe("Add to selection", lambda event: self._set_pick("add")))
        self.remove_button.on_click(self._safe("Remove from selection", lambda event: self._set_pick("remove")))
        self.pick_off.on_click(self._safe("Stop picking", lambda event: self._set_pick(None)))
        self.highlight.on_update(self._safe("Highlight selection", lambda event: self._show_selection()))
        self.edit_button.on_click(self._safe("Edit", lambda event: s.start_edit(self.instruction.value)))
        self.stop_button.on_click(self._safe("Stop", lambda event: s.stop()))
        self.before_after.on_click(self._safe("Before / after", lambda event: self._show_scene(self.before_after.value)))
        self.show_cameras.on_update(self._safe("Cameras", show_cameras))
        self._on_click = self._safe("A click on the scene", self._on_click)
        for suffix, button in self.downloads.items():
            button.on_click(self._safe(f"Download {suffix}", lambda event, suffix=suffix: self._download(event, suffix)))

    def _set_pick(self, mode: Optional[str]) -> None:
        self.pick_mode = mode
        self.pick_off.disabled = mode is None
        self.pick_note.content = "" if mode is None else (
            f"Click on the scene to **{'add to' if mode == 'add' else 'remove from'}** the selection "
            "(Stop picking to turn the view freely again)")

    def _on_click(self, event) -> None:
        if self.pick_mode is None or self.session.localized is None:
            return
        cam = event.client.camera
        camera = client_camera(cam.position, cam.wxyz, cam.fov, cam.aspect)
        x, y = event.screen_pos
        self.session.pick(self.pick_mode, camera, float(x), float(y), int(self.brush.value))

    def _download(self, event, suffix: str) -> None:
        try:
            path = self.session.download(suffix)
        except FileNotFoundError as e:
            self.session._say(f"Download: {e}")
            return
        if event.client is not None:
            event.client.send_file_download(path.name, path.read_bytes(), save_immediately=True)

    # ----- following the session --------------------------------------------------------------
    def on_session(self, what: str) -> None:
        s = self.session
        if what in ("progress", "result", "selection"):
            self.status.content = self._status_text()
        if what == "message":
            self.message.content = f"**Note:** {s.message}" if s.message else ""
        busy = s.progress.running  # (its thread may still be ending)
        editing = busy and s.progress.kind == "edit"
        self.select_button.disabled = s.source is None
        self.stop_button.disabled = not editing
        has_selection = s.localized is not None
        self.threshold.disabled = not has_selection or s.localized.scores is None
        self.add_button.disabled = self.remove_button.disabled = not has_selection
        self.edit_button.disabled = not has_selection
        if what == "selection":
            if s.result is None and s.preview is None:  # a new localization: no edit of it yet
                for button in self.downloads.values():
                    button.disabled = True
                if "edited" in self.nodes:
                    self.nodes.pop("edited").remove()
                    self.metrics.content = ""
                    self._show_scene("Before")
            if s.threshold is not None and abs(self.threshold.value - s.threshold) > 1e-9:
                self.threshold.value = s.threshold
            if s.localized is not None and self._relevance_of != s.localized.trial:  # a new localization
                self._relevance_of = s.localized.trial
                grid = relevance_grid(s.localized.trial)
                if grid is not None:
                    self.relevance.image = grid
                self.relevance.visible = grid is not None
            self._show_selection()
            if self._clicked is not None:
                self.shown_times["select_seconds"] = time.perf_counter() - self._clicked
                self._clicked = None
        if what == "preview" and s.preview is not None:
            self._set_edited(s.preview)
            self._show_scene("After")
        if what == "result" and s.result is not None:
            self._set_edited(s.result.model.to_ply_gaussians())
            self.metrics.content = metrics_markdown(s.result.metrics, s.result.metrics.get("prompt", ""))
            for button in self.downloads.values():
                button.disabled = False
            self._show_scene("After")
        if what == "progress" and not busy:
            self.status.content = self._status_text()

    def _status_text(self) -> str:
        s, p = self.session, self.session.progress
        if s.source is None:
            return "**Status:** no scene"
        if not p.kind:
            return f"**Status:** ready: {s.n:,} Gaussians; type an instruction and press Select region"
        what = "Select region" if p.kind == "select" else "Edit"
        if p.running:
            return f"**Status:** {what}: {p.text} ({time.perf_counter() - p.started:.0f} s)"
        return f"**Status:** {what}: {p.text}"

    def _show_selection(self) -> None:
        s = self.session
        sel = s.selection
        if sel is None or "source" not in self.nodes:
            return
        mask = sel.cpu().numpy()
        shown = mask if self.rows is None else mask[self.rows]
        src = self.splats["source"]
        self.nodes["source"].rgbs = tinted(src.rgbs, shown if self.highlight.value else None)
        extra = []
        if s.added is not None and bool(s.added.any()):
            extra.append(f"{int(s.added.sum()):,} added")
        if s.removed is not None and bool(s.removed.any()):
            extra.append(f"{int(s.removed.sum()):,} removed")
        self.count.content = (f"**Selected:** {int(mask.sum()):,} of {s.n:,} Gaussians"
                              f" (threshold {s.threshold if s.threshold is not None else '-'}"
                              f"{'; ' + ', '.join(extra) + ' on the scene' if extra else ''})"
                              f"; UNet evaluations so far: {s.unet_evals:,}")

    def _set_edited(self, scene) -> None:
        edited = self.splats["edited"] = to_splats(scene, None, self.cap)
        if "edited" in self.nodes:
            self.nodes["edited"].set_gaussians(edited.centers, edited.covariances, edited.rgbs, edited.opacities)
        else:
            self.nodes["edited"] = self.server.scene.add_gaussian_splats(
                "/edited", centers=edited.centers, covariances=edited.covariances, rgbs=edited.rgbs,
                opacities=edited.opacities, visible=self.scene_shown == "After")

    def _show_scene(self, which: str) -> None:
        if which == "After" and "edited" not in self.nodes:
            self.session._say("After: no edit yet; the scene before is shown")
            which = "Before"
        self.scene_shown = which
        if "source" in self.nodes:
            self.nodes["source"].visible = which == "Before"
        if "edited" in self.nodes:
            self.nodes["edited"].visible = which == "After"
        if self.before_after.value != which:
            self.before_after.value = which
        self.showing.content = f"Showing: **{which.lower()}**"


def serve(session: StudioSession, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
          max_gaussians: int = DEFAULT_MAX_GAUSSIANS) -> Studio:
    """Start the viser server of `session` (in its own threads) and build the page."""
    import viser

    server = viser.ViserServer(host=host, port=port, label="gs_regional studio", verbose=False)
    page = Page(server, session, max_gaussians)
    shown_host = "localhost" if host in ("127.0.0.1", "0.0.0.0", "localhost") else host
    return Studio(server=server, url=f"http://{shown_host}:{server.get_port()}", session=session, page=page)
