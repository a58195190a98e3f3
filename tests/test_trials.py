"""Trials (issue 11, item 2): N seeded runs with randomised start poses, obstacle placements and
ball start times; the success rate, the collisions and where; the hallway's ball meets the car."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from qcarlab.car import open_car
from qcarlab.experiments.avoid import AvoidConfig, avoid
from qcarlab.experiments.safety import Clearance
from qcarlab.experiments.trials import AVOID, Randomise, randomise_world, run_trials
from qcarlab.sim.world import load_world, world_from_dict

CORRIDOR = {  # a straight corridor along +X, a ball at its far end rolling back at the car
    "floor": {"size": [10.0, 2.0], "origin": [-1.0, -1.0]},
    "start": [0.0, 0.0, 0.0],
    "walls": [{"points": [[-1.0, -0.75], [9.0, -0.75], [9.0, 0.75], [-1.0, 0.75]], "closed": True, "height": 1.0}],
    "balls": [{"start": [4.5, 0.0], "direction": "180deg", "speed": 1.0, "radius": 0.12}],
}


def _rng(i: int = 0) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([0, i, 11]))


def test_a_trial_moves_the_free_standing_obstacles_and_the_start_but_not_the_walls_or_doors():
    world = load_world("hallway")
    tw = randomise_world(world, world.start, AVOID, _rng())
    walls = [s for s in world.solids if s.wall or s.height >= 1.0]
    moved_walls = [s for s in tw.world.solids if s.wall or s.height >= 1.0]
    assert all(np.array_equal(a.points, b.points) for a, b in zip(walls, moved_walls))  # walls and doors stay
    (bin0,) = [s for s in world.solids if not s.wall and s.height < 1.0]
    (bin1,) = [s for s in tw.world.solids if not s.wall and s.height < 1.0]
    dx, dy = bin1.center[0] - bin0.center[0], bin1.center[1] - bin0.center[1]
    assert 0 < math.hypot(dx, dy) and abs(dx) <= 0.1 and abs(dy) <= 0.1
    x, y, yaw = tw.start
    assert (x, y) != world.start[:2] and abs(x) <= 0.1 + 1e-9 and abs(y) <= 0.1 + 1e-9
    assert abs(yaw - world.start[2]) <= 0.15 + 1e-9
    assert Clearance(tw.world, world.params)(*tw.start)[0] >= 0.05
    assert world.solids[-1] is not tw.world.solids[-1] and bin0.center == (6.0, 1.6)  # the loaded world is untouched
    (ball,) = tw.world.balls
    assert ball.start_time == math.inf  # waits for the car; rolled when it comes within the launch distance
    assert 4.0 <= tw.balls[0]["launch_distance_m"] <= 6.0 and 0.8 <= ball.speed <= 1.2
    assert ball.distance == pytest.approx(ball.start[0] - (-0.75) - ball.radius, abs=0.05)  # rolls to the west wall


def test_the_same_seed_draws_the_same_trial_and_another_trial_another_one():
    world = load_world("obstacles")
    a = randomise_world(world, world.start, AVOID, _rng(3))
    b = randomise_world(world, world.start, AVOID, _rng(3))
    c = randomise_world(world, world.start, AVOID, _rng(4))
    assert a.start == b.start and a.moved == b.moved
    assert a.start != c.start and a.moved != c.moved


def test_a_lane_trial_starts_anywhere_round_the_lane_heading_along_it():
    from qcarlab.experiments.lane_follow import lane_centre

    world = load_world("track")
    centre = lane_centre(world, world.start)
    spec = Randomise(start_along=0.0, start_across=0.0, start_yaw=0.0, along_path=centre)
    starts = [randomise_world(world, world.start, spec, _rng(i)).start for i in range(12)]
    from qcarlab.control.tracking import Polyline

    d, _ = Polyline(centre).nearest(np.array([s[:2] for s in starts]))
    assert d.max() < 0.01  # on the lane centre
    assert np.ptp([s[0] for s in starts]) > 1.0 and np.ptp([s[1] for s in starts]) > 1.0  # round the loop
    for x, y, yaw in starts:  # counter-clockwise, as the world's start drives: the centre of the loop on the left
        assert -math.sin(yaw) * (0.0 - x) + math.cos(yaw) * (0.0 - y) > 0.5, (x, y, yaw)


def test_trials_count_successes_and_report_the_ball_collision_and_its_place():
    world = world_from_dict(CORRIDOR, "corridor")
    cfg = AvoidConfig(strategy="stop", duration=8.0)  # stops for the ball, which rolls on into it
    result = run_trials("avoid", world, lambda car, w, wrap: avoid(car, cfg, world=w, wrap=wrap), n=2, seed=5,
                        spec=Randomise(start_along=0.05, start_across=0.05, start_yaw=0.05))
    m = result.metrics
    assert m["trials"] == 2 and m["successes"] == 0 and m["success_rate"] == 0.0 and m["collisions"] == 2
    assert m["goal_reached"] is False and "2 of 2 trials failed" in m["failure"]
    for hit, run in zip(m["collision_places"], m["runs"]):
        assert hit["with"] == "ball" and 0.0 < hit["x"] < 4.5 and abs(hit["y"]) < 0.3
        (ball,) = run["balls"]
        assert ball["ball_start_s"] == pytest.approx(0.0, abs=0.02)  # the car started within 4-6 m of it
        assert run["seed"] in (5, 6) and len(run["path"]) >= 2
    assert [r["seed"] for r in m["runs"]] == [5, 6]
    assert len(result.logs["trials.csv"]["trial"]) == 2


def test_a_car_that_never_meets_the_ball_does_not_count_as_avoiding_it():
    data = dict(CORRIDOR, balls=[dict(CORRIDOR["balls"][0], start=[8.5, 0.0])])  # 8.5 m away: never within 6 m
    world = world_from_dict(data, "corridor")
    cfg = AvoidConfig(strategy="stop", duration=1.0, speed=0.1)
    result = run_trials("avoid", world, lambda car, w, wrap: avoid(car, cfg, world=w, wrap=wrap), n=1,
                        spec=Randomise(start_along=0.0, start_across=0.0, start_yaw=0.0))
    run = result.metrics["runs"][0]
    assert run["collision"] is None and run["success"] is False and run["failure"] == "did not meet the ball"
    assert run["balls"][0]["ball_start_s"] is None


def test_avoid_trials_from_the_command_line(cli, tmp_path):
    code, out, err = cli("avoid", "--trials", "2", "--duration", "2", "--json", "--out", tmp_path / "t")
    m = json.loads(out)
    assert m["mode"] == "trials" and m["trials"] == 2 and len(m["runs"]) == 2 and m["strategy"] == "combined"
    assert code == (0 if m["successes"] == 2 else 1)
    assert m["runs"][0]["start"] != m["runs"][1]["start"]
    assert {"trials.png", "trials.csv", "results.json"} <= {p.name for p in (tmp_path / "t").iterdir()}
    code2, out2, _ = cli("avoid", "--trials", "2", "--duration", "2", "--json")
    assert json.loads(out2)["runs"] == m["runs"]  # same command, same numbers
    code, out, err = cli("avoid", "--trials", "2", "--car", "tcp://127.0.0.1:9")
    assert code == 2 and "simulator only" in err and "Traceback" not in err


def test_min_success_sets_the_exit_code_of_trials(cli):
    code, out, err = cli("stop-sign", "--trials", "1", "--min-success", "0", "--max-time", "1", "--json")
    m = json.loads(out)
    assert m["successes"] == 0 and m["goal_reached"] is True and code == 0  # 1 s: never stopped, 0 % asked
    code, out, err = cli("stop-sign", "--trials", "1", "--max-time", "1", "--json")
    assert code == 1 and "1 of 1 trials failed" in err


def test_the_hallway_ball_meets_the_car_at_the_default_speed():
    """The old ball stopped rolling at 10 s, 7 s before the car came round the corner."""
    world = load_world("hallway")
    (ball,) = world.balls
    with open_car("sim", world=world) as car:
        r = avoid(car, AvoidConfig(duration=24.0), world=world)
    log = r.data["log"]
    t, x, y = log["t"], log["true_x"], log["true_y"]
    rolling = np.array([(ti - ball.start_time) * ball.speed < ball.distance and ti >= ball.start_time for ti in t])
    bx = np.array([ball.position(ti)[0] for ti in t])
    by = np.array([ball.position(ti)[1] for ti in t])
    gap = np.hypot(bx - x, by - y)
    # it reaches the car while still rolling (and passes beside it: the combined strategy dodges)
    assert rolling.any() and gap[rolling].min() < 0.8


def test_ctrl_c_keeps_the_trials_done_so_far():
    from qcarlab.experiments.result import Result

    class FakeCar:
        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

    calls = []

    def run(car, world, wrap):
        calls.append(world)
        return Result("avoid", {"goal_reached": True, "interrupted": len(calls) == 2, "collision": None})

    world = load_world("obstacles")
    result = run_trials("avoid", world, run, n=5, open_car=lambda w, s, seed, p: FakeCar())
    m = result.metrics
    assert len(calls) == 2 and m["trials"] == 1 and m["trials_asked"] == 5 and m["interrupted"] is True
    assert m["successes"] == 1 and m["goal_reached"] is False and m["failure"] == "interrupted (Ctrl-C)"
