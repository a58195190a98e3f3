"""The simulated RPLidar A2: a 360 degree scan in the horizontal plane at the LIDAR's mount.

    >>> import numpy as np
    >>> from qcarlab.sim.world import load_world
    >>> from qcarlab.sim.lidar import Lidar
    >>> lidar = Lidar(load_world("obstacles"), rng=np.random.default_rng(1))
    >>> scan = lidar.scan((0.0, 0.0, -np.pi / 2))          # car pose: centre x, y, yaw
    >>> scan.angles[0], scan.ranges[0]                     # beam 0 looks straight ahead

The model (DESIGN.md section 3): ``beams`` samples per turn (800 by default, the device at
10 Hz), equally spaced counter-clockwise from the car's forward direction (beam ``i`` at
``2 pi i / beams`` in the body frame, REP-103). ``fov`` (rad, < 2 pi) makes it a sector
scanner instead (F1TENTH's Hokuyo: 1080 beams over 4.7 rad): beam ``i`` at
``-fov/2 + i fov / (beams - 1)``. The beams sweep the horizontal plane at the
mount height ``lidar_z`` (0.186 m): walls, obstacles, sign posts and plates and the moving balls
cut by that plane reflect; shapes lower than the mount are not seen, as on the real car.

A range is the distance from the LIDAR's centre plus Gaussian noise (``lidar_noise``, 5 mm,
drawn from the ``rng`` given, the LIDAR's own: it draws the noise of 16 scans at a time;
``rng=None`` gives exact ranges), kept within
[``lidar_min_range``, ``lidar_max_range``] (0.15-18 m). As the device, a beam reads **0** when
nothing is within the maximum range and also when the object is closer than the minimum range
(the RPLidar reports no valid distance then; set :data:`CLOSE_READS_MIN` to clamp instead).

Speed: a world of polygons and circles alone (every built-in world) is scanned per *edge*: each
polygon edge is intersected with just the beams whose angles it spans (circles likewise), exact
to rounding, a few microseconds a scan (``vector_walls``). A ROS map's grid is drawn once into a
raster with a distance transform (see :mod:`qcarlab.sim.raster`, one uint16 a cell; its walls
also as 8 x 8-cell tiles of one byte a cell, which stay in the cache between scans); a scan
marches every beam through it, two beams at a time, with precomputed sin/cos tables (compiled
with numba when available). The few moving balls are intersected analytically. For a marched
scan ``last_cell_steps`` tells how many cells it looked at: about 3 per cell of a beam's length
at most, whatever the pose (a beam along a cell boundary included); set ``vector_walls = False``
to march a vector world's raster too.
"""

from __future__ import annotations

import math

import numpy as np

from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import InputError
from qcarlab.sensors import LidarScan
from qcarlab.sim.edge_scan import KIND_GRID, edge_table, readings, scan_edges, shape_tables
from qcarlab.sim.world import World, load_world

__all__ = ["CLOSE_READS_MIN", "COMPILED", "SWITCH_AFTER", "Lidar"]

CLOSE_READS_MIN = False  # True: an object nearer than the minimum range reads the minimum, not 0
NOISE_SCANS = 16  # scans whose range noise is drawn from the rng in one go
#: Which implementation scans a vector world: None (default) = numpy (:mod:`qcarlab.sim.edge_scan`)
#: until the process has made :data:`SWITCH_AFTER` such scans, then the numba-compiled kernel;
#: True = always compiled; False = always numpy. Both are the same operations on the same numbers:
#: the same ranges.
COMPILED: bool | None = None
#: Numpy scans after which a process switches to the compiled kernel: importing numba and loading
#: the kernel from its cache costs 0.3-0.8 s and it saves some 0.1-0.2 ms a scan, so a lab's lone
#: run (60 s of avoid: 600 scans) never loads it, a long one (a gym env's training, a sweep) does.
SWITCH_AFTER = 2_000
_numpy_scans = 0
_compiled_scan = None


def _compiled():
    """The compiled edge scan when :data:`COMPILED` (or the scans made so far) ask for it and
    numba is installed, else None (numpy)."""
    use = COMPILED
    if use is None:
        use = _compiled_scan is not None or _numpy_scans >= SWITCH_AFTER
    return load_compiled() if use else None


def load_compiled():
    """Switch this process's vector-world scans to the compiled kernel now (a server, a gym env, the
    grader's warm process: they scan for long; :func:`qcarlab.car.sim.SimCar.warm_physics` calls
    this), unless :data:`COMPILED` is False; None without numba."""
    global _compiled_scan
    if COMPILED is False:
        return None
    if _compiled_scan is None:
        from qcarlab.sim import _kernels

        if _kernels.HAVE_NUMBA:  # (without numba the kernel is plain Python: far slower than numpy)
            _compiled_scan = _kernels.lidar_scan_edges
    return _compiled_scan


class Lidar:
    """A LIDAR in a world. ``scan(pose, t)`` returns a :class:`~qcarlab.sensors.LidarScan`."""

    def __init__(
        self,
        world: World | str,
        params: QCarParams = DEFAULT_PARAMS,
        beams: int | None = None,
        rng: np.random.Generator | None = None,
        fov: float | None = None,
    ):
        self.world = world if isinstance(world, World) else load_world(world, params)
        self.params = params
        n = params.lidar_beams if beams is None else beams
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise InputError(f"LIDAR beams must be a positive integer, got {beams!r}")
        self.beams = int(n)
        self.rng = rng
        if fov is None or fov >= 2.0 * math.pi:
            self.angles = np.arange(self.beams, dtype=np.float64) * (2.0 * math.pi / self.beams)
        elif math.isfinite(fov) and fov > 0.0 and self.beams >= 2:
            # a sector centred on forward, both ends included (as a Hokuyo or F1TENTH's scans)
            self.angles = -fov / 2.0 + np.arange(self.beams, dtype=np.float64) * (fov / (self.beams - 1))
        else:
            raise InputError(f"LIDAR fov must be a positive angle (rad) with at least 2 beams, got {fov!r}")
        self.angles.setflags(write=False)
        self._cos = np.cos(self.angles)
        self._sin = np.sin(self.angles)
        # the shapes cut by the scan plane; the raster (cells to march) is drawn when a scan needs it
        self._shapes = r = shape_tables(self.world, params.lidar_z)
        self._raster_built = None
        self._no_balls = np.zeros((0, 3), np.float64)
        self._no_noise = np.zeros(0, np.float64)
        #: scan per polygon edge (True: a world of polygons and circles alone) or march the raster
        self.vector_walls = not bool(len(r.kinds) and r.kinds[0] == KIND_GRID)
        self._edges = edge_table(r.kinds, r.poly_start, r.poly_count, r.verts)
        self._full = fov is None or fov >= 2.0 * math.pi
        self._a0 = float(self.angles[0])
        self._da = (2.0 * math.pi / self.beams) if self._full else float(self.angles[1] - self.angles[0])
        self.last_cell_steps = 0  # cells the last marched scan looked at (all beams): the work it took
        self._noise_rows = np.zeros((0, self.beams))
        self._noise_i = 0

    @property
    def _raster(self):
        """The world's raster at the scan plane (:func:`qcarlab.sim.raster.build_raster`), drawn (or
        read from the disk cache) on first use: only a marched scan reads its cells."""
        if self._raster_built is None:
            from qcarlab.sim.raster import build_raster

            self._raster_built = build_raster(self.world, z=self.params.lidar_z)
        return self._raster_built

    @property
    def rate(self) -> float:
        """Scans per second (Hz)."""
        return self.params.lidar_rate

    def sensor_pose(self, pose: tuple[float, float, float]) -> tuple[float, float, float]:
        """The LIDAR's (x, y, yaw) in the world for a car pose (x, y, yaw of the car's centre)."""
        x, y, yaw = (float(v) for v in pose)
        lx = self.params.lidar_x
        return (x + lx * math.cos(yaw), y + lx * math.sin(yaw), yaw)

    def _balls(self, t: float) -> np.ndarray:
        if not self.world.balls:
            return self._no_balls
        z = self.params.lidar_z
        rows = []
        for c in self.world.obstacles_at(t):
            dz = z - c.radius  # the sphere rests on the floor: centre at height r
            if abs(dz) < c.radius:
                rows.append((c.x, c.y, math.sqrt(c.radius * c.radius - dz * dz)))
        return np.array(rows, np.float64).reshape(-1, 3) if rows else self._no_balls

    def _cast(self, pose, t: float, noise: np.ndarray, near_mode: int) -> np.ndarray:
        global _numpy_scans
        sx, sy, syaw = self.sensor_pose(pose)
        p = self.params
        out = np.empty(self.beams, np.float64)
        if self.vector_walls:
            s, rmax, rmin = self._shapes, float(p.lidar_max_range), float(p.lidar_min_range)
            kernel = _compiled()
            if kernel is not None:
                kernel(sx, sy, syaw, self._cos, self._sin, self._a0, self._da, self._full, rmax, self._edges, s.kinds,
                       s.circles, self._balls(t), noise, rmin, near_mode, out)
            else:
                _numpy_scans += 1
                dist, dx, dy, _ = scan_edges(sx, sy, syaw, self._cos, self._sin, self._a0, self._da, self._full,
                                             self._edges, s.kinds, s.circles)
                readings(dist, sx, sy, dx, dy, self._balls(t), noise, rmax, rmin, near_mode, out)
            self.last_cell_steps = 0
            return out
        from qcarlab.sim import _kernels

        r = self._raster
        self.last_cell_steps = _kernels.lidar_scan(
            sx, sy, syaw, self._cos, self._sin, float(p.lidar_max_range),
            r.x0, r.y0, r.res, r.cells, r.tiles, r.tiles_x, r.kinds, r.poly_start, r.poly_count, r.verts, r.circles,
            self._balls(t), noise, float(p.lidar_min_range), near_mode, out,
        )
        return out

    def true_ranges(self, pose: tuple[float, float, float], t: float = 0.0) -> np.ndarray:
        """Exact distances (m) of every beam, ``inf`` where nothing is within the maximum range."""
        return self._cast(pose, t, self._no_noise, -1)

    def scan(self, pose: tuple[float, float, float], t: float = 0.0) -> LidarScan:
        """One turn from the car pose (x, y, yaw of its centre) at time ``t`` (moving balls)."""
        p = self.params
        if self.rng is not None and p.lidar_noise > 0.0:
            if self._noise_i >= len(self._noise_rows):
                # the noise of NOISE_SCANS scans drawn at once: the generator's draws come in
                # sequence, so these are the numbers one draw per scan would give
                self._noise_rows = self.rng.standard_normal((NOISE_SCANS, self.beams))
                self._noise_rows *= p.lidar_noise
                self._noise_i = 0
            noise = self._noise_rows[self._noise_i]
            self._noise_i += 1
        else:
            noise = self._no_noise
        ranges = self._cast(pose, t, noise, 1 if CLOSE_READS_MIN else 0)
        return LidarScan(t=float(t), angles=self.angles, ranges=ranges)
