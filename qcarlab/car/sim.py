"""The built-in simulated QCar: the :class:`~qcarlab.sim.vehicle.Vehicle` body behind the Car API.

Two clocks:

- **stepped** (default): time moves only when the caller calls ``advance(dt)``; the run is as fast
  as the CPU allows and exactly reproducible for a given seed;
- **realtime**: simulated time follows the wall clock (keyboard drive, the TCP server); every
  read or write first brings the physics up to the present.

Sensor noise comes from generators spawned from the seed, one per sensor, so adding a reading of
one sensor never changes the numbers of another.
"""

from __future__ import annotations

import math
import time
from collections import deque
from typing import Any

import numpy as np

from qcarlab.car.base import Car, Command, Identity, Readout, Truth
from qcarlab.car.lamps import ALL_OFF
from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import InputError
from qcarlab.sim.vehicle import Vehicle

START_POSE = (0.0, 0.0, -math.pi / 2.0)  # the lab sheet's start: origin, heading -Y


class SimCar(Car):
    """A simulated QCar on its stand or on the floor, optionally in a world with sensors."""

    lidar_beams: int | None = None  # beams per scan; None = the device's (QCarParams.lidar_beams)

    def __init__(
        self,
        params: QCarParams = DEFAULT_PARAMS,
        seed: int = 0,
        on_stand: bool = False,
        world: Any = None,
        start: tuple[float, float, float] | None = None,
        realtime: bool = False,
        throttle_limit: float | None = None,
    ):
        super().__init__(params, throttle_limit)
        if not isinstance(seed, int) or seed < 0:
            raise InputError(f"seed must be a non-negative integer, got {seed!r}")
        self.seed = seed
        self.world = world
        if start is None:
            start = getattr(world, "start", None) or START_POSE
        self.start = tuple(float(v) for v in start)
        self.vehicle = Vehicle(params, on_stand=on_stand, pose=self.start)
        seq = np.random.SeedSequence(seed)
        imu_seq, analog_seq, lidar_seq, rgbd_seq, csi_seq = seq.spawn(5)
        # one noise stream per sensor, fixed by the seed whatever order the sensors are first read in
        self._sensor_seqs = {"lidar": lidar_seq, "rgbd": rgbd_seq, "csi": csi_seq}
        self._imu_rng = np.random.default_rng(imu_seq)
        self._analog_rng = np.random.default_rng(analog_seq)
        self._gyro_bias = self._imu_rng.normal(0.0, params.gyro_bias_sd, 3)
        self._cmd = Command()
        self._realtime = bool(realtime)
        self._t0_wall = time.monotonic()
        self._sensors: dict[str, Any] = {}  # built on first read: rasters cost time and memory
        self._frames: dict[str, tuple[int, Any]] = {}  # sensor -> (frame index, frame)
        self._history: deque[tuple[float, float, float, float]] = deque(maxlen=256)
        self._remember_pose()

    # --- time -----------------------------------------------------------------------------------
    @property
    def stepped(self) -> bool:
        return not self._realtime

    @property
    def time(self) -> float:
        self._sync()
        return self.vehicle.state.t

    def _sync(self) -> None:
        """In realtime mode, run the physics up to the wall clock."""
        if self._realtime:
            lag = (time.monotonic() - self._t0_wall) - self.vehicle.state.t
            if lag > 0.0:
                self.vehicle.step(lag)
                self._remember_pose()

    def _remember_pose(self) -> None:
        s = self.vehicle.state
        self._history.append((s.t, s.x, s.y, s.yaw))

    def pose_at(self, t: float) -> tuple[float, float, float]:
        """The true pose at a recent time ``t``, interpolated between the steps around it."""
        hist = self._history
        if t >= hist[-1][0]:
            return hist[-1][1:]
        for i in range(len(hist) - 1, 0, -1):
            t0, x0, y0, a0 = hist[i - 1]
            t1, x1, y1, a1 = hist[i]
            if t0 <= t:
                u = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
                da = (a1 - a0 + math.pi) % (2.0 * math.pi) - math.pi
                return (x0 + u * (x1 - x0), y0 + u * (y1 - y0), a0 + u * da)
        return hist[0][1:]

    def advance(self, dt: float) -> None:
        if not (math.isfinite(dt) and dt >= 0.0):
            raise InputError(f"advance: dt must be a non-negative number of seconds, got {dt!r}")
        if self._realtime:
            time.sleep(dt)
            self._sync()
        else:
            self.vehicle.step(dt)
            self._remember_pose()

    # --- I/O ------------------------------------------------------------------------------------
    def _apply(self, cmd: Command) -> None:
        self._sync()
        self._cmd = cmd
        self.vehicle.command(cmd.throttle, cmd.steering)

    def read(self) -> Readout:
        self._sync()
        s, p = self.vehicle.state, self.params
        counts_per_rad = p.encoder_cpr / (2.0 * math.pi)
        noise = self._imu_rng.normal(0.0, 1.0, 6)
        gyro = self._gyro_bias + p.gyro_noise * noise[:3]
        gyro[2] += s.yaw_rate
        accel = p.accel_noise * noise[3:]
        accel[0] += s.accel
        accel[1] += s.v * s.yaw_rate  # centripetal
        accel[2] += p.gravity
        an = self._analog_rng.normal(0.0, 1.0, 2)
        return Readout(
            t=s.t,
            encoder_counts=math.floor(s.motor_angle * counts_per_rad),
            tach=s.omega * counts_per_rad,
            motor_current=s.current + p.current_noise * float(an[0]),
            battery_voltage=s.battery_voltage + p.voltage_noise * float(an[1]),
            gyro=gyro,
            accel=accel,
            steering=self._cmd.steering,
            throttle=self._cmd.throttle,
            leds=self._cmd.leds,
        )

    def truth(self) -> Truth:
        self._sync()
        s = self.vehicle.state
        return Truth(
            t=s.t,
            x=s.x,
            y=s.y,
            yaw=s.yaw,
            speed=s.v,
            wheel_speed=self.vehicle.wheel_speed,
            steering=s.delta,
            distance=s.distance,
            wheel_distance=s.wheel_distance,
        )

    # --- exteroceptive sensors ------------------------------------------------------------------
    def _world(self) -> Any:
        if self.world is None:  # sensors without a named world see the lab room
            from qcarlab.sim.world import load_world

            self.world = load_world("studio", self.params)
        return self.world

    def _sensor(self, kind: str) -> Any:
        sensor = self._sensors.get(kind)
        if sensor is None:
            from qcarlab.sim import camera, lidar

            rng = np.random.default_rng(self._sensor_seqs[kind])
            world = self._world()
            if kind == "lidar":
                sensor = lidar.Lidar(world, self.params, beams=self.lidar_beams, rng=rng)
            elif kind == "rgbd":
                sensor = camera.RGBDCamera(world, self.params, rng)
            else:
                sensor = camera.CSICameras(world, self.params, rng)
            self._sensors[kind] = sensor
        return sensor

    def _latest_frame(self, kind: str, rate: float, render) -> Any:
        """The latest frame of a sensor that takes ``rate`` frames/s: frame k is taken at k / rate
        from the pose at that time; reads between two frames return the same frame."""
        self._sync()
        k = math.floor(self.vehicle.state.t * rate + 1e-9)
        cached = self._frames.get(kind)
        if cached is not None and cached[0] == k:
            return cached[1]
        t_k = k / rate
        frame = render(self._sensor(kind), self.pose_at(t_k), t_k)
        self._frames[kind] = (k, frame)
        return frame

    def read_lidar(self) -> Any:
        return self._latest_frame("lidar", self.params.lidar_rate, lambda s, pose, t: s.scan(pose, t))

    def read_rgbd(self) -> Any:
        return self._latest_frame("rgbd", self.params.rgbd_rate, lambda s, pose, t: s.render(pose, t))

    def read_csi(self) -> Any:
        return self._latest_frame("csi", self.params.csi_rate, lambda s, pose, t: s.render(pose, t))

    def identity(self) -> Identity:
        caps = ["drive", "lamps", "encoder", "imu", "battery", "truth", "lidar", "rgbd", "csi"]
        if self.stepped:
            caps.append("lockstep")
        return Identity(
            name="qcarlab-sim",
            backend="sim",
            capabilities=caps,
            extra={"seed": self.seed, "on_stand": self.vehicle.on_stand, "world": getattr(self.world, "name", None)},
        )

    def stop(self) -> None:
        self._apply(Command(0.0, 0.0, ALL_OFF))

    def reset(self) -> None:
        """Back to the state the car was opened in: its start pose at rest, time 0, no command, the
        noise streams re-seeded (a lock-step server's new controlling client starts here)."""
        self.__init__(self.params, seed=self.seed, on_stand=self.vehicle.on_stand, world=self.world,
                      start=self.start, realtime=self._realtime, throttle_limit=self.throttle_limit)
