"""Wiring of the inspection app: ``run(config, server)`` builds it on a server it is given.

Nothing here is module-level state: a test creates ``ViserServer(host="127.0.0.1", port=0)``,
calls :func:`run` and reads ``server.get_port()``; ``pregrasp view`` calls :func:`serve`, which
creates the server, prints how to reach it and serves until interrupted.
"""

from __future__ import annotations

import gc
import getpass
import logging
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pregrasp_core.io import SensorOptions
from pregrasp_core.paths import DEFAULT_OBJECT

from . import viser_hooks
from .compare_layer import CompareLayer
from .controller import DEFAULT_MAX_UPLOAD_BYTES, Controller
from .gui import Gui
from .scene import SceneRenderer
from .state import ViewState

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ViewerConfig:
    """Options of ``pregrasp view``."""

    input: Path | None = None
    """Point cloud or mesh to open; ``None`` opens the default object (the mug with a handle)."""
    host: str = "127.0.0.1"
    """Interface to bind; the default keeps the app private to this machine (use an SSH
    port-forward to reach it from elsewhere, see ``docs/usage.md``)."""
    port: int = 8080
    """Port to listen on (viser moves to the next free port when it is taken; 0 = any)."""
    n_points: int = 20000
    """Points sampled on a mesh."""
    seed: int = 0
    """Seed of the mesh sampling."""
    scale: float | None = None
    """Multiplies the coordinates of the object opened at start (0.001 for a file in
    millimetres); ``None`` = as stored."""
    sensor: SensorOptions | None = None
    """Depth-camera options of the object opened at start (``--intrinsics``, ``--pick``,
    ``--scene``, ``--viewpoint``; ``pregrasp_core.io.SensorOptions``); ``None`` = the loader's
    defaults (a depth image with its sidecar JSON, as a scene)."""
    max_upload_bytes: int = DEFAULT_MAX_UPLOAD_BYTES
    """Largest accepted upload in bytes."""
    max_ghosts: int = 24
    """Most hand ghosts drawn at once (an even subsample of the filtered pool beyond that):
    few, so every action shows within 2 s even where the browser renders WebGL in software;
    choose which with the grasp-type and node filters."""
    animate_hz: float = 30.0
    """Rate of the animation clock (frames per second)."""
    show_ghosts: bool = False
    """Whether the pre-grasp ghosts are drawn at start (the GUI toggles them)."""
    plan_on_start: bool = False
    """Plan the grasps in a background thread once the object is loaded (``pregrasp view``
    does), so the first screen shows the best grasp; the progress bar shows the run."""
    show_face_masks: bool = True
    """Whether the face masks are drawn at start (the GUI toggles them)."""
    params: Any = field(default=None)
    """``PipelineParams`` to start with (defaults when ``None``)."""
    compare: Path | None = None
    """A second ``pregrasp/1`` result file of the same object to compare with (its best grasps
    drawn beside the shown ones), or ``None``."""
    planner_process: bool = True
    """Plan in a worker process of one thread (``app/planner_proc.py``), which forks its copy
    and plans on two cores as ``pregrasp plan`` does, instead of on the server's threads that
    Python's global lock serialises; started with the app, warmed up in the background (plans
    before it is ready, and after it fails, run in the server's process)."""

    def __post_init__(self) -> None:
        if not 0 <= int(self.port) <= 65535:
            raise ValueError(f"port must be in [0, 65535], got {self.port}")
        for name, lo in (("n_points", 10), ("max_upload_bytes", 1), ("max_ghosts", 0)):
            if int(getattr(self, name)) < lo:
                raise ValueError(f"{name} must be at least {lo}, got {getattr(self, name)}")
        if int(self.seed) < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if not float(self.animate_hz) > 0:
            raise ValueError(f"animate_hz must be > 0, got {self.animate_hz}")


class App:
    """A running app: its controller, scene and GUI, plus the animation thread."""

    def __init__(
        self,
        server: Any,
        controller: Controller,
        scene: SceneRenderer,
        gui: Gui,
        animate_hz: float,
        uploads: viser_hooks.UploadGuard,
    ) -> None:
        self.server = server
        self.controller = controller
        self.scene = scene
        self.gui = gui
        self.uploads = uploads
        """The guard in front of viser's upload handlers (see :mod:`app.viser_hooks`)."""
        self.compare_layer: CompareLayer | None = None
        """The layer drawing a compared result file's best grasps (``app.compare_layer``)."""
        self._stop = threading.Event()
        self._period = 1.0 / float(animate_hz)
        self._thread = threading.Thread(target=self._animate, name="pregrasp-animator", daemon=True)
        self._thread.start()

    def _animate(self) -> None:
        last = time.perf_counter()
        while not self._stop.wait(self._period):
            now = time.perf_counter()
            if self.controller.state.view.playing:
                self.controller.act(None, self.controller.tick, now - last)
            last = now

    def plan_in_background(self) -> threading.Thread:
        """Start planning on a daemon thread (errors become notifications); returns it."""
        c = self.controller
        t = threading.Thread(target=lambda: c.act(None, c.plan), name="pregrasp-plan", daemon=True)
        t.start()
        return t

    def close(self) -> None:
        """Stop the animation thread (the caller stops its server)."""
        self._stop.set()
        self.gui.close()
        self._thread.join(timeout=2.0)
        if self.controller.planner is not None:  # no worker outlives the app
            self.controller.planner.close()


def protect(server: Any, host: str) -> None:
    """Refuse requests from other origins on ``server`` (see :mod:`app.viser_hooks`): only
    pages served by this server, under a loopback name or (bound beyond loopback) this
    machine's names, may talk to it. Raises ``ViserHookError`` when viser cannot be hooked."""
    viser_hooks.install_origin_check(server, viser_hooks.allowed_host_names(host))


def run(config: ViewerConfig, server: Any) -> App:
    """Build the app on ``server`` and load ``config.input`` (or the default object).

    Installs the server's defences first (:func:`protect`, the upload and GUI-update guards of
    :mod:`app.viser_hooks`, ``docs/security.md``). Raises the loader's ``PregraspError`` when
    the input cannot be read (the CLI prints it), ``ViserHookError`` when viser's internals
    cannot be hooked (the app never runs unprotected).
    """
    from pregrasp_core.hand import Hand

    protect(server, config.host)
    settle_heap()

    planner = None
    notices: list[Controller] = []  # the controller, once made: the worker's failure notices
    if config.planner_process:  # first: the worker's start-up runs beside the load below
        from .planner_proc import PlannerProcess

        def notice(text: str) -> None:
            for c in notices:
                c.notify(None, "Planner process", text, color="yellow")

        planner = PlannerProcess(notice=notice)
    try:
        return _build(config, server, Hand.load(), planner, notices)
    except BaseException:
        if planner is not None:
            planner.close()
        raise


def settle_heap() -> None:
    """Collect the process's garbage, then freeze what is left (``gc.freeze``) before the app
    is built: the imported modules, numba (imported here: every plan needs it) and whatever
    the process held before.

    The viewer's browsers are answered by Python threads, and a full collection holds the
    global lock while it walks every object of the heap: 0.1 s in the viewer alone, 0.3-0.6 s
    in a process that holds more (a test run's, or one where numba compiled kernels), long
    enough to stall every browser's answers mid-plan (measured, ``docs/app.md``, "Slow
    actions"). Frozen objects are never walked again, so later collections see only what came
    after: the app's own objects, which stay collectable (the app is built after the freeze, so
    a closed app's cycles are freed). Objects alive now stay alive as they would anyway; what
    dies among them later is still freed by reference counting."""
    from pregrasp_core.jit import import_numba

    import_numba()
    gc.collect()
    gc.freeze()


def _build(
    config: ViewerConfig, server: Any, hand: Any, planner: Any, notices: list[Controller]
) -> App:
    """:func:`run` once the defences are in place and the planner process started."""
    scene = SceneRenderer(server, hand=hand, max_ghosts=config.max_ghosts)
    controller = Controller(
        server,
        scene,
        hand,
        params=config.params,
        n_points=config.n_points,
        seed=config.seed,
        max_upload_bytes=config.max_upload_bytes,
        view=ViewState(show_ghosts=config.show_ghosts, show_face_masks=config.show_face_masks),
        planner=planner,
    )
    notices.append(controller)
    scene.on_box_click = lambda node, client: controller.act(client, controller.select_node, node)
    gui = Gui(server, controller, scene)
    uploads = viser_hooks.install_upload_guard(server, lambda: controller.max_upload_bytes)
    viser_hooks.install_update_guard(server, gui.on_bad_value, gui.begin_edit)
    layer = CompareLayer(server, hand)
    controller.subscribe(layer.render)
    path = config.input if config.input is not None else DEFAULT_OBJECT
    is_result = Path(path).suffix.lower() == ".json"
    if is_result:  # a pregrasp/1 result file: shown as it is, nothing recomputed
        controller.load_result_path(path)
    else:
        controller.load_path(path, scale=config.scale, sensor=config.sensor)
    if config.compare is not None:
        controller.compare_result_path(config.compare)
    app = App(server, controller, scene, gui, config.animate_hz, uploads)
    app.compare_layer = layer
    if config.plan_on_start and not is_result:
        app.plan_in_background()
    return app


def access_lines(host: str, port: int) -> list[str]:
    """The lines ``pregrasp view`` prints: the local URL and the exact SSH port-forward."""
    shown = "localhost" if host in ("127.0.0.1", "localhost", "0.0.0.0", "::") else host
    target = "localhost" if host in ("0.0.0.0", "::") else host
    fqdn = socket.getfqdn()
    machine = fqdn if fqdn and not fqdn.startswith("localhost") else socket.gethostname()
    user = getpass.getuser()
    return [
        f"pregrasp view: open http://{shown}:{port}",
        "From another computer, forward the port over SSH and open the same URL there:",
        f"  ssh -N -L {port}:{target}:{port} {user}@{machine}",
    ]


def exposure_warning(host: str) -> list[str]:
    """The warning ``pregrasp view`` prints when ``host`` is not a loopback address."""
    if viser_hooks.host_name(host) in viser_hooks.LOOPBACK_NAMES or host.startswith("127."):
        return []
    return [
        f"WARNING: --host {host} makes the viewer reachable from the network, with no password "
        "and no encryption: anyone who can reach this port can load files into it and use its "
        "CPU and memory.",
        "  Safer: keep the default --host 127.0.0.1 and reach it over SSH with the port-forward "
        "below (see docs/security.md).",
    ]


def serve(config: ViewerConfig) -> None:
    """Create the server, build the app, print how to reach it and serve until Ctrl-C."""
    import viser

    server = viser.ViserServer(host=config.host, port=config.port, verbose=False)
    try:
        app = run(config, server)
        lines = exposure_warning(config.host) + access_lines(config.host, server.get_port())
        for line in lines:
            print(line, flush=True)  # noqa: T201 - the CLI's output
        try:
            while True:
                time.sleep(3600)
        finally:
            app.close()
    finally:
        server.stop()
