"""Simulated worlds: a floor with painted lines, walls, boxes, stop signs and rolling balls.

Load a shipped world by name, a world YAML file, or a ROS ``map_server`` map::

    >>> from qcarlab.sim.world import load_world, list_worlds
    >>> [name for name, _ in list_worlds()]
    ['hallway', 'obstacles', 'stop-sign', 'studio', 'track']
    >>> w = load_world("track")
    >>> w.start                                   # (x, y, yaw) of the car's centre
    >>> load_world("../shared/data/maps/berlin.yaml")   # ROS map: occupied cells become walls

World frame: X right, Y up, metres; angles in radians counter-clockwise from +X (a string such as
``"-90deg"`` is also accepted wherever an angle is asked for).

The world YAML format
---------------------
Every section except ``floor`` is optional. Colours are RGB: a name (``yellow``, ``white``,
``red``, ``green``, ``blue``, ``black``, ``gray``, ``darkgray``, ``lightgray``, ``orange``,
``brown``, ``asphalt``, ``wood``, ``concrete``), ``"#rrggbb"``, or ``[r, g, b]`` with 0-255 values.
Unknown keys are refused, so a typo is reported rather than ignored::

    name: my-room                 # optional (default: the file name)
    description: One line shown by the world listing.
    floor:
      size: [6.0, 6.0]            # width along X, height along Y (m)
      origin: [-3.0, -3.0]        # X, Y of the floor's lower-left corner (default: centred on 0, 0)
      color: concrete
    background: "#3c3c46"         # what the cameras see above the walls (default dark grey)
    start: [0.0, 0.0, -90deg]     # the car's centre x, y and yaw (or {x: .., y: .., yaw: ..})
    markings:                     # paint on the floor (drawn in order, later on top)
      - points: [[-1, 0], [1, 0]] # a polyline, at least 2 points
        width: 0.05               # m
        color: yellow
        dashed: false             # true = 0.3 m dashes with 0.2 m gaps, or dash: [paint, gap]
        closed: false             # true joins the last point to the first
      - rect: [-2, -0.5, 2, 0.5]  # instead of points: a filled area [x0, y0, x1, y1] ...
        color: asphalt            # (or `polygon: [[x, y], ...]` for any filled shape)
    regions:                      # areas lit differently (the sheet: light differs along the track)
      - rect: [0, 0, 3, 3]        # or polygon: [[x, y], ...]
        brightness: 0.6           # multiplies every colour seen there (1 = normal, > 1 brighter)
    walls:                        # polylines extruded to walls
      - points: [[-3, -3], [3, -3], [3, 3], [-3, 3]]
        closed: true
        thickness: 0.1            # m (default 0.1)
        height: 0.6               # m (default 0.6)
        color: white
    obstacles:                    # solid shapes standing on the floor
      - shape: box                # box | circle | polygon
        center: [1.0, 0.0]
        size: [0.4, 0.3]          # length along the box's own x, width along its y (m)
        yaw: 0.0                  # rad (default 0)
        height: 0.3               # m (default 0.3)
        color: brown
      - {shape: circle, center: [0, 1], radius: 0.1, height: 0.5, color: blue}
      - {shape: polygon, points: [[0, 0], [0.5, 0], [0.2, 0.4]], height: 0.2, color: green}
    signs:
      - type: stop                # the only sign type: red octagon, white border, on a post
        position: [2.0, -0.3]     # of the post on the floor
        facing: 180deg            # direction the sign's face looks (towards the cars that read it)
        size: 0.15                # across the flats of the octagon (m, default 0.15)
        height: 0.22              # of the octagon's centre above the floor (m, default 0.22)
    balls:                        # balls rolling in a straight line at constant speed
      - start: [3.0, 1.0]
        direction: -90deg         # heading of the motion
        speed: 1.0                # m/s
        radius: 0.12              # m (default 0.12)
        color: orange
        start_time: 0.0           # s; the ball waits at `start` until then (default 0)
        distance: 6.0             # m rolled before it stops (default: never stops)

A ROS ``map_server`` YAML (``image``, ``resolution``, ``origin``, ``negate``, ``occupied_thresh``,
``free_thresh``; the image a PGM or PNG next to it) loads as a world whose occupied cells are walls
(``wall_height``, default 0.5 m). It may also carry qcarlab's ``name``, ``description``, ``start``
and ``wall_height`` keys; without ``start`` the car starts on the free cell nearest (0, 0),
heading +X. The origin's yaw is ignored, as most ROS tools do.

The LIDAR scans the horizontal plane at its mount height (0.20 m): shapes lower than that are
invisible to it (as on the real car), while the cameras see everything.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import InputError
from qcarlab.yamlio import load_yaml

__all__ = [
    "Ball",
    "Circle",
    "COLORS",
    "Marking",
    "OccupancyGrid",
    "Region",
    "Sign",
    "Solid",
    "World",
    "WORLDS_DIR",
    "list_worlds",
    "load_world",
    "shipped_names",
    "world_from_dict",
]

WORLDS_DIR = Path(__file__).resolve().parents[1] / "worlds"

#: RGB colours by name (the YAML's colour names); stored internally as BGR.
COLORS: dict[str, tuple[int, int, int]] = {
    "yellow": (240, 200, 20),  # hue 50 deg: the lane's centre line
    "white": (235, 235, 235),
    "red": (200, 16, 16),  # hue 0: the stop sign (the sheet thresholds red at hue 0)
    "green": (40, 160, 60),
    "blue": (40, 80, 200),
    "black": (20, 20, 20),
    "gray": (128, 128, 128),
    "grey": (128, 128, 128),
    "darkgray": (70, 70, 70),
    "darkgrey": (70, 70, 70),
    "lightgray": (190, 190, 190),
    "lightgrey": (190, 190, 190),
    "orange": (240, 120, 20),
    "brown": (150, 105, 60),  # cardboard boxes
    "asphalt": (48, 48, 52),  # the road mat
    "wood": (170, 130, 90),
    "concrete": (150, 148, 142),
}

DEFAULT_FLOOR_COLOR = (150, 148, 142)
DEFAULT_BACKGROUND = (60, 60, 70)
DEFAULT_WALL_HEIGHT = 0.6
DEFAULT_WALL_THICKNESS = 0.1
DEFAULT_OBSTACLE_HEIGHT = 0.3
DEFAULT_ROS_WALL_HEIGHT = 0.5
DEFAULT_DASH = (0.3, 0.2)
STOP_SIGN_SIZE = 0.15  # m across the flats
STOP_SIGN_HEIGHT = 0.22  # m, centre above the floor
STOP_SIGN_POST_RADIUS = 0.012  # m
STOP_SIGN_BORDER = 0.1  # white border, as a fraction of the size
BALL_RADIUS = 0.12  # m


def _bgr(rgb: tuple[int, int, int]) -> tuple[int, int, int]:
    return (int(rgb[2]), int(rgb[1]), int(rgb[0]))


# --------------------------------------------------------------------------------------------
# the world's parts
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Marking:
    """Paint on the floor: a polyline of ``width`` (``filled=False``) or a filled polygon."""

    points: np.ndarray  # (n, 2)
    color: tuple[int, int, int]  # BGR
    width: float = 0.05
    dash: tuple[float, float] | None = None  # (paint, gap) lengths, None = solid
    closed: bool = False
    filled: bool = False


@dataclass(frozen=True, eq=False)
class Region:
    """A floor area lit differently: every colour seen there is multiplied by ``brightness``."""

    polygon: np.ndarray  # (n, 2)
    brightness: float


@dataclass(frozen=True, eq=False)
class Solid:
    """A vertical prism standing on the floor: a polygon (walls, boxes) or a circle (posts, pillars)."""

    kind: str  # "polygon" or "circle"
    height: float
    color: tuple[int, int, int]  # BGR
    points: np.ndarray | None = None  # (n, 2) for polygons, counter-clockwise or not
    center: tuple[float, float] | None = None  # circles
    radius: float = 0.0
    z0: float = 0.0  # bottom above the floor (sign plates float on their post)
    wall: bool = False


@dataclass(frozen=True)
class Sign:
    """A stop sign: a red octagon with a white border on a grey post."""

    kind: str
    x: float
    y: float
    facing: float  # rad: the direction the face looks
    size: float = STOP_SIGN_SIZE  # across the flats
    height: float = STOP_SIGN_HEIGHT  # centre above the floor
    post_radius: float = STOP_SIGN_POST_RADIUS

    @property
    def circumradius(self) -> float:
        return self.size / 2.0 / math.cos(math.pi / 8.0)

    @property
    def bottom(self) -> float:
        """Height of the octagon's lowest edge (the post ends there)."""
        return self.height - self.size / 2.0

    @property
    def plate_center(self) -> tuple[float, float, float]:
        """World (x, y, z) of the centre of the face (just in front of the post)."""
        d = self.post_radius + 0.005
        return (self.x + d * math.cos(self.facing), self.y + d * math.sin(self.facing), self.height)

    def corners(self, inset: float = 0.0) -> np.ndarray:
        """The octagon's corners in the world, (8, 3), counter-clockwise as seen from the front.

        ``inset`` shrinks the octagon by that many metres on every side (the red part inside the
        white border).
        """
        r = (self.size / 2.0 - inset) / math.cos(math.pi / 8.0)
        ang = math.pi / 8.0 + np.arange(8) * math.pi / 4.0
        # a viewer facing the sign looks along -facing; their right is facing turned +90 deg
        rx, ry = math.cos(self.facing + math.pi / 2.0), math.sin(self.facing + math.pi / 2.0)
        cx, cy, cz = self.plate_center
        right, up = r * np.cos(ang), r * np.sin(ang)
        return np.column_stack((cx + right * rx, cy + right * ry, cz + up))


@dataclass(frozen=True)
class Circle:
    """A ball at one instant (from :meth:`World.obstacles_at`): a sphere resting on the floor."""

    x: float
    y: float
    radius: float
    color: tuple[int, int, int]  # BGR


@dataclass(frozen=True)
class Ball:
    """A ball rolling from ``start`` along ``direction`` at ``speed`` (m/s), from ``start_time``."""

    start: tuple[float, float]
    direction: float
    speed: float
    radius: float = BALL_RADIUS
    color: tuple[int, int, int] = _bgr(COLORS["orange"])
    start_time: float = 0.0
    distance: float = math.inf  # m rolled before stopping

    def position(self, t: float) -> tuple[float, float]:
        s = min(max(t - self.start_time, 0.0) * self.speed, self.distance)
        return (self.start[0] + s * math.cos(self.direction), self.start[1] + s * math.sin(self.direction))


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """A ROS map as loaded: ``occupied``/``unknown`` (rows from the bottom, y up), cell size and origin."""

    occupied: np.ndarray  # bool (ny, nx); row 0 is the bottom edge (y = origin y)
    unknown: np.ndarray  # bool (ny, nx)
    resolution: float
    origin: tuple[float, float]
    wall_height: float = DEFAULT_ROS_WALL_HEIGHT
    wall_color: tuple[int, int, int] = _bgr(COLORS["lightgray"])

    @property
    def shape(self) -> tuple[int, int]:
        return self.occupied.shape  # type: ignore[return-value]

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the cell holding world point (x, y)."""
        return (
            int(math.floor((y - self.origin[1]) / self.resolution)),
            int(math.floor((x - self.origin[0]) / self.resolution)),
        )


@dataclass(eq=False)
class World:
    """Everything the simulated sensors see. Build it with :func:`load_world`."""

    name: str
    description: str = ""
    source: str = "<memory>"
    floor_size: tuple[float, float] = (6.0, 6.0)
    floor_origin: tuple[float, float] = (-3.0, -3.0)
    floor_color: tuple[int, int, int] = _bgr(DEFAULT_FLOOR_COLOR)
    background: tuple[int, int, int] = _bgr(DEFAULT_BACKGROUND)
    start: tuple[float, float, float] = (0.0, 0.0, -math.pi / 2.0)
    markings: list[Marking] = field(default_factory=list)
    regions: list[Region] = field(default_factory=list)
    solids: list[Solid] = field(default_factory=list)
    signs: list[Sign] = field(default_factory=list)
    balls: list[Ball] = field(default_factory=list)
    grid: OccupancyGrid | None = None
    params: QCarParams = DEFAULT_PARAMS
    _cache: dict[Any, Any] = field(default_factory=dict, repr=False, compare=False)

    def __getstate__(self) -> dict[str, Any]:
        """Pickled without ``_cache`` (the sensors' rasters, tens of MB, built again on demand):
        a world handed to another process (the recorder's, a grading worker) is its shapes."""
        state = self.__dict__.copy()
        state["_cache"] = {}
        return state

    # --- geometry -------------------------------------------------------------------------------
    def obstacles_at(self, t: float) -> list[Circle]:
        """The moving obstacles (balls) at time ``t`` (s)."""
        out = []
        for b in self.balls:
            x, y = b.position(t)
            out.append(Circle(x, y, b.radius, b.color))
        return out

    @property
    def floor_bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the floor."""
        x0, y0 = self.floor_origin
        return (x0, y0, x0 + self.floor_size[0], y0 + self.floor_size[1])

    @cached_property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) holding the floor and every static shape."""
        xs = [self.floor_bounds[0], self.floor_bounds[2]]
        ys = [self.floor_bounds[1], self.floor_bounds[3]]
        for s in self.solids:
            if s.kind == "polygon" and s.points is not None:
                xs += [float(s.points[:, 0].min()), float(s.points[:, 0].max())]
                ys += [float(s.points[:, 1].min()), float(s.points[:, 1].max())]
            elif s.center is not None:
                xs += [s.center[0] - s.radius, s.center[0] + s.radius]
                ys += [s.center[1] - s.radius, s.center[1] + s.radius]
        for g in self.signs:
            xs += [g.x - g.size, g.x + g.size]
            ys += [g.y - g.size, g.y + g.size]
        return (min(xs), min(ys), max(xs), max(ys))

    def add_box(
        self,
        x: float,
        y: float,
        length: float,
        width: float,
        yaw: float = 0.0,
        height: float = DEFAULT_OBSTACLE_HEIGHT,
        color: tuple[int, int, int] = _bgr(COLORS["brown"]),
    ) -> Solid:
        """Add a box (centre x, y; ``length`` along its yaw, ``width`` across; BGR colour).

        For tools that place a target in any world (``lidar-scan --target D``). The sensors built
        afterwards see it; sensors built before keep their precomputed rasters.
        """
        if not (length > 0 and width > 0 and height > 0):
            raise InputError(f"box: length, width and height must be positive, got {length}, {width}, {height}")
        solid = Solid("polygon", float(height), tuple(int(c) for c in color), points=_box(x, y, length, width, yaw))  # type: ignore[arg-type]
        self.solids.append(solid)
        self._cache.clear()
        self.__dict__.pop("bounds", None)
        return solid

    def static_solids(self) -> list[Solid]:
        """Every static shape the sensors can hit: walls, obstacles, sign posts and sign plates.

        A sign's plate is a thin box 5 mm thick, floating from ``sign.bottom`` to its top.
        """
        out = list(self.solids)
        for g in self.signs:
            out.append(Solid("circle", g.bottom, _bgr(COLORS["lightgray"]), center=(g.x, g.y), radius=g.post_radius))
            fx, fy = math.cos(g.facing), math.sin(g.facing)
            rx, ry = -fy, fx
            w = g.circumradius * math.cos(math.pi / 8.0)  # half across flats
            t = 0.0025
            cx, cy = g.x + fx * (g.post_radius + t), g.y + fy * (g.post_radius + t)
            pts = np.array(
                [
                    [cx - rx * w - fx * t, cy - ry * w - fy * t],
                    [cx + rx * w - fx * t, cy + ry * w - fy * t],
                    [cx + rx * w + fx * t, cy + ry * w + fy * t],
                    [cx - rx * w + fx * t, cy - ry * w + fy * t],
                ]
            )
            out.append(
                Solid("polygon", g.height + g.size / 2.0, _bgr(COLORS["red"]), points=pts, z0=g.bottom)
            )
        return out


# --------------------------------------------------------------------------------------------
# validation helpers: one line naming the file and the field
# --------------------------------------------------------------------------------------------
class _Ctx:
    def __init__(self, source: str):
        self.source = source

    def fail(self, where: str, msg: str) -> InputError:
        return InputError(f"{self.source}: {where}: {msg}" if where else f"{self.source}: {msg}")

    def mapping(self, value: Any, where: str, known: set[str], required: tuple[str, ...] = ()) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.fail(where, f"expected a mapping, got {_kind(value)}")
        for k in value:
            if k not in known:
                raise self.fail(f"{where}.{k}" if where else str(k), f"unknown field (known: {', '.join(sorted(known))})")
        for k in required:
            if k not in value:
                raise self.fail(f"{where}.{k}" if where else k, "missing (required)")
        return value

    def number(self, value: Any, where: str, positive: bool = False, nonneg: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            kind = "a positive number" if positive else "a non-negative number" if nonneg else "a number"
            raise self.fail(where, f"expected {kind}, got {value!r}")
        v = float(value)
        if positive and v <= 0.0:
            raise self.fail(where, f"expected a positive number, got {value!r}")
        if nonneg and v < 0.0:
            raise self.fail(where, f"expected a non-negative number, got {value!r}")
        return v

    def angle(self, value: Any, where: str) -> float:
        if isinstance(value, str):
            m = re.fullmatch(r"\s*([-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)\s*(deg|rad)?\s*", value)
            if not m:
                raise self.fail(where, f"expected an angle in radians or like '90deg', got {value!r}")
            v = float(m.group(1))
            return math.radians(v) if m.group(2) == "deg" else v
        return self.number(value, where)

    def point(self, value: Any, where: str) -> tuple[float, float]:
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise self.fail(where, f"expected [x, y], got {value!r}")
        return (self.number(value[0], f"{where}[0]"), self.number(value[1], f"{where}[1]"))

    def points(self, value: Any, where: str, minimum: int) -> np.ndarray:
        if not isinstance(value, (list, tuple)) or len(value) < minimum:
            raise self.fail(where, f"expected a list of at least {minimum} [x, y] points, got {_short(value)}")
        return np.array([self.point(p, f"{where}[{i}]") for i, p in enumerate(value)], dtype=float)

    def rect(self, value: Any, where: str) -> np.ndarray:
        if not isinstance(value, (list, tuple)) or len(value) != 4:
            raise self.fail(where, f"expected [x0, y0, x1, y1], got {_short(value)}")
        x0, y0, x1, y1 = (self.number(v, f"{where}[{i}]") for i, v in enumerate(value))
        if x1 <= x0 or y1 <= y0:
            raise self.fail(where, "expected x1 > x0 and y1 > y0")
        return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)

    def color(self, value: Any, where: str) -> tuple[int, int, int]:
        if isinstance(value, str):
            s = value.strip().lower()
            if s in COLORS:
                return _bgr(COLORS[s])
            m = re.fullmatch(r"#([0-9a-f]{6})", s)
            if m:
                h = m.group(1)
                return _bgr((int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16)))
            raise self.fail(where, f"unknown colour {value!r} (a name such as {', '.join(list(COLORS)[:6])}, '#rrggbb' or [r, g, b])")
        if isinstance(value, (list, tuple)) and len(value) == 3:
            rgb = []
            for i, c in enumerate(value):
                if isinstance(c, bool) or not isinstance(c, (int, float)) or not 0 <= c <= 255:
                    raise self.fail(f"{where}[{i}]", f"expected a number 0-255, got {c!r}")
                rgb.append(int(round(c)))
            return _bgr((rgb[0], rgb[1], rgb[2]))
        raise self.fail(where, f"expected a colour name, '#rrggbb' or [r, g, b], got {_short(value)}")

    def boolean(self, value: Any, where: str) -> bool:
        if not isinstance(value, bool):
            raise self.fail(where, f"expected true or false, got {value!r}")
        return value

    def text(self, value: Any, where: str) -> str:
        if not isinstance(value, str):
            raise self.fail(where, f"expected text, got {_kind(value)}")
        return value

    def items(self, value: Any, where: str) -> list[Any]:
        if value is None:
            return []
        if not isinstance(value, list):
            raise self.fail(where, f"expected a list, got {_kind(value)}")
        return value


def _kind(value: Any) -> str:
    return {dict: "a mapping", list: "a list", str: "text", type(None): "nothing"}.get(type(value), type(value).__name__)


def _short(value: Any) -> str:
    s = repr(value)
    return s if len(s) <= 40 else s[:37] + "..."


# --------------------------------------------------------------------------------------------
# parsing
# --------------------------------------------------------------------------------------------
_TOP_KEYS = {"name", "description", "floor", "background", "start", "markings", "regions", "walls", "obstacles", "signs", "balls"}
_ROS_KEYS = {"image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh", "mode", "name", "description", "start", "wall_height"}


def _parse_start(c: _Ctx, value: Any) -> tuple[float, float, float]:
    if isinstance(value, dict):
        m = c.mapping(value, "start", {"x", "y", "yaw"}, ("x", "y"))
        return (c.number(m["x"], "start.x"), c.number(m["y"], "start.y"), c.angle(m.get("yaw", 0.0), "start.yaw"))
    if isinstance(value, (list, tuple)) and len(value) in (2, 3):
        yaw = c.angle(value[2], "start[2]") if len(value) == 3 else 0.0
        return (c.number(value[0], "start[0]"), c.number(value[1], "start[1]"), yaw)
    raise c.fail("start", f"expected [x, y, yaw] or {{x: .., y: .., yaw: ..}}, got {_short(value)}")


def _parse_world(data: Any, c: _Ctx, name: str, params: QCarParams) -> World:
    top = c.mapping(data, "", _TOP_KEYS, ("floor",))
    floor = c.mapping(top["floor"], "floor", {"size", "origin", "color"}, ("size",))
    size = c.point(floor["size"], "floor.size")
    if size[0] <= 0 or size[1] <= 0:
        raise c.fail("floor.size", f"expected two positive numbers, got {floor['size']!r}")
    origin = c.point(floor["origin"], "floor.origin") if "origin" in floor else (-size[0] / 2.0, -size[1] / 2.0)
    w = World(
        name=c.text(top.get("name", name), "name"),
        description=c.text(top.get("description", ""), "description"),
        source=c.source,
        floor_size=size,
        floor_origin=origin,
        floor_color=c.color(floor.get("color", list(DEFAULT_FLOOR_COLOR)), "floor.color"),
        background=c.color(top.get("background", list(DEFAULT_BACKGROUND)), "background"),
        start=_parse_start(c, top["start"]) if "start" in top else (0.0, 0.0, -math.pi / 2.0),
        params=params,
    )

    for i, item in enumerate(c.items(top.get("markings"), "markings")):
        where = f"markings[{i}]"
        m = c.mapping(item, where, {"points", "rect", "polygon", "width", "color", "dashed", "dash", "closed"})
        shapes = [k for k in ("points", "rect", "polygon") if k in m]
        if len(shapes) != 1:
            raise c.fail(where, "expected exactly one of points (a line), rect or polygon (a filled area)")
        color = c.color(m.get("color", "white"), f"{where}.color")
        if shapes[0] == "points":
            pts = c.points(m["points"], f"{where}.points", 2)
            dash = None
            if "dash" in m:
                d = c.point(m["dash"], f"{where}.dash")
                if d[0] <= 0 or d[1] <= 0:
                    raise c.fail(f"{where}.dash", "expected two positive lengths [paint, gap]")
                dash = d
            elif c.boolean(m.get("dashed", False), f"{where}.dashed"):
                dash = DEFAULT_DASH
            w.markings.append(
                Marking(
                    pts,
                    color,
                    width=c.number(m.get("width", 0.05), f"{where}.width", positive=True),
                    dash=dash,
                    closed=c.boolean(m.get("closed", False), f"{where}.closed"),
                )
            )
        else:
            for k in ("width", "dashed", "dash", "closed"):
                if k in m:
                    raise c.fail(f"{where}.{k}", f"only for line markings (with points), not with {shapes[0]}")
            pts = c.rect(m["rect"], f"{where}.rect") if shapes[0] == "rect" else c.points(m["polygon"], f"{where}.polygon", 3)
            w.markings.append(Marking(pts, color, filled=True))

    for i, item in enumerate(c.items(top.get("regions"), "regions")):
        where = f"regions[{i}]"
        m = c.mapping(item, where, {"rect", "polygon", "brightness"}, ("brightness",))
        if ("rect" in m) == ("polygon" in m):
            raise c.fail(where, "expected exactly one of rect or polygon")
        pts = c.rect(m["rect"], f"{where}.rect") if "rect" in m else c.points(m["polygon"], f"{where}.polygon", 3)
        w.regions.append(Region(pts, c.number(m["brightness"], f"{where}.brightness", positive=True)))

    for i, item in enumerate(c.items(top.get("walls"), "walls")):
        where = f"walls[{i}]"
        m = c.mapping(item, where, {"points", "closed", "thickness", "height", "color"}, ("points",))
        pts = c.points(m["points"], f"{where}.points", 2)
        thick = c.number(m.get("thickness", DEFAULT_WALL_THICKNESS), f"{where}.thickness", positive=True)
        height = c.number(m.get("height", DEFAULT_WALL_HEIGHT), f"{where}.height", positive=True)
        color = c.color(m.get("color", "white"), f"{where}.color")
        closed = c.boolean(m.get("closed", False), f"{where}.closed")
        segs = list(zip(pts[:-1], pts[1:]))
        if closed and len(pts) > 2:
            segs.append((pts[-1], pts[0]))
        for j, (a, b) in enumerate(segs):
            if float(np.hypot(*(b - a))) < 1e-9:
                raise c.fail(f"{where}.points[{j + 1}]", "repeats the previous point")
            w.solids.append(Solid("polygon", height, color, points=_thick_segment(a, b, thick), wall=True))

    for i, item in enumerate(c.items(top.get("obstacles"), "obstacles")):
        where = f"obstacles[{i}]"
        m = c.mapping(item, where, {"shape", "center", "size", "yaw", "radius", "points", "height", "color"}, ("shape",))
        shape = m["shape"]
        height = c.number(m.get("height", DEFAULT_OBSTACLE_HEIGHT), f"{where}.height", positive=True)
        color = c.color(m.get("color", "brown"), f"{where}.color")
        allowed = {"box": {"center", "size", "yaw"}, "circle": {"center", "radius"}, "polygon": {"points"}}
        if shape not in allowed:
            raise c.fail(f"{where}.shape", f"unknown shape {shape!r} (box, circle or polygon)")
        for k in m:
            if k not in allowed[shape] | {"shape", "height", "color"}:
                raise c.fail(f"{where}.{k}", f"not a field of a {shape} (it has {', '.join(sorted(allowed[shape]))})")
        for k in sorted(allowed[shape] - {"yaw"}):
            if k not in m:
                raise c.fail(f"{where}.{k}", f"missing (required for a {shape})")
        if shape == "box":
            cx, cy = c.point(m["center"], f"{where}.center")
            lw = c.point(m["size"], f"{where}.size")
            if lw[0] <= 0 or lw[1] <= 0:
                raise c.fail(f"{where}.size", f"expected two positive numbers, got {m['size']!r}")
            yaw = c.angle(m.get("yaw", 0.0), f"{where}.yaw")
            w.solids.append(Solid("polygon", height, color, points=_box(cx, cy, lw[0], lw[1], yaw)))
        elif shape == "circle":
            center = c.point(m["center"], f"{where}.center")
            r = c.number(m["radius"], f"{where}.radius", positive=True)
            w.solids.append(Solid("circle", height, color, center=center, radius=r))
        else:
            pts = c.points(m["points"], f"{where}.points", 3)
            w.solids.append(Solid("polygon", height, color, points=pts))

    for i, item in enumerate(c.items(top.get("signs"), "signs")):
        where = f"signs[{i}]"
        m = c.mapping(item, where, {"type", "position", "facing", "size", "height"}, ("type", "position", "facing"))
        if m["type"] != "stop":
            raise c.fail(f"{where}.type", f"unknown sign type {m['type']!r} (stop)")
        x, y = c.point(m["position"], f"{where}.position")
        size = c.number(m.get("size", STOP_SIGN_SIZE), f"{where}.size", positive=True)
        height = c.number(m.get("height", STOP_SIGN_HEIGHT), f"{where}.height", positive=True)
        if height <= size / 2.0:
            raise c.fail(f"{where}.height", f"the sign's centre must be higher than half its size ({size / 2:g} m)")
        w.signs.append(Sign("stop", x, y, c.angle(m["facing"], f"{where}.facing"), size, height))

    for i, item in enumerate(c.items(top.get("balls"), "balls")):
        where = f"balls[{i}]"
        m = c.mapping(item, where, {"start", "direction", "speed", "radius", "color", "start_time", "distance"}, ("start", "direction", "speed"))
        w.balls.append(
            Ball(
                start=c.point(m["start"], f"{where}.start"),
                direction=c.angle(m["direction"], f"{where}.direction"),
                speed=c.number(m["speed"], f"{where}.speed", nonneg=True),
                radius=c.number(m.get("radius", BALL_RADIUS), f"{where}.radius", positive=True),
                color=c.color(m.get("color", "orange"), f"{where}.color"),
                start_time=c.number(m.get("start_time", 0.0), f"{where}.start_time", nonneg=True),
                distance=c.number(m["distance"], f"{where}.distance", nonneg=True) if "distance" in m else math.inf,
            )
        )
    return w


def _thick_segment(a: np.ndarray, b: np.ndarray, thickness: float) -> np.ndarray:
    """The rectangle of a wall segment a-b, extended by half the thickness at both ends (closed corners)."""
    d = (b - a) / float(np.hypot(*(b - a)))
    n = np.array([-d[1], d[0]])
    h = thickness / 2.0
    a2, b2 = a - d * h, b + d * h
    return np.array([a2 + n * h, a2 - n * h, b2 - n * h, b2 + n * h])


def _box(cx: float, cy: float, length: float, width: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=float) * [length / 2.0, width / 2.0]
    return np.column_stack((cx + local[:, 0] * c - local[:, 1] * s, cy + local[:, 0] * s + local[:, 1] * c))


def _load_ros(data: dict[str, Any], c: _Ctx, path: Path, params: QCarParams) -> World:
    import cv2

    m = c.mapping(data, "", _ROS_KEYS, ("image", "resolution", "origin"))
    image = c.text(m["image"], "image")
    res = c.number(m["resolution"], "resolution", positive=True)
    origin = m["origin"]
    if not isinstance(origin, (list, tuple)) or len(origin) not in (2, 3):
        raise c.fail("origin", f"expected [x, y, yaw], got {_short(origin)}")
    ox = c.number(origin[0], "origin[0]")
    oy = c.number(origin[1], "origin[1]")
    negate = m.get("negate", 0)
    if negate not in (0, 1, True, False):
        raise c.fail("negate", f"expected 0 or 1, got {negate!r}")
    occ_t = c.number(m.get("occupied_thresh", 0.65), "occupied_thresh")
    free_t = c.number(m.get("free_thresh", 0.196), "free_thresh")
    if not 0.0 <= free_t <= occ_t <= 1.0:
        raise c.fail("free_thresh", f"expected 0 <= free_thresh ({free_t}) <= occupied_thresh ({occ_t}) <= 1")
    mode = m.get("mode", "trinary")
    if mode not in ("trinary", "scale", "raw"):
        raise c.fail("mode", f"expected trinary, scale or raw, got {mode!r}")
    img_path = (path.parent / image) if not Path(image).is_absolute() else Path(image)
    img = None
    if img_path.is_file():
        from qcarlab.media import check_image_size

        data = np.fromfile(str(img_path), np.uint8)
        try:
            check_image_size(data, img_path)
        except InputError as exc:
            raise c.fail("image", str(exc)) from None
        img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
    if img is None:
        raise c.fail("image", f"cannot read map image '{image}' (looked for {img_path})")
    if mode == "raw":
        occ = img.astype(np.float32) / 100.0  # raw: pixel values are occupancy in percent
    else:
        occ = (255.0 - img.astype(np.float32)) / 255.0 if not negate else img.astype(np.float32) / 255.0
    occupied = occ > occ_t
    unknown = ~occupied & ~(occ < free_t)
    occupied = np.ascontiguousarray(occupied[::-1])  # image row 0 is the top; grid row 0 the bottom
    unknown = np.ascontiguousarray(unknown[::-1])
    wall_h = c.number(m.get("wall_height", DEFAULT_ROS_WALL_HEIGHT), "wall_height", positive=True)
    grid = OccupancyGrid(occupied, unknown, res, (ox, oy), wall_h)
    ny, nx = occupied.shape
    w = World(
        name=c.text(m.get("name", path.stem), "name"),
        description=c.text(m.get("description", f"ROS map {path.name} ({nx}x{ny} cells of {res:g} m)"), "description"),
        source=c.source,
        floor_size=(nx * res, ny * res),
        floor_origin=(ox, oy),
        floor_color=_bgr(COLORS["concrete"]),
        grid=grid,
        params=params,
    )
    w.start = _parse_start(c, m["start"]) if "start" in m else _free_start(grid)
    return w


def _free_start(grid: OccupancyGrid) -> tuple[float, float, float]:
    """The centre of the free cell nearest (0, 0) (well clear of walls when possible), heading +X."""
    import cv2

    free = (~grid.occupied & ~grid.unknown).astype(np.uint8)
    if not free.any():
        return (0.0, 0.0, 0.0)
    clear = cv2.distanceTransform(free, cv2.DIST_L2, 5) * grid.resolution
    ok = clear >= min(0.3, float(clear.max()))  # at least 0.3 m from any wall when there is room
    rows, cols = np.nonzero(ok)
    xs = grid.origin[0] + (cols + 0.5) * grid.resolution
    ys = grid.origin[1] + (rows + 0.5) * grid.resolution
    k = int(np.argmin(xs * xs + ys * ys))
    return (float(xs[k]), float(ys[k]), 0.0)


def _read_yaml(path: Path) -> Any:
    return load_yaml(path, "world file")


def _shipped() -> dict[str, Path]:
    return {p.stem: p for p in sorted(WORLDS_DIR.glob("*.yaml"))}


def shipped_names() -> list[str]:
    """The shipped worlds' names (without reading them)."""
    return list(_shipped())


def list_worlds() -> list[tuple[str, str]]:
    """The shipped worlds as (name, description), sorted by name."""
    out = []
    for name, p in _shipped().items():
        try:
            data = _read_yaml(p)
            desc = data.get("description", "") if isinstance(data, dict) else ""
        except InputError:
            desc = "(unreadable)"
        out.append((name, str(desc).strip()))
    return out


def world_from_dict(data: Any, name: str = "world", source: str = "<dict>", params: QCarParams = DEFAULT_PARAMS) -> World:
    """A world from an already parsed mapping in the YAML format (errors name ``source``)."""
    c = _Ctx(source)
    if not isinstance(data, dict):
        raise c.fail("", f"expected a world (a mapping with at least 'floor'), got {_kind(data)}")
    return _parse_world(data, c, name, params)


def load_world(name_or_path: str | Path | World, params: QCarParams = DEFAULT_PARAMS) -> World:
    """A shipped world by name, a world YAML file, or a ROS map_server YAML (occupied cells = walls).

    Raises :class:`InputError` with one line naming the file and the field for bad files, and
    listing the shipped names for an unknown name.
    """
    if isinstance(name_or_path, World):
        return name_or_path
    shipped = _shipped()
    key = str(name_or_path)
    if key in shipped:
        path = shipped[key]
        source = f"worlds/{path.name}"
    else:
        path = Path(key).expanduser()
        source = str(path)
        if not path.is_file():
            if path.suffix.lower() in (".yaml", ".yml") or "/" in key or "\\" in key:
                raise InputError(f"{key}: no such world file")
            raise InputError(f"unknown world {key!r} (shipped: {', '.join(shipped)}; or give a world or ROS map YAML file)")
    data = _read_yaml(path)
    c = _Ctx(source)
    if isinstance(data, dict) and "image" in data and "resolution" in data:
        return _load_ros(data, c, path, params)
    if not isinstance(data, dict):
        raise c.fail("", f"expected a world (a mapping with at least 'floor'), got {_kind(data)}")
    return _parse_world(data, c, path.stem, params)

