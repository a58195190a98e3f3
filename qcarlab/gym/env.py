"""The simulated QCar as a gymnasium environment: :class:`QCarEnv`.

    import gymnasium, qcarlab.gym
    env = gymnasium.make("qcarlab/Hallway-v0", observe=("readout", "lidar"), realism="lab")
    obs, info = env.reset(seed=1)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

One step is one tick of a lab's control loop: the action (throttle, steering) is written to the
car, the stepped simulator advances ``1 / rate`` s (its physics in 2 ms steps), the chosen sensors
are read. Nothing here reaches into the simulator: the car is :class:`~qcarlab.car.sim.SimCar`
through the Car API, and a collision or the car leaving its world comes from
:meth:`SimCar.contact <qcarlab.car.sim.SimCar.contact>`.

- **Observations** (``observe``, any of): ``"readout"``, the car's own sensors as a float32
  vector (:data:`READOUT_FIELDS`: speed from the encoder, motor current, battery voltage, gyro,
  accelerometer, the applied steering and throttle); ``"lidar"``, one LIDAR turn (m, 0 = no
  return; the device's latest scan: it turns at ``params.lidar_rate``, 10 Hz, so at 50 Hz a scan
  is seen for five steps, as on the car); ``"color"`` and ``"depth"``, the RGBD camera's latest
  frame (RGB uint8, gymnasium's order; float32 m, 0 = no data), ``"rgbd"`` for both, optionally
  resized (``image_size=(W, H)``). The observation is a Dict of them (gymnasium's
  ``FlattenObservation`` makes one vector of readout and LIDAR).
- **Action**: Box([-throttle limit, -steering limit], [+throttle limit, +steering limit]),
  float32: throttle as the PWM duty fraction (0.3 by default, as on the real car) and the wheel
  angle in rad (+-0.5, + = left). Actions outside are clipped to the box; NaN is refused.
- **Termination** on a collision with a wall, an obstacle, a sign or a ball, and on leaving the
  world (``info["event"]`` says which and ``info["contact"]`` where); **truncation** when the
  episode's ``max_time`` (simulated seconds) is over.
- **Reward**: by default :func:`progress_reward` (metres driven forward this step, -1 on a
  collision or leaving the world); any callable ``reward(env, action, info) -> float`` replaces it.
- **Seeds**: ``reset(seed=s)`` reproduces the episode exactly (the car's noise streams and the
  start pose's jitter are drawn from the env's generator); resets without a seed go on with it.
- **Realism**: ``realism="lab"`` (the default: the real car's steering trim, play and delay,
  tyre slip, gyro drift, LIDAR dropouts, camera exposure and blur), ``"ideal"`` or a profile YAML.
- **Truth**: ``info`` holds the simulator's truth (``x``, ``y``, ``yaw``, ``speed``, ``t``,
  ``distance``), for rewards and plots; the observations never hold it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from qcarlab.car.sim import SimCar
from qcarlab.constants import DEFAULT_PARAMS, QCarParams, load_params
from qcarlab.errors import InputError
from qcarlab.sim.realism import load_realism

__all__ = ["OBSERVATIONS", "READOUT_FIELDS", "QCarEnv", "progress_reward"]

#: the names of the "readout" observation's entries, in order (SI units)
READOUT_FIELDS = ("speed", "motor_current", "battery_voltage", "gyro_x", "gyro_y", "gyro_z",
                  "accel_x", "accel_y", "accel_z", "steering", "throttle")
#: what ``observe`` may name ("rgbd" is "color" and "depth")
OBSERVATIONS = ("readout", "lidar", "color", "depth", "rgbd")

Reward = Callable[["QCarEnv", np.ndarray, dict[str, Any]], float]


def progress_reward(env: QCarEnv, action: np.ndarray, info: dict[str, Any]) -> float:
    """The default reward: metres driven forward this step (backwards counts negative), and -1
    when the step ended in a collision or left the world."""
    return info["forward_m"] - (1.0 if info["event"] is not None else 0.0)


def _observe(observe: str | Iterable[str]) -> tuple[str, ...]:
    names = [observe] if isinstance(observe, str) else list(observe)
    out: list[str] = []
    for name in names:
        if name not in OBSERVATIONS:
            raise InputError(f"observe: unknown observation {name!r} (known: {', '.join(OBSERVATIONS)})")
        for key in (("color", "depth") if name == "rgbd" else (name,)):
            if key not in out:
                out.append(key)
    if not out:
        raise InputError(f"observe: name at least one of {', '.join(OBSERVATIONS)}")
    return tuple(out)


def _positive(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a positive number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0.0):
        raise InputError(f"{name} must be a positive number, got {value!r}")
    return v


class QCarEnv(gym.Env):
    """A simulated QCar in a lab world, as a gymnasium environment (see the module's doc).

    ``world``: a shipped world's name (``hallway``, ``obstacles``, ``stop-sign``, ``studio``,
    ``track``), a world or ROS-map YAML, or a loaded World. ``observe``: the observations (any of
    :data:`OBSERVATIONS`). ``rate``: steps per simulated second (the lab loops' 50-200 Hz).
    ``max_time``: the episode's length in simulated seconds (then truncated). ``reward``: a
    callable ``reward(env, action, info) -> float`` (default :func:`progress_reward`). ``start``:
    the start pose (x, y, yaw), default the world's; ``start_noise``: (m, rad), the pose jitter
    drawn at each reset (a start that touches a solid is drawn again). ``params``: the car's
    parameters (a QCarParams or a YAML file); ``lidar_beams``: beams per LIDAR turn (800 on the
    device); ``image_size``: (W, H) of the camera observations (the camera's 640x480 otherwise).
    ``render_mode="rgb_array"`` renders the RGBD camera's colour image (RGB).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(
        self,
        world: Any = "hallway",
        observe: str | Iterable[str] = ("readout", "lidar"),
        *,
        realism: Any = "lab",
        rate: float = 50.0,
        max_time: float = 30.0,
        reward: Reward | None = None,
        start: tuple[float, float, float] | None = None,
        start_noise: tuple[float, float] = (0.0, 0.0),
        params: QCarParams | str | Path | None = None,
        throttle_limit: float | None = None,
        lidar_beams: int | None = None,
        image_size: tuple[int, int] | None = None,
        render_mode: str | None = None,
    ):
        from qcarlab.sim.world import load_world

        self.params = params = params if isinstance(params, QCarParams) else (
            load_params(params) if params is not None else DEFAULT_PARAMS)
        self.world = load_world(world, params)
        self.observe = _observe(observe)
        self.realism = load_realism(realism)
        self.rate = _positive("rate", rate)
        if not 1.0 <= self.rate <= 2000.0:
            raise InputError(f"rate must be between 1 and 2000 steps per simulated second, got {rate}")
        self.dt = 1.0 / self.rate
        self.max_time = _positive("max_time", max_time)
        self.max_steps = max(1, round(self.max_time * self.rate))
        if reward is not None and not callable(reward):
            raise InputError(f"reward must be a callable reward(env, action, info) -> float, got {reward!r}")
        self.reward_fn: Reward = reward or progress_reward
        self.start = tuple(float(v) for v in (start if start is not None else self.world.start))
        if len(self.start) != 3 or not all(math.isfinite(v) for v in self.start):
            raise InputError(f"start must be three finite numbers x, y, yaw, got {start!r}")
        noise = tuple(float(v) for v in start_noise)
        if len(noise) != 2 or not all(math.isfinite(v) and v >= 0.0 for v in noise):
            raise InputError(f"start_noise must be two non-negative numbers (m, rad), got {start_noise!r}")
        self.start_noise = noise
        if lidar_beams is not None and not (isinstance(lidar_beams, int) and 8 <= lidar_beams <= 100_000):
            raise InputError(f"lidar_beams must be an integer of 8-100000, got {lidar_beams!r}")
        self.lidar_beams = lidar_beams
        if image_size is not None:
            if len(image_size) != 2 or not all(isinstance(v, int) and 8 <= v <= 4096 for v in image_size):
                raise InputError(f"image_size must be (width, height) in pixels, 8-4096, got {image_size!r}")
            image_size = (int(image_size[0]), int(image_size[1]))
        self.image_size = image_size
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise InputError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode

        # a car for the limits (and numba's physics warm now, not in the first episode)
        self.car = self._new_car(0, self.start)
        self.car.warm_physics()
        tl, sl = self.car.throttle_limit, self.car.steering_limit
        self.action_space = spaces.Box(np.array([-tl, -sl], np.float32), np.array([tl, sl], np.float32),
                                       dtype=np.float32)
        p = self.params
        # the readout's range: what the car can reach (full duty on a full battery: 14.7 m/s, a
        # stalled motor 27 A) with room to spare, the IMU's (an MPU-9250-class one: +-2000 deg/s, +-16 g)
        self._readout_bound = np.array((20.0, 40.0, 15.0, 35.0, 35.0, 35.0, 160.0, 160.0, 160.0, p.max_steering,
                                        1.0), np.float32)
        self.observation_space = spaces.Dict(self._spaces())
        self._steps: int | None = None  # None until the first reset()
        self._pose = (self.start[0], self.start[1], self.start[2])

    # --- spaces and observations --------------------------------------------------------------
    def _spaces(self) -> dict[str, spaces.Space]:
        p = self.params
        w, h = self.image_size or (p.rgbd_width, p.rgbd_height)
        beams = self.lidar_beams or p.lidar_beams
        out: dict[str, spaces.Space] = {}
        for key in self.observe:
            if key == "readout":
                out[key] = spaces.Box(-self._readout_bound, self._readout_bound, (len(READOUT_FIELDS),), np.float32)
            elif key == "lidar":
                out[key] = spaces.Box(0.0, np.float32(p.lidar_max_range), (beams,), np.float32)
            elif key == "color":
                out[key] = spaces.Box(0, 255, (h, w, 3), np.uint8)
            else:
                out[key] = spaces.Box(0.0, np.float32(p.rgbd_max_depth), (h, w), np.float32)
        return out

    def _obs(self) -> dict[str, np.ndarray]:
        car, out = self.car, {}
        frame = None
        for key in self.observe:
            if key == "readout":
                r = car.read()
                g, a = r.gyro, r.accel
                v = np.array((r.tach * self.params.speed_per_count, r.motor_current, r.battery_voltage,
                              g[0], g[1], g[2], a[0], a[1], a[2], r.steering, r.throttle), np.float32)
                out[key] = np.clip(v, -self._readout_bound, self._readout_bound, out=v)
            elif key == "lidar":
                out[key] = car.read_lidar().ranges.astype(np.float32)
            else:
                if frame is None:
                    frame = car.read_rgbd()
                out[key] = self._image(frame, key)
        return out

    def _image(self, frame: Any, key: str) -> np.ndarray:
        import cv2

        if key == "color":
            img = frame.color
            if self.image_size is not None and img.shape[1::-1] != self.image_size:
                img = cv2.resize(img, self.image_size, interpolation=cv2.INTER_AREA)
            return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        depth = frame.depth
        if self.image_size is not None and depth.shape[::-1] != self.image_size:
            depth = cv2.resize(depth, self.image_size, interpolation=cv2.INTER_NEAREST)
        return np.ascontiguousarray(depth, dtype=np.float32)

    # --- episodes -----------------------------------------------------------------------------
    def _new_car(self, seed: int, start: tuple[float, float, float]) -> SimCar:
        car = SimCar(self.params, seed=seed, world=self.world, start=start, realism=self.realism)
        if self.lidar_beams is not None:
            car.lidar_beams = self.lidar_beams
        return car

    def _start_pose(self) -> tuple[float, float, float]:
        x, y, yaw = self.start
        dxy, dyaw = self.start_noise
        if dxy == 0.0 and dyaw == 0.0:
            return (x, y, yaw)
        from qcarlab.sim.contact import Contact

        contact = Contact(self.world, self.params)
        for _ in range(100):
            u = self.np_random.uniform(-1.0, 1.0, 3)
            pose = (x + dxy * float(u[0]), y + dxy * float(u[1]), yaw + dyaw * float(u[2]))
            contact.forget()
            if contact.check(*pose) is None:
                return pose
        raise InputError(f"start_noise {self.start_noise}: no free start pose found within it around {self.start}")

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """A new episode: the car at rest at its start pose (jittered by ``start_noise``), time 0.
        ``options={"start": (x, y, yaw)}`` starts this episode there instead."""
        super().reset(seed=seed)
        car_seed = int(self.np_random.integers(0, 2**31 - 1))
        if options and options.get("start") is not None:
            start = tuple(float(v) for v in options["start"])
            if len(start) != 3 or not all(math.isfinite(v) for v in start):
                raise InputError(f"options['start'] must be three finite numbers x, y, yaw, got {options['start']!r}")
        else:
            start = self._start_pose()
        self.car.close()
        self.car = self._new_car(car_seed, start)
        self._steps = 0
        tr = self.car.truth()
        self._pose = (tr.x, tr.y, tr.yaw)
        return self._obs(), self._info(tr, 0.0, self.car.contact())

    def step(self, action: Any):
        if self._steps is None:
            raise InputError("step() before reset(): call env.reset() first")
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (2,) or not np.isfinite(a).all():
            raise InputError(f"action must be two finite numbers (throttle, steering), got {action!r}")
        low, high = self.action_space.low, self.action_space.high
        throttle = min(max(float(a[0]), float(low[0])), float(high[0]))
        steering = min(max(float(a[1]), float(low[1])), float(high[1]))
        car = self.car
        car.write(throttle, steering)
        car.advance(self.dt)
        self._steps += 1
        event = car.contact()
        tr = car.truth()
        x0, y0, _ = self._pose
        forward = (tr.x - x0) * math.cos(tr.yaw) + (tr.y - y0) * math.sin(tr.yaw)
        self._pose = (tr.x, tr.y, tr.yaw)
        obs = self._obs()
        info = self._info(tr, forward, event)
        reward = float(self.reward_fn(self, a.astype(np.float32), info))
        terminated = event is not None
        truncated = not terminated and self._steps >= self.max_steps
        return obs, reward, terminated, truncated, info

    def _info(self, tr: Any, forward: float, event: Any) -> dict[str, Any]:
        return {"t": tr.t, "x": tr.x, "y": tr.y, "yaw": tr.yaw, "speed": tr.speed, "distance": tr.distance,
                "forward_m": forward, "event": None if event is None else event.kind,
                "contact": None if event is None else event._asdict()}

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        import cv2

        return cv2.cvtColor(self.car.read_rgbd().color, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        self.car.close()
