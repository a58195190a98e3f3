"""qcarlab.gym: the simulated QCar as a gymnasium environment (issue 29, item 5).

Skipped cleanly without gymnasium (``pip install "qcarlab[gym]"``; the ``test`` extra has it)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")

import qcarlab.gym  # noqa: E402
from qcarlab.errors import InputError  # noqa: E402
from qcarlab.gym import QCarEnv  # noqa: E402
from qcarlab.sim.world import world_from_dict  # noqa: E402


def _rollout(env, seed: int, n: int, action_seed: int = 7):
    """n steps of seeded random actions: the observations, rewards and poses, flattened."""
    obs, info = env.reset(seed=seed)
    actions = np.random.default_rng(action_seed).uniform(env.action_space.low, env.action_space.high, (n, 2))
    rows = [np.concatenate([np.ravel(v).astype(np.float64) for v in obs.values()])]
    poses = [(info["x"], info["y"], info["yaw"])]
    rewards, ends = [], []
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a.astype(np.float32))
        rows.append(np.concatenate([np.ravel(v).astype(np.float64) for v in obs.values()]))
        poses.append((info["x"], info["y"], info["yaw"]))
        rewards.append(reward)
        ends.append((terminated, truncated))
        if terminated or truncated:
            break
    return np.array(rows), np.array(poses), rewards, ends


def test_check_env_passes_without_warnings():
    from gymnasium.utils.env_checker import check_env

    env = gymnasium.make("qcarlab/Hallway-v0", observe=("readout", "lidar", "rgbd"), image_size=(64, 48),
                         render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium's checker warns of what it dislikes: none of it
        check_env(env.unwrapped)
    frame = env.unwrapped.render()
    assert frame.shape == (480, 640, 3) and frame.dtype == np.uint8


def test_every_shipped_world_is_registered():
    assert set(qcarlab.gym.ENV_IDS) >= {"qcarlab/QCar-v0", "qcarlab/Hallway-v0", "qcarlab/Obstacles-v0",
                                        "qcarlab/StopSign-v0", "qcarlab/Studio-v0", "qcarlab/Track-v0"}
    env = gymnasium.make("qcarlab/StopSign-v0", observe="readout")
    assert env.unwrapped.world.name == "stop-sign"
    env = gymnasium.make("qcarlab/QCar-v0", world="track", observe="readout")
    assert env.unwrapped.world.name == "track"


def test_same_seed_same_trajectory_other_seed_another():
    env = QCarEnv("obstacles", observe=("readout", "lidar"), realism="lab")
    a = _rollout(env, seed=3, n=150)
    b = _rollout(QCarEnv("obstacles", observe=("readout", "lidar"), realism="lab"), seed=3, n=150)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and a[2] == b[2]
    c = _rollout(env, seed=4, n=150)  # the noise differs (same actions)
    assert not np.array_equal(a[0], c[0])
    # a reset without a seed goes on with the env's generator: reproducible as a sequence
    env.reset(seed=11)
    first = _rollout(env, seed=None, n=20)[0]
    env2 = QCarEnv("obstacles", observe=("readout", "lidar"), realism="lab")
    env2.reset(seed=11)
    assert np.array_equal(first, _rollout(env2, seed=None, n=20)[0])


def test_start_noise_is_seeded_and_free():
    env = QCarEnv("hallway", observe="readout", start_noise=(0.2, 0.3))
    poses = [env.reset(seed=s)[1] for s in (1, 1, 2)]
    assert (poses[0]["x"], poses[0]["yaw"]) == (poses[1]["x"], poses[1]["yaw"])
    assert (poses[0]["x"], poses[0]["yaw"]) != (poses[2]["x"], poses[2]["yaw"])
    assert env.car.contact() is None


def test_driving_into_a_wall_terminates_with_a_collision():
    env = QCarEnv("hallway", observe="readout", realism="ideal")
    env.reset(seed=0)  # the west corridor, heading -Y: the south wall is 5.8 m ahead
    for _ in range(500):
        obs, reward, terminated, truncated, info = env.step(np.array([0.3, 0.0], np.float32))
        if terminated or truncated:
            break
    assert terminated and not truncated
    assert info["event"] == "collision" and info["contact"]["kind"] == "collision"
    assert info["y"] < -5.5 and info["t"] < 5.0
    assert reward < 0.0  # the default reward's -1 on a collision


def test_leaving_the_world_terminates():
    world = world_from_dict({"name": "open", "floor": {"size": [2.0, 2.0], "origin": [-1.0, -1.0]},
                             "start": [0.0, 0.0, 0.0]})
    env = QCarEnv(world, observe="readout", realism="ideal")
    env.reset(seed=0)
    for _ in range(500):
        _, _, terminated, truncated, info = env.step(np.array([0.2, 0.0], np.float32))
        if terminated or truncated:
            break
    assert terminated and info["event"] == "left_world" and info["x"] > 1.0


def test_time_limit_truncates():
    env = QCarEnv("studio", observe="readout", rate=50.0, max_time=1.0)
    env.reset(seed=0)
    ends = [env.step(np.zeros(2, np.float32))[2:4] for _ in range(50)]
    assert ends[-1] == (False, True) and all(e == (False, False) for e in ends[:-1])
    assert math.isclose(env.car.time, 1.0)


def test_reward_is_replaceable_and_default_is_progress():
    seen = []

    def mine(env, action, info):
        seen.append((float(action[0]), info["forward_m"]))
        return 7.0

    env = QCarEnv("studio", observe="readout", reward=mine)
    env.reset(seed=0)
    assert env.step(np.array([0.1, 0.0], np.float32))[1] == 7.0
    assert seen and math.isclose(seen[0][0], 0.1, rel_tol=1e-6)
    env = QCarEnv("studio", observe="readout")
    env.reset(seed=0)
    total = sum(env.step(np.array([0.2, 0.0], np.float32))[1] for _ in range(100))
    assert 0.5 < total < 10.0 and math.isclose(total, env.car.truth().distance, rel_tol=0.02)
    with pytest.raises(InputError, match="reward must be a callable"):
        QCarEnv("studio", reward=3)


def test_realism_profiles_are_selectable():
    a = _rollout(QCarEnv("track", observe="readout", realism="ideal"), seed=1, n=100)[1]
    b = _rollout(QCarEnv("track", observe="readout", realism="lab"), seed=1, n=100)[1]
    assert not np.array_equal(a, b)  # the lab profile's trim, slip and delay move the car otherwise
    assert QCarEnv("track", observe="readout", realism="lab").car.realism.name == "lab"
    with pytest.raises(InputError, match="realism"):
        QCarEnv("track", realism="nope")


def test_observations_and_action_space():
    env = QCarEnv("track", observe=("readout", "lidar", "rgbd"), lidar_beams=360, image_size=(80, 60))
    obs, _ = env.reset(seed=0)
    assert set(obs) == {"readout", "lidar", "color", "depth"}
    assert obs["readout"].shape == (len(qcarlab.gym.READOUT_FIELDS),) and obs["lidar"].shape == (360,)
    assert obs["color"].shape == (60, 80, 3) and obs["depth"].shape == (60, 80)
    assert env.observation_space.contains(obs)
    assert np.allclose(env.action_space.high, [0.3, 0.5]) and env.action_space.dtype == np.float32
    obs, *_ = env.step(np.array([5.0, -5.0], np.float32))  # clipped to the box
    i = qcarlab.gym.READOUT_FIELDS.index
    assert math.isclose(obs["readout"][i("throttle")], 0.3, rel_tol=1e-6)
    assert math.isclose(obs["readout"][i("steering")], -0.5, rel_tol=1e-6)
    with pytest.raises(InputError, match="action must be two finite numbers"):
        env.step(np.array([math.nan, 0.0]))
    with pytest.raises(InputError, match="unknown observation 'sonar'"):
        QCarEnv("track", observe=("readout", "sonar"))


def test_step_before_reset_is_refused():
    with pytest.raises(InputError, match="reset"):
        QCarEnv("studio", observe="readout").step(np.zeros(2, np.float32))


def test_vector_env_of_many_cars_is_seeded():
    envs = qcarlab.gym.make_vec(3, world="hallway", observe="readout", max_time=0.5)
    obs, info = envs.reset(seed=5)
    assert obs["readout"].shape == (3, len(qcarlab.gym.READOUT_FIELDS))
    actions = np.tile(np.array([[0.3, 0.1]], np.float32), (3, 1))
    rows, ends = [], []
    for _ in range(30):
        obs, _, terminated, truncated, _ = envs.step(actions)
        rows.append(obs["readout"].copy())
        ends.append((terminated.copy(), truncated.copy()))
    # each car has its own noise (seeds 5, 6, 7), the batch reproduces under the same seed
    assert not np.array_equal(rows[-1][0], rows[-1][1])
    again = qcarlab.gym.make_vec(3, world="hallway", observe="readout", max_time=0.5)
    again.reset(seed=5)
    assert all(np.array_equal(r, again.step(actions)[0]["readout"]) for r in rows)
    # the time limit (25 steps at 50 per second) truncated every car at once; then gymnasium's
    # autoreset started them again (the step after: speed back to 0)
    assert ends[24][1].all() and not any(t.any() for t, _ in ends)
    assert not any(tr.any() for _, tr in ends[:24])
    assert np.allclose(rows[25][:, 0], 0.0, atol=0.05)
    envs.close()
    again.close()
