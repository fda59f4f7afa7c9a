"""What the subcommands share: the input file's options and the pipeline's options by stage.

Every option is generated from a dataclass and its field docstrings (:mod:`app.commands.options`):
the input from :class:`InputOptions`, the pipeline from the core's parameter dataclasses, one
``--help`` group per stage (:data:`STAGE_OPTIONS`). ``decompose``, ``pregrasps``, ``plan`` and
``view`` take the options of their stages from this one definition (:func:`pipeline_options`).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pregrasp_core.decomposition import DecompositionParams
from pregrasp_core.facemask import FaceMaskParams
from pregrasp_core.io import (
    DEFAULT_N_POINTS,
    MAX_POINTS,
    MIN_POINTS,
    SCENE_OBSTACLES,
    SUPPORTED_EXTENSIONS,
    PointCloud,
    SensorOptions,
    load_point_cloud,
)
from pregrasp_core.io.depth_image import DEPTH_IMAGE_EXTENSIONS
from pregrasp_core.limits import MAX_SCALE, MIN_SCALE, check_real
from pregrasp_core.normals import ORIENT_MODES, NormalParams
from pregrasp_core.paths import DEFAULT_OBJECT
from pregrasp_core.pipeline import PipelineParams
from pregrasp_core.planner import PlannerParams
from pregrasp_core.pregrasps import SamplingParams
from pregrasp_core.quality import TORQUE_ORIGINS, QualityParams
from pregrasp_core.sensor.occluded import OCCLUDED_MODES
from pregrasp_core.shape import ShapeParams

from .options import Flag, OptionError, Options

# ---------------------------------------------------------------------------------- input


@dataclass(frozen=True)
class InputOptions:
    """How the input file becomes a cloud (the options of ``load_point_cloud``)."""

    points: int = DEFAULT_N_POINTS
    """Points sampled on a mesh / kept of a cloud."""
    seed: int = 0
    """Sampling seed (>= 0); the same seed gives the same cloud."""
    scale: float | None = None
    """Multiply the coordinates by this, e.g. 0.001 for a file in millimetres; None: a cloud
    whose size and spacing say millimetres is scaled by 0.001 with a warning."""
    intrinsics: tuple[str, ...] | None = None
    """A depth image's pinhole intrinsics: four numbers FX FY CX CY (pixels) or a JSON file;
    default: NAME.json beside NAME.png / NAME.npy (an NPY is a depth map only with them)."""
    pick: tuple[float, float, float] | None = None
    """In a scene, keep the object cluster nearest this point (metres) instead of the largest."""
    scene: bool | None = None
    """Read the input as a scene: the table found by RANSAC becomes the support plane, the
    object cluster is kept and, for a single view (a viewpoint known), its unseen back
    completed; without a viewpoint, a complete scene (a scan or mesh with its table: the object
    kept whole). Default: for depth images and PCD files with a VIEWPOINT; --no-scene reads
    every point as the object."""
    viewpoint: tuple[float, float, float] | None = None
    """The camera position (from --viewpoint, shared with the normals' option)."""
    flying_pixels: bool = False
    """In a scene, drop the flying pixels first: points strung along the camera's rays between
    an edge and what lies behind it, as time-of-flight cameras give them (docs/input.md)."""
    scene_obstacles: str = "all"
    """In a scene, what of the rest the hand must clear: all (the other objects, walls and, for
    a single view, the space hidden behind the other objects), seen (their seen points only:
    more grasps in dense clutter, but a hand may pass through a neighbour's unseen back) or off
    (the object alone) (docs/input.md)."""

    def __post_init__(self) -> None:
        if not MIN_POINTS <= self.points <= MAX_POINTS:
            raise ValueError(f"points must be in [{MIN_POINTS}, {MAX_POINTS}], got {self.points}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.scale is not None:
            check_real("scale", self.scale, MIN_SCALE, MAX_SCALE, what="a positive factor")

        if self.intrinsics is not None and len(self.intrinsics) not in (1, 4):
            raise OptionError(
                "--intrinsics: give four numbers FX FY CX CY or one JSON file, got "
                f"{' '.join(self.intrinsics)}"
            )

    def sensor(self) -> SensorOptions:
        """The depth-camera options of ``load_point_cloud``."""
        intr: tuple[float, ...] | str | None = None
        if self.intrinsics is not None and len(self.intrinsics) == 1:
            intr = self.intrinsics[0]
        elif self.intrinsics is not None:
            try:
                intr = tuple(float(v) for v in self.intrinsics)
            except ValueError:
                raise OptionError(
                    f"--intrinsics: give four numbers FX FY CX CY or one JSON file, got "
                    f"{' '.join(self.intrinsics)}"
                ) from None
        return SensorOptions(
            intrinsics=intr,
            viewpoint=self.viewpoint,
            scene=self.scene,
            pick=self.pick,
            flying_pixels=self.flying_pixels,
            obstacles=self.scene_obstacles,
        )

    def load(self, path: str | Path) -> PointCloud:
        """The cloud of the file at ``path`` (``PregraspError`` naming the file if unreadable)."""
        return load_point_cloud(
            path, n_points=self.points, seed=self.seed, scale=self.scale, sensor=self.sensor()
        )


class _InputSpec(Options[InputOptions]):
    """The generated ``--points``, ``--seed``, ``--scale``, ``--pick``, plus ``--intrinsics``
    (one JSON file or four numbers: no dataclass type says that), ``--scene`` / ``--no-scene``
    (unset by default) and the normals' ``--viewpoint`` read back for the loader."""

    def add_to(
        self, parser: argparse.ArgumentParser, group: argparse._ArgumentGroup | None = None
    ) -> None:
        g = group if group is not None else parser.add_argument_group(self.title)
        super().add_to(parser, g)
        g.add_argument(
            "--intrinsics",
            dest=self._key("intrinsics"),
            nargs="+",
            metavar="V",
            default=None,
            help=" ".join(self._docs["intrinsics"].split()),
        )
        g.add_argument(
            "--scene",
            dest=self._key("scene"),
            action=argparse.BooleanOptionalAction,
            default=None,
            help=" ".join(self._docs["scene"].split()),
        )

    def values(self, ns: argparse.Namespace) -> dict[str, Any]:
        out = super().values(ns)
        for name in ("intrinsics", "scene"):
            v = getattr(ns, self._key(name), None)
            out[name] = tuple(v) if isinstance(v, list) else v
        vp = getattr(ns, "planner.normals.viewpoint", None)
        out["viewpoint"] = None if vp is None else tuple(vp)
        return out


INPUT_OPTIONS: Options[InputOptions] = _InputSpec(
    InputOptions,
    "input",
    "input",
    flags={
        "points": Flag(metavar="N"),
        "seed": Flag(metavar="S"),
        "scale": Flag(metavar="F"),
        "pick": Flag(metavar=("X", "Y", "Z")),
        "flying_pixels": Flag(store_true=True),
        "scene_obstacles": Flag(choices=SCENE_OBSTACLES),
    },
    fields=("points", "seed", "scale", "pick", "flying_pixels", "scene_obstacles"),
)
"""``--points``, ``--seed``, ``--scale``, ``--intrinsics``, ``--pick``, ``--flying-pixels``,
``--scene-obstacles``, ``--scene`` (after the
positional INPUT of :func:`add_input_args`)."""

FORMATS = ", ".join(e.lstrip(".").upper() for e in (*SUPPORTED_EXTENSIONS, *DEPTH_IMAGE_EXTENSIONS))


def add_input_args(
    p: argparse.ArgumentParser, required: bool = True, what: str = "point cloud or mesh file"
) -> None:
    """INPUT (a point-cloud or mesh file; optional when ``required`` is False, then the default
    object) and the options of :class:`InputOptions`, in one group."""
    g = p.add_argument_group("input")
    if required:
        g.add_argument("input", metavar="INPUT", help=f"{what} ({FORMATS})")
    else:
        g.add_argument(
            "input",
            metavar="INPUT",
            nargs="?",
            default=None,
            help=f"{what} (default: {DEFAULT_OBJECT.name})",
        )
    INPUT_OPTIONS.add_to(p, g)


def input_path(args: argparse.Namespace) -> str:
    """The input file of ``args`` (the default object when INPUT was optional and omitted)."""
    return str(DEFAULT_OBJECT if args.input is None else args.input)


# ------------------------------------------------------------------------------ pipeline

STAGE_OPTIONS: dict[str, Options[Any]] = {
    "decomposition": Options(
        DecompositionParams,
        "decomposition",
        "decomposition",
        flags={
            "volume_ratio": Flag(metavar="R"),
            "min_points": Flag(metavar="M"),
            "max_depth": Flag(metavar="D"),
        },
    ),
    "shape": Options(
        ShapeParams,
        "shape classes (PCA)",
        "shape",
        flags={
            "max_ratio_1d": Flag("--ratio-1d", "A"),
            "max_ratio_2d": Flag("--ratio-2d", "B"),
            "small_size": Flag(metavar="METRES"),
        },
    ),
    "facemask": Options(
        FaceMaskParams,
        "face masks and support plane",
        "facemask",
        flags={"clearance": Flag("--face-clearance"), "support_height": Flag(metavar="Z")},
    ),
    "sampling": Options(SamplingParams, "traversal and sampling", "sampling"),
    "planner": Options(
        PlannerParams,
        "planner",
        "planner",
        flags={
            "approach_clearance": Flag("--clearance", "D"),
            "max_approach": Flag(metavar="D"),
            "max_lift": Flag(metavar="D"),
            "closing_margin": Flag(metavar="D"),
            "slice_resolution": Flag(metavar="D"),
            "contact_distance": Flag(metavar="D"),
            "penetration_tol": Flag(metavar="D"),
            "assumed_clearance": Flag(metavar="D"),
            "threads": Flag(metavar="T"),
        },
        nested={
            "quality": Options(
                QualityParams,
                "grasp quality (Ferrari-Canny epsilon)",
                "planner.quality",
                flags={
                    "mu": Flag(metavar="MU"),
                    "n_edges": Flag("--cone-edges", "M"),
                    "torque_scale": Flag(metavar="RHO"),
                    "torque_origin": Flag(choices=TORQUE_ORIGINS),
                },
            ),
            "normals": Options(
                NormalParams,
                "cloud normals",
                "planner.normals",
                flags={
                    "k": Flag("--normals-k", "K"),
                    "orient": Flag(
                        "--normals-orient",
                        choices=ORIENT_MODES,
                        help="How the normals are turned outwards: reference = agree with the "
                        "normals the file carries (a mesh's faces), viewpoint = face the camera "
                        "at --viewpoint (a single view), visibility = the side seen from many "
                        "directions around the cloud (thin walls, concave shapes), propagate = "
                        "along a minimum spanning tree over the neighbours, centroid = away "
                        "from the centroid, auto = reference when the cloud has normals, else "
                        "viewpoint when --viewpoint is given, else visibility.",
                    ),
                    "viewpoint": Flag(metavar=("X", "Y", "Z")),
                    "n_views": Flag("--normals-views", "N"),
                },
            ),
        },
    ),
}
"""The options of each stage's parameters, keyed by the ``PipelineParams`` field."""

POOL_STAGES: tuple[str, ...] = ("decomposition", "shape", "facemask", "sampling")
"""The stages up to the pre-grasp pool (``pregrasp pregrasps``)."""

ALL_STAGES: tuple[str, ...] = (*POOL_STAGES, "planner")
"""Every stage (``pregrasp plan`` and ``pregrasp view``)."""


def pipeline_options(stages: tuple[str, ...]) -> Options[PipelineParams]:
    """The options of ``PipelineParams`` for ``stages`` (the others keep their defaults)."""
    return Options(
        PipelineParams,
        "single views (depth camera)",
        "pipeline",
        flags={"occluded": Flag(choices=OCCLUDED_MODES)},
        fields=("occluded",) if "planner" in stages else (),  # plan and view
        nested={s: STAGE_OPTIONS[s] for s in stages},
    )
