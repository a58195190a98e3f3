"""Compile the simulator's kernels for this machine before a lab needs them.

After an install (or an edit of the kernels' source) numba's cache is empty, and the first camera
or LIDAR lab compiles the kernels its frames use: a first ``qcarlab stop-sign`` takes some 13 s
instead of one. The warm server (:mod:`qcarlab.warm`), which a student's first ``qcarlab`` command
at a terminal starts in the background (``--help``, ``labs``, ``template`` or a lab), runs this
first when the cache is cold, so the lab that follows finds every kernel compiled::

    python -m qcarlab.precompile      # 15-19 s on a 2-core VM (2026-12-06); nothing to compile: 1.5 s

It draws what the labs draw, in each built-in world kind and realism profile: one RGBD frame,
one LIDAR scan and the four CSI views at the world's start, a few physics steps (the compiled
step), the referee's clearance, and the avoidance controller's kernels. The numbers are the
same as ever: a kernel compiled here is the one a lab would have compiled. A separate process,
because a server that forks commands runs no OpenCV code itself.
"""

from __future__ import annotations

import sys
import time

#: The worlds drawn: the stop sign's, polygons and balls (hallway), the lane track's mat.
WORLDS = ("stop-sign", "hallway", "track")
REALISMS = ("ideal", "lab")
TIMEOUT = 240.0  # s: a compile this long has hung (under warm.START_TIMEOUT: a client waits that long)
#: One kernel of each sensor and of the referee (all in ``qcarlab/sim/_kernels.py``): compiled for
#: this machine in the cache, the precompile has run (or the labs have drawn every sensor already).
KERNELS = ("compose_rows", "column_layers", "lidar_scan_edges", "render_columns", "polygon_clearance")


def needs_compiling() -> bool:
    """Whether numba's cache lacks one of :data:`KERNELS` compiled for this machine (its CPU and
    features: a cache in a home folder shared by several machines holds others' too) and this
    source (an edited file's index is stale). False without numba, or where numba's cache API
    is not what this reads (then the labs compile what they use, as before)."""
    try:
        from qcarlab.sim import _kernels

        for name in KERNELS:
            kernel = getattr(_kernels, name)
            magic = kernel.targetctx.codegen().magic_tuple()
            if not any(key[1] == magic for key in kernel._cache._cache_file._load_index()):
                return True
    except Exception:  # noqa: BLE001 - no numba (plain functions), or its cache API moved: no guess
        return False
    return False


def compile_kernels() -> float:
    """Draw one frame of every sensor and step the car in each world and profile (compiling what
    the cache lacks, loading the rest); the seconds it took."""
    from qcarlab.car.sim import SimCar
    from qcarlab.control import _kernels as control_kernels
    from qcarlab.sim.contact import Clearance
    from qcarlab.sim.world import load_world

    t0 = time.perf_counter()
    for realism in REALISMS:
        for name in WORLDS:
            world = load_world(name)
            car = SimCar(world=world, realism=realism)
            car.warm_physics()
            for kind in ("rgbd", "lidar", "csi"):
                car.draw_frame(kind, car.start, 0.0)
            for _ in range(3):
                car.write(0.05, 0.0)
                car.read()
            Clearance(world, car.params)(*car.start)
    control_kernels.warm()
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> None:
    """``python -m qcarlab.precompile [--if-needed]``: with ``--if-needed``, nothing when the
    cache holds the kernels already (:func:`needs_compiling`: about 0.7 s to find out)."""
    args = sys.argv[1:] if argv is None else argv
    if any(a != "--if-needed" for a in args):
        sys.stderr.write("usage: python -m qcarlab.precompile [--if-needed]\n")
        raise SystemExit(2)
    if args and not needs_compiling():
        return
    seconds = compile_kernels()
    print(f"the simulator's kernels are compiled for this machine ({seconds:.1f} s)", file=sys.stderr)


if __name__ == "__main__":
    main()
