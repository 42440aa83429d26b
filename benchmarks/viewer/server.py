"""The viewer's viser wiring: GUI, camera frusta, and one render thread per browser tab.

Each connected browser tab (a viser client) has a :class:`ClientView` whose thread renders the latest request
and sends it as the scene's background image: small JPEG previews while the camera moves or the time plays,
the full-size PNG once the camera has been still for :data:`STILL_S` seconds. Looking through a named camera
(click its frustum, or the buttons) renders that camera's own ``K``, pose and size, letterboxed to the canvas,
until the user moves the camera away. The geometry and image logic live in :mod:`.camera` and :mod:`.frames`.
"""

from __future__ import annotations

import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from benchmarks.viewer import camera as cam
from benchmarks.viewer import frames
from benchmarks.viewer.source import ViewCamera, ViewSource, find_test_camera
from worldtree.infra.errors import UserError

#: Seconds without a camera change after which the full-size image is rendered.
STILL_S = 0.3
#: Seconds after the server places a camera during which the browser's intermediate echoes are not taken as
#: the user moving away (the pose arrives as several messages).
LOCK_GRACE_S = 1.0
#: Pose tolerance (see :func:`camera.same_pose`) of "still looking through the named camera".
LOCK_TOL = 1e-3
TEST_COLOUR = (220, 40, 40)
TRAIN_COLOUR = (120, 120, 120)
CURRENT_COLOUR = (40, 120, 230)
#: Opacity (0..255) of a frustum's image plane.
FRUSTUM_PLANE_ALPHA = 40
#: Frames kept of those last sent (all tabs), for :meth:`Viewer.wait_for_frame`: a drag's last previews, then
#: its full image, outlive a waiter that wakes late on a busy machine.
FRAME_HISTORY = 8


def check_can_serve(host: str, port: int) -> None:
    """Raise a :class:`UserError` unless ``host:port`` can be listened on (viser itself would silently move
    to the next port, or wait forever for a host it cannot bind)."""
    if not 0 <= port <= 65535:
        raise UserError(f"--port {port}: not a port number; use 1..65535 (or 0 for any free port)")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as e:
        raise UserError(f"--host {host}: not an address of this machine ({e}); use 127.0.0.1") from None
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as s:
        # As the server will: a port left in TIME_WAIT by an earlier viewer is free.
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
        except OSError as e:
            if port and e.errno in (98, 48, 10048):  # EADDRINUSE on Linux, macOS, Windows
                raise UserError(
                    f"--port {port} is in use; choose another port (or --port 0 for any free one)"
                ) from None
            raise UserError(
                f"--host {host} --port {port}: cannot listen there ({e.strerror}); use --host 127.0.0.1"
            ) from None


@dataclass
class Frame:
    """One image the viewer sent to a browser tab."""

    image: np.ndarray
    """``uint8 [H, W, 3]`` as rendered (for a named camera: its own size, before letterboxing)."""
    sent: np.ndarray
    """``uint8 [H', W', 3]``: the image sent (``image``, letterboxed for a named camera)."""
    format: str
    """``png`` or ``jpeg``."""
    camera: str | None
    """The named camera looked through, or None for the free camera."""
    time: int
    """Time index."""
    mode: str
    """Render mode (menu label)."""
    preview: bool
    """A reduced-size preview (camera moving or playing)."""
    box: cam.Letterbox
    """Where ``image`` sits in ``sent``."""
    seconds: float
    """Render time, seconds."""
    seq: int = 0
    """Counter of frames sent by the whole viewer (set when recorded)."""


@dataclass
class _Request:
    time: int
    mode: str
    locked: ViewCamera | None
    wxyz: np.ndarray
    position: np.ndarray
    fov: float
    canvas: tuple[int, int]
    moving: bool


@dataclass
class _ClientState:
    locked: ViewCamera | None = None
    locked_at: float = 0.0
    #: The poses of the browser's camera an intermediate echo of the last placement may mix: its ``(wxyz,
    #: position)`` before the server placed it and the placed ones.
    placing: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    moved_at: float = 0.0
    version: int = 0
    done: int = -1
    canvas: tuple[int, int] = (0, 0)
    ready: bool = False
    stop: bool = False
    cond: threading.Condition = field(default_factory=threading.Condition)


class ClientView:
    """The render thread and camera state of one browser tab."""

    def __init__(self, viewer: Viewer, client) -> None:
        self.viewer = viewer
        self.client = client
        self.state = _ClientState()
        self.status = client.gui.add_markdown("", order=100)
        self.thread = threading.Thread(
            target=self._loop, name=f"viewer-client-{client.client_id}", daemon=True
        )
        client.camera.on_update(self._on_camera)
        self.thread.start()

    # -- requests ---------------------------------------------------------------------------------------------
    def request(self) -> None:
        """Render again (the time, mode or playing state changed)."""
        st = self.state
        with st.cond:
            st.version += 1
            st.cond.notify_all()

    def look_through(self, camera: ViewCamera) -> None:
        """Place the browser camera at ``camera`` and render that camera exactly."""
        st = self.state
        c = self.client.camera
        if not st.ready:  # the browser has not reported its camera yet: do it on its first report
            with st.cond:
                st.locked = camera
            return
        wxyz, position = cam.viser_from_w2c(camera.w2c)
        before = (np.array(c.wxyz, dtype=np.float64), np.array(c.position, dtype=np.float64))
        with st.cond:
            st.locked, st.locked_at = camera, time.monotonic()
            st.placing = (before, (wxyz, position))
            st.version += 1
            st.cond.notify_all()
        self.viewer.refresh_frusta()
        aspect = c.aspect if c.image_height > 0 else camera.width / camera.height
        with self.client.atomic():
            c.fov = cam.letterbox_fov(camera.K, camera.width, camera.height, aspect)
            c.wxyz = wxyz
            c.position = position

    def _on_camera(self, c) -> None:
        st = self.state
        first = not st.ready
        with st.cond:
            st.ready = True
            if first:
                st.canvas = (int(c.image_width), int(c.image_height))
        if first:
            initial = st.locked or self.viewer.initial_camera
            if initial is not None:
                self.look_through(initial)
                return
        w2c = cam.w2c_from_viser(c.wxyz, c.position)
        now = time.monotonic()
        left = False
        with st.cond:
            canvas = (int(c.image_width), int(c.image_height))
            before, st.canvas = st.canvas, canvas
            if st.locked is not None:
                if cam.same_pose(w2c, st.locked.w2c, self.viewer.scale, LOCK_TOL):
                    if _box(st.locked, before) != _box(st.locked, canvas):  # the canvas changed shape
                        st.version += 1
                        st.cond.notify_all()
                    return
                if now - st.locked_at < LOCK_GRACE_S or self._mixes_placement(w2c):
                    return  # an intermediate echo of the pose the server is placing (late on a busy machine)
                st.locked, left = None, True
            st.moved_at = now
            st.version += 1
            st.cond.notify_all()
        if left:
            self.viewer.refresh_frusta()

    def _mixes_placement(self, w2c: np.ndarray) -> bool:
        """Whether the browser pose ``w2c [4, 4]`` is the last placement's rotation or position each taken from
        before or after it: what the browser echoes while the placement's messages arrive one by one."""
        if self.state.placing is None:
            return False
        (q0, p0), (q1, p1) = self.state.placing
        return any(
            cam.same_pose(w2c, cam.w2c_from_viser(q, p), self.viewer.scale, LOCK_TOL)
            for q in (q0, q1)
            for p in (p0, p1)
        )

    # -- rendering --------------------------------------------------------------------------------------------
    def _snapshot(self) -> _Request:
        st, c, v = self.state, self.client.camera, self.viewer
        moving = (time.monotonic() - st.moved_at < STILL_S) or v.playing
        return _Request(
            time=v.time_index(),
            mode=v.mode(),
            locked=st.locked,
            wxyz=np.array(c.wxyz, dtype=np.float64),
            position=np.array(c.position, dtype=np.float64),
            fov=float(c.fov),
            canvas=st.canvas,
            moving=moving and st.locked is None,
        )

    def _loop(self) -> None:
        st = self.state
        while True:
            with st.cond:
                while not st.stop and (st.done == st.version or not st.ready):
                    st.cond.wait()
                if st.stop:
                    return
                version = st.version
            try:
                req = self._snapshot()
            except AssertionError:  # viser's camera not initialised yet
                time.sleep(0.05)
                continue
            self._render(req)
            with st.cond:
                if req.moving:
                    # Come back for the full-size image once the camera has been still for STILL_S.
                    left = st.moved_at + STILL_S - time.monotonic()
                    if st.version == version and left > 0:
                        st.cond.wait(timeout=left)
                    if self.viewer.playing:
                        st.done = max(st.done, version)
                elif st.version == version:
                    st.done = version

    def _render(self, req: _Request) -> None:
        v = self.viewer
        t0 = time.perf_counter()
        node = v.source.node_label(req.time)
        try:
            if req.locked is not None:
                c = req.locked
                rendered = v.render(c, req.time, req.mode)
                image = frames.to_display(rendered, req.mode, node)
                box = _box(c, req.canvas)
                sent = np.zeros((box.height, box.width, 3), dtype=np.uint8)
                sent[box.y0 : box.y0 + c.height, box.x0 : box.x0 + c.width] = image
            else:
                W, H = cam.render_size(req.canvas[0], req.canvas[1], v.max_size, req.moving)
                K = cam.free_intrinsics(req.fov, W, H)
                w2c = cam.w2c_from_viser(req.wxyz, req.position)
                rendered = v.render((K, w2c, W, H), req.time, req.mode)
                image = sent = frames.to_display(rendered, req.mode, node)
                box = cam.Letterbox(W, H, 0, 0)
        except Exception as e:  # a failed render must not end the tab's thread; say why once per failure
            print(f"viewer: render failed ({type(e).__name__}: {e})", file=sys.stderr)
            return
        enc = frames.encoding_for(req.moving)
        self.client.scene.set_background_image(sent, format=enc.format, jpeg_quality=enc.jpeg_quality)
        seconds = time.perf_counter() - t0
        where = req.locked.name if req.locked is not None else "free camera"
        label = f" · node {node}" if node is not None else ""
        self.status.content = (
            f"**{where}** · time {v.source.times[req.time]}{label}  \n"
            f"{image.shape[1]}x{image.shape[0]} {enc.format} in {seconds * 1000:.0f} ms"
        )
        v.record(
            Frame(image, sent, enc.format, req.locked.name if req.locked else None, req.time, req.mode,
                  req.moving, box, seconds),
        )  # fmt: skip

    def stop(self) -> None:
        with self.state.cond:
            self.state.stop = True
            self.state.cond.notify_all()


class Viewer:
    """A running viewer of ``source`` (starts serving on construction; :meth:`stop` ends it)."""

    def __init__(
        self,
        source: ViewSource,
        host: str = "127.0.0.1",
        port: int = 8080,
        max_size: int | None = None,
        fps: float = 10.0,
    ) -> None:
        import viser

        if not source.times:
            raise UserError("the run has no times to show; is it a finished run folder?")
        check_can_serve(host, port)
        self.source = source
        sizes = [max(c.width, c.height) for c in source.cameras]
        self.max_size = int(max_size or (max(sizes) if sizes else 960))
        self.fps = fps
        self.playing = False
        self.scale = cam.scene_scale([c.w2c for c in source.cameras]) if source.cameras else 1.0
        self.initial_camera = find_test_camera(source) or (source.cameras[0] if source.cameras else None)
        self.frames: deque[Frame] = deque(maxlen=FRAME_HISTORY)
        self._frame_cond = threading.Condition()
        self._seq = 0
        self._render_lock = threading.Lock()
        self._clients: dict[int, ClientView] = {}
        self._clients_lock = threading.Lock()
        self._stop = threading.Event()

        self.server = viser.ViserServer(host=host, port=port, label=source.title, verbose=False)
        self.host, self.port = host, self.server.get_port()
        self._build_scene()
        self._build_gui()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._player = threading.Thread(target=self._play_loop, name="viewer-player", daemon=True)
        self._player.start()

    # -- scene and GUI ----------------------------------------------------------------------------------------
    def _build_scene(self) -> None:
        scene = self.server.scene
        if self.source.cameras:
            scene.set_up_direction(cam.scene_up([c.w2c for c in self.source.cameras]))
        size = 0.12 * self.scale
        self._frusta: dict[str, object] = {}
        for c in self.source.cameras:
            wxyz, position = cam.viser_from_w2c(c.w2c)
            colour = TEST_COLOUR if c.is_test else TRAIN_COLOUR
            handle = scene.add_camera_frustum(
                f"/cameras/{_node_name(c.name)}",
                fov=cam.vertical_fov(c.K, c.height),
                aspect=c.width / c.height,
                scale=size * (1.5 if c.is_test else 1.0),
                thickness=1.5,
                thickness_units="screen",
                color=colour,
                # A faint image plane: viser picks clicks on a frustum's meshes only (its lines are not hit).
                image=np.array([[[*colour, FRUSTUM_PLANE_ALPHA]]], dtype=np.uint8),
                format="png",
                wxyz=wxyz,
                position=position,
            )
            handle.on_click(lambda event, c=c: self._client_view(event.client).look_through(c))
            self._frusta[c.name] = handle

    def _build_gui(self) -> None:
        gui = self.server.gui
        src = self.source
        gui.add_markdown(f"**{src.title}**  \nrendering on {src.device}")
        n = len(src.times)
        self.time_slider = gui.add_slider("time", min=0, max=max(n - 1, 0), step=1, initial_value=0,
                                          disabled=n < 2, hint="Time index into the run's frames")  # fmt: skip
        self.time_slider.on_update(lambda _: self._changed())
        self.play_button = gui.add_button("Play", hint="Play or pause the time")
        self.play_button.on_click(lambda _: self.set_playing(not self.playing))
        self.fps_input = gui.add_number(
            "frames per second", initial_value=self.fps, min=0.5, max=60.0, step=0.5
        )
        has_tree = src.node_label(0) is not None
        self.mode_menu = gui.add_dropdown("render", frames.modes_for(has_tree), initial_value="colour")
        self.mode_menu.on_update(lambda _: self._changed())
        test = find_test_camera(src)
        if test is not None:
            b = gui.add_button("Test camera", hint="Look through the held-out test camera")
            b.on_click(lambda e, c=test: self._client_view(e.client).look_through(c))
        if any(c.time is not None for c in src.cameras):
            b = gui.add_button(
                "Training camera at this time", hint="Look through the frame trained on at this time"
            )
            b.on_click(lambda e: self._look_at_training_frame(e.client))
        self.show_cameras = gui.add_checkbox("show cameras", initial_value=True)
        self.show_cameras.on_update(lambda _: self.refresh_frusta())
        self._highlight(0)

    def refresh_frusta(self) -> None:
        """Show the frusta (unless *show cameras* is off), but not one a tab looks through: its image plane
        would cover that tab's view."""
        with self._clients_lock:
            looked = {v.state.locked.name for v in self._clients.values() if v.state.locked is not None}
        show = bool(self.show_cameras.value)
        for name, h in self._frusta.items():
            visible = show and name not in looked
            if h.visible != visible:
                h.visible = visible

    def _highlight(self, t: int) -> None:
        """Colour the training frustum of time index ``t`` (the frame the video shows now)."""
        for c in self.source.cameras:
            if c.is_test:
                continue
            colour = CURRENT_COLOUR if c.time == t else TRAIN_COLOUR
            h = self._frusta[c.name]
            if tuple(h.color) != colour:
                h.color = colour

    def _look_at_training_frame(self, client) -> None:
        t = self.time_index()
        c = next((c for c in self.source.cameras if c.time == t and not c.is_test), None)
        if c is not None:
            self._client_view(client).look_through(c)

    # -- state read by the render threads ---------------------------------------------------------------------
    def time_index(self) -> int:
        """Time index the slider shows."""
        return frames.time_index(self.time_slider.value, len(self.source.times))

    def mode(self) -> str:
        """Render mode (menu label) chosen."""
        return str(self.mode_menu.value)

    def set_playing(self, playing: bool) -> None:
        """Start or pause playback of the time."""
        self.playing = playing
        self.play_button.label = "Pause" if playing else "Play"
        self._changed()

    def _changed(self) -> None:
        self._highlight(self.time_index())
        with self._clients_lock:
            views = list(self._clients.values())
        for view in views:
            view.request()

    def _play_loop(self) -> None:
        next_at = time.monotonic()
        while not self._stop.is_set():
            if not self.playing:
                next_at = time.monotonic()
                self._stop.wait(0.05)
                continue
            next_at += 1.0 / max(float(self.fps_input.value), 0.5)
            self._stop.wait(max(0.0, next_at - time.monotonic()))
            if self.playing and not self._stop.is_set():
                self.time_slider.value = frames.next_time_index(self.time_index(), len(self.source.times))

    def render(self, camera, t: int, mode: str):
        """The source's render of ``camera`` at time index ``t`` in menu mode ``mode`` (one render at a time)."""
        with self._render_lock:
            return self.source.render(camera, t, frames.MODES[mode])

    # -- clients ----------------------------------------------------------------------------------------------
    def _connect(self, client) -> None:
        self._client_view(client)

    def _client_view(self, client) -> ClientView:
        with self._clients_lock:
            view = self._clients.get(client.client_id)
            if view is None:
                view = self._clients[client.client_id] = ClientView(self, client)
            return view

    def _disconnect(self, client) -> None:
        with self._clients_lock:
            view = self._clients.pop(client.client_id, None)
        if view is not None:
            view.stop()

    def record(self, frame: Frame) -> None:
        """Keep ``frame`` among the last :data:`FRAME_HISTORY` sent (tests read :attr:`frames`)."""
        with self._frame_cond:
            self._seq += 1
            frame.seq = self._seq
            self.frames.append(frame)
            self._frame_cond.notify_all()

    def wait_for_frame(self, accept: Callable[[Frame], bool], timeout: float = 30.0) -> Frame:
        """Block until a tab was sent a frame that ``accept`` takes; return the newest such frame of those
        kept (TimeoutError after ``timeout`` seconds)."""
        deadline = time.monotonic() + timeout
        with self._frame_cond:
            while True:
                for f in reversed(self.frames):
                    if accept(f):
                        return f
                left = deadline - time.monotonic()
                if left <= 0:  # say what was sent instead: a failed wait on a busy machine is read from this
                    kept = ", ".join(
                        f"#{f.seq} {f.camera or 'free'} t{f.time} {f.mode}{' preview' if f.preview else ''}"
                        for f in self.frames
                    )
                    raise TimeoutError(
                        f"no frame as expected was sent in {timeout:g} s (playing: {self.playing}; "
                        f"the last sent: {kept or 'none'})"
                    )
                self._frame_cond.wait(left)

    @property
    def url(self) -> str:
        """Address to open in a browser."""
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}"

    def stop(self) -> None:
        """Stop playback, the render threads and the server."""
        self._stop.set()
        self.playing = False
        with self._clients_lock:
            views = list(self._clients.values())
            self._clients.clear()
        for view in views:
            view.stop()
        self.server.stop()


def _box(c: ViewCamera, canvas: tuple[int, int]) -> cam.Letterbox:
    """Where camera ``c``'s image sits when letterboxed for a ``canvas`` of ``(width, height)`` pixels."""
    aspect = canvas[0] / canvas[1] if canvas[1] > 0 else c.width / c.height
    return cam.letterbox(c.width, c.height, aspect)


def _node_name(name: str) -> str:
    """A scene-tree node name for a camera name (viser's names are '/'-separated paths)."""
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)
