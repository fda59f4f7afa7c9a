"""The state of the inspection app: plain, immutable data and nothing else.

One :class:`AppState` per server. The controller replaces it as a whole (``dataclasses.replace``)
under its lock after every action; the scene and the GUI only read it. It holds no viser handles,
no locks and no threads, so a test can build one, compare two, or keep an old one around.

Several browsers connected to the same server share this one state (one object, one tree, one
pool, one selection): what one user changes, every other browser sees. See ``docs/app.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

ALL = "all"
"""Value of the grasp-type and node filters that keeps every pre-grasp."""


@dataclass(frozen=True)
class ObjectSource:
    """Where the current point cloud comes from, enough to load it again with a new N or seed."""

    name: str
    """Display name: the demo object's file stem or the uploaded file's name."""
    path: str | None = None
    """File path of a demo object or of the ``INPUT`` given on the command line, else ``None``."""
    data: bytes | None = field(default=None, repr=False)
    """Raw bytes of an uploaded file (parsed by ``pregrasp_core.io`` only, never executed)."""
    scale: float | None = None
    """Multiplies the coordinates when read (``pregrasp view --scale``, the scale field);
    ``None`` = as stored, or by 0.001 when the loader recognises millimetres."""
    sensor: Any = None
    """Depth-camera options of the loader (``pregrasp_core.io.SensorOptions``: intrinsics,
    viewpoint, scene, pick), or ``None`` for its defaults."""


@dataclass(frozen=True)
class ViewState:
    """What the user looks at: selections, filters and the animation clock."""

    level: int | None = None
    """Number of accepted splits shown by the level slider; ``None`` = all of them (the leaves)."""
    selected_node: int | None = None
    """Node id picked by clicking its box, or ``None``."""
    show_face_masks: bool = True
    """Draw the free/blocked faces and the usable sub-faces on the shown boxes."""
    show_ghosts: bool = False
    """Draw (a capped subset of) the pre-grasp pool as translucent hand ghosts; off at start, so
    the first screen shows the object, its boxes and the best grasp."""
    show_hidden_space: bool = True
    """Draw the space hidden behind a single depth view when it was planned with ``--occluded
    occupied`` (``PipelineResult.occupied``; nothing to draw otherwise)."""
    ghost_type: str = ALL
    """Grasp-type filter of the ghosts (a ``GraspType`` value or :data:`ALL`)."""
    ghost_node: int | None = None
    """Node filter of the ghosts (a node id or ``None`` for every node)."""
    selected_grasp: int | None = None
    """Rank (0 = best) of the grasp shown with the URDF hand, or ``None``."""
    anim_t: float = 1.0
    """Animation phase in [0, 1]: 0 = pre-grasp pose in its preshape, 0.5 = end of the approach,
    1 = fingers closed on the contacts (where a played animation stops)."""
    playing: bool = False
    """Whether the animation clock advances by itself."""
    speed: float = 1.0
    """Animation speed: full cycles (pre-grasp to closed) per 2 seconds; a simulated lift
    plays at this many times real time."""
    show_lift: bool = False
    """Whether the scene shows the chosen grasp's simulated lift (``AppState.lift``) instead of
    its planned closing; the phase slider and choosing a grasp turn it off."""
    lift_t: float = 0.0
    """Playback clock of the shown lift: seconds of simulated time."""

    def for_new_object(self, **changes: Any) -> ViewState:
        """The view of a newly shown object: selections, filters and the clock reset, the
        user's layer toggles and animation speed kept; ``changes`` set other fields."""
        return ViewState(
            show_face_masks=self.show_face_masks,
            show_ghosts=self.show_ghosts,
            show_hidden_space=self.show_hidden_space,
            speed=self.speed,
            **changes,
        )


@dataclass(frozen=True)
class AppState:
    """Everything the app shows, as plain data. Replaced as a whole, never mutated."""

    source: ObjectSource | None = None
    """The loaded object, or ``None`` before the first load."""
    n_points: int = 20000
    """Number of points sampled on a mesh (point clouds keep at most this many)."""
    seed: int = 0
    """Seed of the mesh sampling (same seed, same cloud)."""
    params: Any = None
    """``pregrasp_core.pipeline.PipelineParams`` of the current run."""
    result: Any = None
    """``pregrasp_core.pipeline.PipelineResult`` (cloud, tree, shapes, masks, pool, grasps,
    timings) of the current run, or ``None`` before the first run."""
    planned: bool = False
    """Whether ``result`` holds planned grasps for the current thresholds."""
    replanning: bool = False
    """Whether a threshold change found planned grasps and plans them again for the new
    thresholds: a newer edit that cancels that re-plan plans again too (the grasps follow the
    last edit); a plan the user started and an edit cancelled is not restarted."""
    loaded: Any = None
    """The ``app.result_file.ResultFile`` shown (``result`` is its content, nothing recomputed),
    or ``None`` when ``result`` was computed here from ``source``."""
    compare: Any = None
    """A second ``ResultFile`` of the same object whose best grasps are drawn beside the
    current ones ("compare with"), or ``None``."""
    view: ViewState = field(default_factory=ViewState)
    """Selections, filters and the animation clock."""
    busy: str = ""
    """Name of the slow action in progress ("" when idle); the GUI disables its buttons."""
    progress: float = 0.0
    """Progress of ``busy`` in [0, 1]."""
    message: str = ""
    """The last status line (what was loaded or computed, and how long it took)."""
    camera: Any = None
    """The camera given in the Object panel for depth images (an
    ``pregrasp_core.sensor.Intrinsics`` typed there, or the ``CameraFile`` of an uploaded JSON):
    used by the next depth image uploaded, or ``None``."""
    waiting: ObjectSource | None = None
    """An uploaded depth image waiting for its intrinsics (the shown object stays meanwhile),
    or ``None``."""
    lift: Any = None
    """``app.simulate_view.LiftView``: the lift tests run on the current grasps (outcomes and
    the last recorded lift), or ``None``; stale (ignored) once the grasps change."""
    error: str = ""
    """The last error message shown to the user ("" after a successful action)."""
    version: int = 0
    """Incremented on every replacement of the state (lets tests and the GUI detect changes)."""

    @property
    def cloud(self) -> Any:
        """The current ``PointCloud`` or ``None``."""
        return None if self.result is None else self.result.cloud

    @property
    def tree(self) -> Any:
        """The current ``BoxTree`` or ``None``."""
        return None if self.result is None else self.result.tree

    @property
    def shown_level(self) -> int:
        """The level (number of accepted splits) whose boxes are shown."""
        tree = self.tree
        if tree is None:
            return 0
        n = n_splits(tree)
        return n if self.view.level is None else min(max(self.view.level, 0), n)

    def shown_nodes(self) -> list[int]:
        """Ids of the boxes shown at the current level (a cut of the tree)."""
        tree = self.tree
        if tree is None:
            return []
        return list(tree.cut_at_level(self.shown_level))


def n_splits(tree: Any) -> int:
    """Number of accepted splits of a ``BoxTree`` (``max split_order``)."""
    n = getattr(tree, "n_splits", None)
    if n is not None:
        return int(n() if callable(n) else n)
    return max(int(node.split_order) for node in tree.nodes)
