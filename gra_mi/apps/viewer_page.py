"""``gra-mi view``: the browser page (viser, the library nerfstudio's viewer is built on) around a :class:`ViewerSession`.

The server renders each browser's view itself (gra-mi's relit texture through gra-mi's rasteriser, for that browser's
camera) and sends it as the page's background image, as nerfstudio's viewer does; the page draws the rig's LEDs, a
gizmo for the point light and the controls on top. A control change re-shades the current frame and re-sends one
image per browser; orbiting re-renders for the new viewpoint (highlights follow the view). Every browser has a worker
that renders only the latest request, so a fast drag never queues stale frames. The page reads no file a browser
names: the maps it offers are the ones the server was started with.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from gra_mi.apps.viewer import MODES, ViewerSession, camera_pose, scaled_to, viewer_camera, with_lighting
from gra_mi.core.errors import GraMiInputError

logger = logging.getLogger(__name__)

LED_COLOR, LED_LIT = (90, 90, 110), (255, 60, 40)
WORKER_JOIN_S = 120  # a frame's visibility or a view in progress finishes first (seconds on a CPU)


class ClientView:
    """One browser: renders its camera's view whenever asked, the latest request only."""

    def __init__(self, page: ViewerPage, client):
        self.page, self.client = page, client
        self.wanted = threading.Event()
        self.closed = False
        page.start_worker(self._loop, f"view-{client.client_id}")
        client.camera.on_update(lambda _: self.wanted.set())
        self.wanted.set()

    def _loop(self) -> None:
        while not self.closed and not self.page.stop.is_set():
            if not self.wanted.wait(timeout=0.5):
                continue
            self.wanted.clear()
            try:
                self._render()
            except GraMiInputError as exc:
                self.page.say(str(exc))
            except Exception:  # a render that fails must not take the page down with it
                logger.exception("render failed")
                self.page.say("a render failed: the server's terminal has the details")

    def _render(self) -> None:
        cam = self.client.camera
        if cam.update_timestamp == 0.0:  # the browser has not said where it looks yet
            self.wanted.set()
            time.sleep(0.05)
            return
        start = time.perf_counter()
        width, height = scaled_to(cam.image_width, cam.image_height, self.page.max_size)
        view = self.page.session.render(viewer_camera(cam.position, cam.wxyz, cam.fov, width, height))
        encode = time.perf_counter()
        self.client.scene.set_background_image(view.image, format="jpeg", jpeg_quality=92, depth=view.depth)
        view.timings["send"] = 1000 * (time.perf_counter() - encode)
        view.timings["total"] = 1000 * (time.perf_counter() - start)
        self.page.show_timings(view.timings, width, height)


class ViewerPage:
    """The viser server, its controls and one :class:`ClientView` per browser."""

    def __init__(self, session: ViewerSession, host: str = "127.0.0.1", port: int = 8080, max_size: int = 512):
        import viser

        self.session, self.max_size = session, max_size
        self.rendered = 0
        self.stop = threading.Event()
        self.views: dict[int, ClientView] = {}
        self.workers: list[threading.Thread] = []
        self.server = viser.ViserServer(host=host, port=port, label="gra-mi view", verbose=False)
        self.server.scene.set_up_direction("+y")
        # No share button: viser's share link tunnels the page to a public URL, which a shared machine must not do.
        self.server.gui.configure_theme(dark_mode=True, show_share_button=False, control_width="medium")
        self._controls()
        self._rig()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self.start_worker(self._precompute, "visibility")

    # ---------------------------------------------------------------- page
    def _controls(self) -> None:
        gui, s, light = self.server.gui, self.session, self.session.lighting
        self.ready = "\n\n".join(f"**Note:** {n}" for n in s.notices) or "Ready."
        self.status = gui.add_markdown(self.ready)
        with gui.add_folder("Lighting"):
            self.mode = gui.add_dropdown("mode", MODES, initial_value=light.mode)
            self.envmap = gui.add_dropdown("envmap", list(s.envmap_sources), initial_value=light.envmap)
            self.rotation = gui.add_slider("rotation (deg)", -180, 180, 5, 0)
            self.field = gui.add_dropdown("lighting model", ("far field", "near field"), initial_value="far field")
            self.bounces = gui.add_dropdown(
                "bounces of light", tuple(sorted({"1", "2", "3", str(light.bounces)}, key=int)), initial_value=str(light.bounces)
            )
            self.olat = gui.add_slider("LED (OLAT)", 0, s.ls.stage.num_leds - 1, 1, 0)
            self.point = gui.add_vector3("point light (m)", light.point, min=(-5.0, -5.0, -5.0), max=(5.0, 5.0, 5.0), step=0.05)
            self.intensity = gui.add_slider("point light W/sr", 0.1, 10.0, 0.1, light.point_intensity)
            self.exposure = gui.add_slider("exposure (EV)", -4.0, 4.0, 0.25, 0.0)
        with gui.add_folder("Subject"):
            self.stage = gui.add_dropdown("show", s.stages, initial_value="microfacet")
            self.frame = gui.add_slider("frame", 0, max(s.num_frames - 1, 1), 1, 0, disabled=s.num_frames == 1)
            self.play = gui.add_checkbox("play", False, disabled=s.num_frames == 1)
            self.camera = gui.add_dropdown("camera", [c.name for c in s.ls.stage.cameras])
            snap = gui.add_button("view from this camera")
        self.env_preview = gui.add_image(self._env_preview(), label="lighting (lat-long, as RelightNet sees it)")
        self.truth = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="ground truth", visible=False)
        self.progress = gui.add_progress_bar(0.0, animated=True)
        self.timings = gui.add_markdown("")
        for handle in (
            self.mode,
            self.envmap,
            self.rotation,
            self.field,
            self.bounces,
            self.olat,
            self.point,
            self.intensity,
            self.exposure,
            self.stage,
            self.frame,
        ):
            handle.on_update(lambda _: self._changed())
        self.play.on_update(lambda _: self._start_playing())
        snap.on_click(lambda event: self._snap(event.client))

    def _rig(self) -> None:
        stage = self.session.ls.stage
        self.leds = self.server.scene.add_point_cloud(
            "/rig/leds", stage.led_positions.astype(np.float32), np.tile(np.array(LED_COLOR, np.uint8), (stage.num_leds, 1)), point_size=0.015
        )  # fmt: skip
        self.gizmo = self.server.scene.add_transform_controls(
            "/point_light", scale=0.25, position=self.session.lighting.point, disable_rotations=True
        )
        self.gizmo.on_update(lambda _: self._gizmo_moved())
        self._show_rig()

    def _show_rig(self) -> None:
        light = self.session.lighting
        colors = np.tile(np.array(LED_COLOR, np.uint8), (self.session.ls.stage.num_leds, 1))
        if light.mode == "olat":
            colors[light.olat] = LED_LIT
        self.leds.colors = colors
        self.gizmo.visible = light.mode == "point light"
        for handle, shown in ((self.envmap, "envmap"), (self.rotation, "envmap"), (self.field, "envmap"), (self.olat, "olat"),
                              (self.point, "point light"), (self.intensity, "point light")):  # fmt: skip
            handle.visible = light.mode == shown

    def _env_preview(self) -> np.ndarray:
        from gra_mi.core.color import display_exposure
        from gra_mi.core.io import to_srgb8

        try:
            env = self.session.lighting_preview()
        except GraMiInputError:
            return np.zeros((32, 64, 3), np.uint8)
        return to_srgb8(env, display_exposure(env) if env.max() > 0 else 1.0)

    # ---------------------------------------------------------------- events
    def _changed(self) -> None:
        point = tuple(float(v) for v in self.point.value)
        try:
            with_lighting(
                self.session, mode=self.mode.value, envmap=self.envmap.value, rotation=float(self.rotation.value),
                far_field=self.field.value == "far field", olat=int(self.olat.value), point=point,
                point_intensity=float(self.intensity.value), stage=self.stage.value, frame=int(self.frame.value),
                exposure=float(self.exposure.value), bounces=int(self.bounces.value),
            )  # fmt: skip
        except GraMiInputError as exc:  # e.g. an envmap file that cannot be read: said, and the last lighting stays
            self.say(str(exc))
            return
        self.status.content = self.ready  # a change that worked clears the last error
        if np.any(np.abs(np.asarray(self.gizmo.position) - point) > 1e-6):
            self.gizmo.position = point
        self._show_rig()
        self.env_preview.image = self._env_preview()
        self._show_truth()
        self.refresh()

    def _gizmo_moved(self) -> None:
        position = tuple(round(float(v), 4) for v in self.gizmo.position)
        if position != tuple(self.point.value):
            self.point.value = position  # the vector's update re-renders

    def _snap(self, client) -> None:
        if client is None:
            return
        position, wxyz, fov = camera_pose(self.session.ls.stage.camera(self.camera.value))
        with client.atomic():
            client.camera.wxyz, client.camera.position, client.camera.fov = wxyz, position, fov
        self._show_truth()

    def _show_truth(self) -> None:
        truth = self.session.ground_truth(self.camera.value, self.session.lighting.frame)
        self.truth.visible = truth is not None
        if truth is not None:
            self.truth.image, self.truth.label = truth[0], f"ground truth ({truth[1]})"

    def _start_playing(self) -> None:
        if self.play.value:
            self.start_worker(self._play, "play")

    def _play(self) -> None:
        period = 1.0 / float(self.session.ls.sequence.fps or 24.0)
        while self.play.value and not self.stop.is_set():
            start = time.perf_counter()
            self.frame.value = (int(self.frame.value) + 1) % self.session.num_frames
            time.sleep(max(0.0, period - (time.perf_counter() - start)))

    def _precompute(self) -> None:
        """The frames' visibility (:meth:`ViewerSession.frames_to_precompute`), traced in the background with its
        progress on the page."""
        frames = self.session.frames_to_precompute()

        def progress(done: int, total: int) -> None:
            self.progress.value = 100.0 * done / total

        skipped = self.session.precompute(frames, far_field=self.session.lighting.far_field, progress=progress, stop=self.stop)
        self.progress.visible = False
        if skipped:  # said once, not per frame: the first names the file and the frame
            self.say(f"{len(skipped)} frame(s) could not be traced and will not show: {skipped[0]}")

    def _connect(self, client) -> None:
        """A new browser starts where the rig's first camera stands, orbiting the subject's centre."""
        position, wxyz, fov = camera_pose(self.session.ls.stage.cameras[0])
        with client.atomic():
            client.camera.position, client.camera.fov = position, fov
            client.camera.look_at = self.session.subject_center()
        self.views[client.client_id] = ClientView(self, client)

    def _disconnect(self, client) -> None:
        view = self.views.pop(client.client_id, None)
        if view is not None:
            view.closed = True

    # ---------------------------------------------------------------- output
    def refresh(self) -> None:
        for view in list(self.views.values()):
            view.wanted.set()

    def say(self, message: str) -> None:
        logger.warning("%s", message)
        self.status.content = f"**{message}**"

    def show_timings(self, timings: dict[str, float], width: int, height: int) -> None:
        parts = " · ".join(f"{k} {v:.0f}" for k, v in timings.items() if k != "total")
        self.rendered += 1
        self.timings.content = f"view {self.rendered}, {width}×{height}: **{timings['total']:.0f} ms** on the server ({parts})"

    def start_worker(self, target, name: str) -> None:
        """A background thread of the page, joined by :meth:`close`."""
        worker = threading.Thread(target=target, daemon=True, name=name)
        self.workers = [w for w in self.workers if w.is_alive()] + [worker]
        worker.start()

    def close(self) -> None:
        """Stop the page and wait for its threads: one that still traces or renders when Python exits finds Mitsuba
        torn down (a Ctrl-C in the first seconds once ended in tracebacks and a C++ abort)."""
        self.stop.set()
        for worker in self.workers:  # each finishes its frame or view while the server can still take what it sends
            worker.join(timeout=WORKER_JOIN_S)
            if worker.is_alive():
                logger.warning("thread %s still running after %d s; exiting anyway", worker.name, WORKER_JOIN_S)
        self.server.stop()
