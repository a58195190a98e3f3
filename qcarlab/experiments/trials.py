"""Trials, as the race-car report measured its avoidance: N seeded runs of a lab, each with a
randomised start pose, obstacle placements and (for a rolling ball) start time; the success rate,
the collisions and where they happened, and one figure overlaying every run.

    qcarlab avoid --world hallway --trials 20 --speed 0.5 --out runs/ball
    qcarlab stop-sign --trials 10 --json
    qcarlab lane-follow --trials 5 --duration 20

    from qcarlab.experiments.trials import AVOID, run_trials
    result = run_trials("avoid", world, lambda car, w, wrap: avoid(car, cfg, world=w, wrap=wrap),
                        n=10, seed=0, spec=AVOID)
    result.metrics["success_rate"]

What a trial changes, each drawn uniformly from a generator seeded by ``(seed, trial)`` (the same
command gives the same trials; trial ``i`` runs the simulator with seed ``seed + i``):

- **the start pose**: moved up to ``start_along`` m along the world's start heading and up to
  ``start_across`` m across it, and turned up to ``start_yaw`` rad; with ``along_path`` (a
  polyline such as the lane centre) anywhere along the path instead, heading along it. A pose
  whose footprint comes within ``MIN_START_CLEARANCE`` (5 cm) of a solid is drawn again;
- **free-standing obstacles** (solids that are not walls and are lower than 1 m: the boxes, the
  hallway's bin; doors and walls stay): moved up to ``obstacle_xy`` m in x and in y, turned up to
  ``obstacle_yaw`` rad about their centre;
- **stop signs**: moved up to ``sign_along`` m along the road (their facing);
- **balls**: rolled at the car when its centre first comes within ``launch_distance`` m of the
  ball (a distance drawn from the range), as the report's team rolled theirs from about 5 m; the
  moment is the ball's start time (``ball_start_s`` per trial). Its speed is drawn from
  ``ball_speed``, its start moved up to ``ball_across`` m across its direction and the direction
  turned up to ``ball_direction`` rad. It rolls until it meets a wall.

A trial succeeds when its run reached the lab's goal (avoid: no collision; stop-sign: came to rest
before the sign; lane-follow: stayed in its lane) and, in a world with balls, every ball met the
car and rolled by: the encounter is over once the ball is 1 m farther from the car than at their
closest approach, and the run then ends 1 s later. A car that never comes within the launch
distance, or stands while the ball waits, fails ("did not meet the ball").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from qcarlab.car.base import Car
from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import InputError
from qcarlab.experiments.loop import STOP
from qcarlab.experiments.result import Result, save_figure
from qcarlab.experiments.safety import Clearance

__all__ = ["AVOID", "LANE_FOLLOW", "STOP_SIGN", "Randomise", "TrialWorld", "randomise_world", "run_trials",
           "trials_figure"]

MIN_START_CLEARANCE = 0.05  # m between the car's footprint and any solid at the start
MOVABLE_HEIGHT = 1.0  # m: solids lower than this (and not walls) are moved between trials
ENCOUNTER_MARGIN = 1.0  # m past the closest approach that ends a ball's encounter
AFTER_ENCOUNTER = 1.0  # s the run goes on after the last encounter
MAX_TRIALS = 1000
#: Each lab's own measure of a run, summarised over the trials (name in the run's metrics, label).
KEY_METRIC = {"avoid": ("min_clearance_m", "clearance"),
              "stop-sign": ("stop_distance_m", "stopped at"),
              "lane-follow": ("rms_lateral_deviation_m", "RMS off lane")}


@dataclass(frozen=True)
class Randomise:
    """How far each trial moves things (m, rad; every value drawn uniformly in +-range)."""

    start_along: float = 0.10
    start_across: float = 0.10
    start_yaw: float = 0.15
    obstacle_xy: float = 0.10
    obstacle_yaw: float = 0.25
    sign_along: float = 0.0
    launch_distance: tuple[float, float] = (4.0, 6.0)  # m, a range
    ball_speed: tuple[float, float] = (0.8, 1.2)  # m/s, a range
    ball_across: float = 0.20
    ball_direction: float = 0.05
    along_path: Any = None  # (n, 2) polyline: starts anywhere along it, heading along it

    def check(self) -> None:
        for name in ("start_along", "start_across", "start_yaw", "obstacle_xy", "obstacle_yaw", "sign_along",
                     "ball_across", "ball_direction"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise InputError(f"trials: {name} must be a non-negative number, got {v}")
        for name in ("launch_distance", "ball_speed"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= hi):
                raise InputError(f"trials: {name} must be a range 0 < low <= high, got {(lo, hi)}")

    def as_dict(self) -> dict[str, Any]:
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "along_path"}
        out["along_path"] = self.along_path is not None
        return {k: list(v) if isinstance(v, tuple) else v for k, v in out.items()}


#: The labs' randomisation (the defaults above, unless the lab needs less: a stop-sign car must
#: still face its sign, a lane car starts anywhere round its lane).
AVOID = Randomise()
STOP_SIGN = Randomise(start_along=0.4, start_across=0.02, start_yaw=0.03, sign_along=0.2)
LANE_FOLLOW = Randomise(start_along=0.0, start_across=0.04, start_yaw=0.08)


@dataclass
class TrialWorld:
    """One trial's world and what was drawn for it."""

    world: Any
    start: tuple[float, float, float]
    moved: list[dict[str, Any]]  # obstacles and signs: from (x, y) to (x, y)
    balls: list[dict[str, Any]]  # per ball: launch distance, speed, start, direction


# --------------------------------------------------------------------------------------------
# drawing one trial's world
# --------------------------------------------------------------------------------------------
def _u(rng: np.random.Generator, half: float) -> float:
    return float(rng.uniform(-half, half)) if half > 0.0 else 0.0


def _centre(solid: Any) -> tuple[float, float]:
    if solid.kind == "polygon":
        p = np.asarray(solid.points, dtype=float)
        return float(p[:, 0].mean()), float(p[:, 1].mean())
    return float(solid.center[0]), float(solid.center[1])


def _moved_solid(solid: Any, dx: float, dy: float, dyaw: float) -> Any:
    cx, cy = _centre(solid)
    if solid.kind == "polygon":
        p = np.asarray(solid.points, dtype=float) - (cx, cy)
        c, s = math.cos(dyaw), math.sin(dyaw)
        q = np.column_stack((c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1])) + (cx + dx, cy + dy)
        return dataclasses.replace(solid, points=q)
    return dataclasses.replace(solid, center=(cx + dx, cy + dy))


def _roll_distance(world: Any, x: float, y: float, direction: float, radius: float) -> float:
    """How far (m) a ball of ``radius`` at (x, y) rolls along ``direction`` before it touches a wall
    or a tall solid (a ray against every polygon edge and circle; capped at 30 m)."""
    ux, uy = math.cos(direction), math.sin(direction)
    best = 30.0
    for s in world.static_solids():
        if s.z0 > radius:  # a sign plate: the ball rolls under it
            continue
        if s.kind == "polygon" and s.points is not None:
            a = np.asarray(s.points, dtype=float)
            b = np.roll(a, -1, axis=0)
            e = b - a
            den = ux * e[:, 1] - uy * e[:, 0]
            ok = np.abs(den) > 1e-12
            wx, wy = a[:, 0] - x, a[:, 1] - y
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (wx * e[:, 1] - wy * e[:, 0]) / den
                u = (wx * uy - wy * ux) / den
            hit = ok & (t > 0.0) & (u >= 0.0) & (u <= 1.0)
            if hit.any():
                best = min(best, float(t[hit].min()))
        elif s.center is not None:
            cx, cy = s.center[0] - x, s.center[1] - y
            along = cx * ux + cy * uy
            off2 = cx * cx + cy * cy - along * along
            r = s.radius + radius
            if along > 0.0 and off2 < r * r:
                best = min(best, along - math.sqrt(r * r - off2) + radius)
    return max(0.0, best - radius)


def _point_on_path(path: np.ndarray, s: float) -> tuple[float, float, float]:
    seg = np.diff(path, axis=0)
    lengths = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate(([0.0], np.cumsum(lengths)))
    s = s % cum[-1]
    j = min(int(np.searchsorted(cum, s, side="right")) - 1, len(seg) - 1)
    u = (s - cum[j]) / lengths[j] if lengths[j] > 0 else 0.0
    p = path[j] + u * seg[j]
    return float(p[0]), float(p[1]), math.atan2(seg[j, 1], seg[j, 0])


def _nearest_segment(path: np.ndarray, x: float, y: float) -> np.ndarray:
    """The direction vector (dx, dy) of the segment of ``path`` nearest to (x, y)."""
    a, b = path[:-1], path[1:]
    ab = b - a
    t = np.clip(((x - a[:, 0]) * ab[:, 0] + (y - a[:, 1]) * ab[:, 1]) / np.maximum((ab * ab).sum(axis=1), 1e-18), 0, 1)
    d = np.hypot(a[:, 0] + t * ab[:, 0] - x, a[:, 1] + t * ab[:, 1] - y)
    return ab[int(np.argmin(d))]


def randomise_world(world: Any, start: tuple[float, float, float], spec: Randomise, rng: np.random.Generator,
                    params: QCarParams = DEFAULT_PARAMS) -> TrialWorld:
    """A copy of ``world`` (a :class:`qcarlab.sim.world.World`, not changed) with the obstacles,
    signs and balls moved as ``spec`` says, and a start pose near ``start`` clear of every solid."""
    moved: list[dict[str, Any]] = []
    solids = []
    for s in world.solids:
        if s.wall or s.height >= MOVABLE_HEIGHT or spec.obstacle_xy == 0.0 and spec.obstacle_yaw == 0.0:
            solids.append(s)
            continue
        dx, dy, dyaw = _u(rng, spec.obstacle_xy), _u(rng, spec.obstacle_xy), _u(rng, spec.obstacle_yaw)
        m = _moved_solid(s, dx, dy, dyaw)
        moved.append({"what": "obstacle", "from": [round(v, 4) for v in _centre(s)],
                      "to": [round(v, 4) for v in _centre(m)], "turned_rad": round(dyaw, 4)})
        solids.append(m)
    signs = []
    for g in world.signs:
        d = _u(rng, spec.sign_along)
        if d:
            n = dataclasses.replace(g, x=g.x + d * math.cos(g.facing), y=g.y + d * math.sin(g.facing))
            moved.append({"what": "sign", "from": [round(g.x, 4), round(g.y, 4)], "to": [round(n.x, 4), round(n.y, 4)]})
            g = n
        signs.append(g)
    new = dataclasses.replace(world, solids=solids, signs=signs, balls=[], _cache={})
    balls, drawn = [], []
    for b in world.balls:
        across = _u(rng, spec.ball_across)
        direction = b.direction + _u(rng, spec.ball_direction)
        sx = b.start[0] - across * math.sin(b.direction)
        sy = b.start[1] + across * math.cos(b.direction)
        speed = float(rng.uniform(*spec.ball_speed))
        launch = float(rng.uniform(*spec.launch_distance))
        roll = _roll_distance(new, sx, sy, direction, b.radius)
        balls.append(dataclasses.replace(b, start=(sx, sy), direction=direction, speed=speed, start_time=math.inf,
                                         distance=roll))
        drawn.append({"launch_distance_m": round(launch, 4), "speed_mps": round(speed, 4),
                      "start": [round(sx, 4), round(sy, 4)], "direction_rad": round(direction, 4),
                      "rolls_m": round(roll, 3)})
    new.balls = balls
    clear = Clearance(new, params)
    x0, y0, yaw0 = start
    poly = None if spec.along_path is None else np.asarray(spec.along_path, dtype=float).reshape(-1, 2)
    if poly is not None:
        seg = np.diff(poly, axis=0)
        length = float(np.hypot(seg[:, 0], seg[:, 1]).sum())
        # the way round the path the start drives: the path's own direction where the start is, or against it
        heading = math.atan2(*_nearest_segment(poly, x0, y0)[::-1])
        backwards = math.cos(heading - yaw0) < 0.0
    for _ in range(200):
        if poly is not None:
            x, y, yaw = _point_on_path(poly, float(rng.uniform(0.0, length)))
            if backwards:
                yaw += math.pi
        else:
            x, y, yaw = x0, y0, yaw0
        along, across = _u(rng, spec.start_along), _u(rng, spec.start_across)
        turned = yaw + _u(rng, spec.start_yaw)
        c, s = math.cos(yaw), math.sin(yaw)
        pose = (x + c * along - s * across, y + s * along + c * across, math.atan2(math.sin(turned), math.cos(turned)))
        if clear(*pose, 0.0)[0] >= MIN_START_CLEARANCE:
            return TrialWorld(new, pose, moved, drawn)
    raise InputError(f"trials: no start pose near {tuple(round(v, 3) for v in start)} is clear of the obstacles "
                     f"of '{world.name}' (moved by up to {spec.obstacle_xy:g} m); move the start (--start)")


# --------------------------------------------------------------------------------------------
# the balls: rolled at the car, and the encounter watched
# --------------------------------------------------------------------------------------------
class _Encounters:
    """Wraps a lab's model: launches each ball when the car comes within its launch distance, ends
    the run ``AFTER_ENCOUNTER`` s after every ball has rolled by."""

    def __init__(self, model: Any, car: Car, world: Any, launch: Sequence[float]):
        self.model, self.car, self.world = model, car, world
        self.launch = list(launch)
        self.started: list[float | None] = [None] * len(launch)
        self.closest = [math.inf] * len(launch)
        self.over: list[bool] = [False] * len(launch)
        self.end_t: float | None = None

    def start(self, car: Car, dt: float) -> None:
        start = getattr(self.model, "start", None)
        if callable(start):
            start(car, dt)

    def step(self, t: float, readout: Any, dt: float) -> Any:
        tr = self.car.truth()
        for i, ball in enumerate(self.world.balls):
            if self.over[i]:
                continue
            bx, by = ball.position(tr.t)
            d = math.hypot(bx - tr.x, by - tr.y)
            if self.started[i] is None:
                if math.hypot(ball.start[0] - tr.x, ball.start[1] - tr.y) <= self.launch[i]:
                    self.started[i] = tr.t
                    self.world.balls[i] = dataclasses.replace(ball, start_time=tr.t)
                continue
            self.closest[i] = min(self.closest[i], d)
            if d > self.closest[i] + ENCOUNTER_MARGIN:
                self.over[i] = True
        if self.end_t is None and self.over and all(self.over):
            self.end_t = t + AFTER_ENCOUNTER
        if self.end_t is not None and t >= self.end_t:
            return STOP
        return self.model.step(t, readout, dt)


# --------------------------------------------------------------------------------------------
# the trials
# --------------------------------------------------------------------------------------------
RunFn = Callable[[Car, Any, Callable[[Any], Any] | None], Result]


def _open_sim(world: Any, start: tuple[float, float, float], seed: int, params: QCarParams,
              realism: Any = None) -> Car:
    from qcarlab.car import open_car

    return open_car("sim", world=world, seed=seed, start=start, params=params, realism=realism)


def _path(result: Result, every: int = 5) -> list[list[float]]:
    log = next(iter(result.logs.values()), {}) if result.logs else {}
    if "true_x" not in log:
        return []
    x, y = np.asarray(log["true_x"], float), np.asarray(log["true_y"], float)
    keep = np.arange(0, len(x), every)
    if len(x) and keep[-1] != len(x) - 1:
        keep = np.append(keep, len(x) - 1)
    return [[round(float(x[k]), 3), round(float(y[k]), 3)] for k in keep]


def _collision(metrics: dict, world: Any) -> dict[str, Any] | None:
    hit = metrics.get("collision")
    if not hit:
        return None
    out = {k: hit.get(k) for k in ("t", "x", "y", "yaw")}
    where = hit.get("obstacle")
    out["obstacle"] = where
    what = "solid"
    if where is not None:
        for b in world.obstacles_at(float(hit["t"])) if hit.get("t") is not None else []:
            if math.hypot(b.x - where[0], b.y - where[1]) < 1e-6:
                what = "ball"
    out["with"] = what
    return out


def run_trials(lab: str, world: Any, run: RunFn, n: int, seed: int = 0, spec: Randomise = AVOID,
               params: QCarParams = DEFAULT_PARAMS, start: tuple[float, float, float] | None = None,
               on_trial: Callable[[int, dict[str, Any]], None] | None = None,
               open_car: Callable[[Any, tuple[float, float, float], int, QCarParams], Car] | None = None,
               min_success: float = 1.0, realism: Any = None) -> Result:
    """Run ``run(car, trial_world, wrap)`` ``n`` times on a simulated car; return the trials' Result.

    ``run`` is the lab's single run (it must apply ``wrap`` to its model, when given, before the
    loop: that rolls the balls and ends the run after the encounter). ``on_trial(i, row)`` is called
    after each trial (progress). ``goal_reached`` is true when the success rate is at least
    ``min_success`` (a fraction; 1 = every trial). ``realism`` is the simulated cars' profile
    (None = ideal).
    """
    if not (isinstance(n, int) and 1 <= n <= MAX_TRIALS):
        raise InputError(f"--trials must be a whole number in 1..{MAX_TRIALS}, got {n!r}")
    if not (isinstance(min_success, (int, float)) and math.isfinite(min_success) and 0.0 <= min_success <= 1.0):
        raise InputError(f"--min-success must be a fraction in 0..1, got {min_success!r}")
    spec.check()
    opener = open_car or (lambda w, st, sd, p: _open_sim(w, st, sd, p, realism))
    start = tuple(start) if start is not None else tuple(world.start)
    rows: list[dict[str, Any]] = []
    interrupted = False
    for i in range(n):
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), i, 11]))
        tw = randomise_world(world, start, spec, rng, params)
        launch = [b["launch_distance_m"] for b in tw.balls]
        enc: list[_Encounters] = []
        with opener(tw.world, tw.start, seed + i, params) as car:

            def wrap(model: Any, car: Car = car, tw: TrialWorld = tw, launch: list[float] = launch) -> Any:
                if not tw.world.balls:
                    return model
                e = _Encounters(model, car, tw.world, launch)
                enc.append(e)
                return e

            result = run(car, tw.world, wrap)
        m = result.metrics
        if m.get("interrupted"):  # Ctrl-C: the trials so far are the result (saved, exit 130)
            interrupted = True
            break
        reasons = [] if m.get("goal_reached") else [m.get("failure") or "goal missed"]
        e = enc[0] if enc else None
        balls = []
        for j, b in enumerate(tw.balls):
            info = dict(b)
            if e is not None:
                info["ball_start_s"] = e.started[j]
                info["closest_m"] = None if not math.isfinite(e.closest[j]) else round(e.closest[j], 4)
                info["rolled_by"] = e.over[j]
            balls.append(info)
        if tw.balls and not reasons and not all(b.get("rolled_by") for b in balls):
            reasons.append("did not meet the ball" if any(b.get("ball_start_s") is None for b in balls)
                           else "the ball had not rolled by when the time was up")
        row = {
            "trial": i,
            "seed": seed + i,
            "start": [round(v, 4) for v in tw.start],
            "success": not reasons,
            "failure": "; ".join(reasons) if reasons else None,
            "collision": _collision(m, tw.world),
            "min_clearance_m": m.get("min_clearance_m"),
            "distance_m": m.get("distance_m", m.get("distance_along_lane_m")),
            "duration_s": m.get("duration_s"),
            "moved": tw.moved,
            "balls": balls,
            "metrics": {k: v for k, v in m.items() if k not in ("config", "student_blocks", "loop")
                        and not isinstance(v, (dict, list))},
            "path": _path(result),
        }
        rows.append(row)
        if on_trial is not None:
            on_trial(i, row)
    ok = sum(r["success"] for r in rows)
    hits = [dict(r["collision"], trial=r["trial"]) for r in rows if r["collision"]]
    done = len(rows)
    metrics: dict[str, Any] = {
        "experiment": lab,
        "mode": "trials",
        "trials": done,
        "trials_asked": n,
        "interrupted": interrupted,
        "successes": ok,
        "success_rate": ok / done if done else 0.0,
        "collisions": len(hits),
        "collision_places": hits,
        "failures": {r["trial"]: r["failure"] for r in rows if not r["success"]},
        "seed": seed,
        "randomise": spec.as_dict(),
        "runs": rows,
    }
    key = KEY_METRIC.get(lab)
    if key is not None:
        values = [r["metrics"].get(key[0]) for r in rows]
        values = [float(v) for v in values if isinstance(v, (int, float)) and math.isfinite(v)]
        metrics["key_metric"] = {"name": key[0], "label": key[1], "trials_with_value": len(values),
                                 "mean": float(np.mean(values)) if values else None,
                                 "min": min(values) if values else None, "max": max(values) if values else None}
    metrics["min_success"] = float(min_success)
    metrics["goal_reached"] = bool(done) and not interrupted and ok / done >= min_success - 1e-12
    metrics["failure"] = None if metrics["goal_reached"] else "interrupted (Ctrl-C)" if interrupted else (
        f"{done - ok} of {done} trials failed (success rate {100.0 * ok / done:.0f} %, "
        + ("every trial must succeed" if min_success >= 1.0 else f"at least {100.0 * min_success:.0f} % asked") + ")")
    table = {
        "trial": [r["trial"] for r in rows],
        "seed": [r["seed"] for r in rows],
        "start_x": [r["start"][0] for r in rows],
        "start_y": [r["start"][1] for r in rows],
        "start_yaw": [r["start"][2] for r in rows],
        "success": [int(r["success"]) for r in rows],
        "collision_x": [r["collision"]["x"] if r["collision"] else math.nan for r in rows],
        "collision_y": [r["collision"]["y"] if r["collision"] else math.nan for r in rows],
        "min_clearance_m": [math.nan if r["min_clearance_m"] is None else r["min_clearance_m"] for r in rows],
        "distance_m": [math.nan if r["distance_m"] is None else r["distance_m"] for r in rows],
        "ball_start_s": [_or_nan(next((b.get("ball_start_s") for b in r["balls"]), None)) for r in rows],
        "failure": [r["failure"] or "" for r in rows],
    }
    out = Result(lab, metrics, logs={"trials.csv": table})
    out.data["world"] = world
    out.figures["trials.png"] = lambda f: save_figure(f, trials_figure(world, out))
    return out


def _or_nan(v: float | None) -> float:
    return math.nan if v is None else float(v)



def trials_figure(world: Any, result: Result) -> Any:
    """``trials.png``: every trial over the world seen from above, axes in metres: successful runs
    green, failed ones red, each start a black dot, each collision a cross, the balls' rolls dashed,
    where obstacles were moved to; a legend and the success rate in the title
    (:func:`qcarlab.plots.trials_figure`). Returns the matplotlib Figure."""
    from qcarlab import plots
    from qcarlab.experiments.worlds import figure_map

    background, extent = figure_map(world, show_start=False)
    return plots.trials_figure(background, extent, result.metrics)
