"""What the command line needs of the simulator's worlds, through the experiments layer.

``cli/`` only parses, calls and prints, and never imports ``sim/`` itself: loading a world for
``--world``, listing the shipped ones, the top-down map under a figure and the CSI panorama come
from here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import InputError
from qcarlab.sim.world import World, list_worlds, shipped_names
from qcarlab.sim.world import load_world as _load_world

__all__ = ["check_start", "label_views", "list_worlds", "load_world", "looks_like_path", "render_topdown", "stitch_panorama",
           "topdown_map"]


def render_topdown(*args: Any, **kwargs: Any) -> Any:
    """:func:`qcarlab.sim.render.render_topdown` (imported when used: it loads OpenCV, which a
    LIDAR lab's run never needs)."""
    from qcarlab.sim.render import render_topdown as render

    return render(*args, **kwargs)


def world_to_pixel(*args: Any, **kwargs: Any) -> Any:
    """:func:`qcarlab.sim.render.world_to_pixel` (imported when used, as :func:`render_topdown`)."""
    from qcarlab.sim.render import world_to_pixel as to_pixel

    return to_pixel(*args, **kwargs)


def stitch_panorama(*args: Any, **kwargs: Any) -> Any:
    """:func:`qcarlab.sim.camera.stitch_panorama` (imported when used: the camera loads numba,
    which a run without cameras does not need)."""
    from qcarlab.sim.camera import stitch_panorama as stitch

    return stitch(*args, **kwargs)


def looks_like_path(text: str) -> bool:
    """True when ``--world``'s argument is meant as a file: it has a folder separator, starts
    with ``.`` or ``~``, or ends in .yaml/.yml. Anything else that is a shipped world's name is that
    world, whatever the current folder holds (``qcarlab template stop-sign --out stop-sign`` makes
    a folder named like the shipped world; it must not shadow it)."""
    return ("/" in text or "\\" in text or text.startswith((".", "~"))
            or text.lower().endswith((".yaml", ".yml")))


def load_world(name_or_path: str | Path | World, params: QCarParams = DEFAULT_PARAMS) -> World:
    """The simulator's :func:`~qcarlab.sim.world.load_world`, with one clear line for a folder.

    A shipped world's name wins over a file or folder of the same name in the current folder,
    unless the argument looks like a path (:func:`looks_like_path`: ``./stop-sign``)."""
    if isinstance(name_or_path, (str, Path)) and str(name_or_path) in shipped_names() \
            and not looks_like_path(str(name_or_path)):
        return _load_world(str(name_or_path), params)
    if isinstance(name_or_path, (str, Path)) and Path(str(name_or_path)).expanduser().is_dir():
        raise InputError(f"--world {name_or_path}: is a folder; give a shipped world's name, a world YAML file "
                         "or a ROS map YAML file (qcarlab lidar-scan --worlds lists the shipped ones)")
    return _load_world(name_or_path, params)


def check_start(world: World, pose: tuple[float, float, float] | None, params: QCarParams = DEFAULT_PARAMS,
                option: str = "--start") -> None:
    """Refuse a start pose off the world's floor, or with the car standing inside a solid."""
    if pose is None or world is None:
        return
    from qcarlab.experiments.safety import Clearance

    x, y, yaw = pose
    x0, y0, x1, y1 = world.bounds
    text = f"{x:g},{y:g},{yaw:g}"
    if not (x0 <= x <= x1 and y0 <= y <= y1):
        raise InputError(f"{option} {text}: ({x:g}, {y:g}) is outside the world '{world.name}', which spans "
                         f"x {x0:g}..{x1:g} m, y {y0:g}..{y1:g} m")
    if Clearance(world, params)(x, y, yaw)[0] <= 0.0:
        raise InputError(f"{option} {text}: the car would stand inside an obstacle (or a wall) of '{world.name}'")


def topdown_map(world: World, px_per_m: float = 50.0, **render: Any) -> tuple[np.ndarray, list[float]]:
    """The world seen from above (:func:`render_topdown`, given ``render``'s keywords such as
    ``t``, ``show_start``, ``scale_bar``) and its extent ``[xmin, xmax, ymin, ymax]`` in metres,
    for drawing it under world-frame data (matplotlib's ``imshow(extent=...)``). The extent comes
    from :func:`world_to_pixel`, so it includes the renderer's margin round the world."""
    img = render_topdown(world, px_per_m=px_per_m, **render)
    col0, row0 = world_to_pixel(world, [(0.0, 0.0)], px_per_m)[0]
    x0 = -(col0 + 0.5) / px_per_m  # the world x of the image's left edge (pixel centres at +0.5)
    y1 = (row0 + 0.5) / px_per_m  # the world y of its top edge
    h, w = img.shape[:2]
    return img, [x0, x0 + w / px_per_m, y1 - h / px_per_m, y1]


def figure_map(world: World, most_px_per_m: float = 80.0, longest_px: int = 2400,
               **render: Any) -> tuple[np.ndarray, list[float]]:
    """:func:`topdown_map` at a resolution fit for a figure: ``most_px_per_m``, less on a large
    world so that the longer side stays within ``longest_px``; no scale bar (the axes are in m)."""
    xmin, ymin, xmax, ymax = world.bounds
    span = max(xmax - xmin, ymax - ymin, 1e-6) + 0.5
    render.setdefault("scale_bar", False)
    return topdown_map(world, px_per_m=min(most_px_per_m, longest_px / span), **render)


def label_views(views: dict[str, Any]) -> dict[str, np.ndarray]:
    """Each camera view with its camera's name in a band across its top (BGR images, copied)."""
    import cv2

    out = {}
    for name, img in views.items():
        im = np.ascontiguousarray(img).copy()
        h = max(18, im.shape[0] // 16)
        scale = h / 30.0
        cv2.rectangle(im, (0, 0), (im.shape[1] - 1, h + 6), (0, 0, 0), -1)
        cv2.putText(im, name, (8, h), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), max(1, int(scale * 2)),
                    cv2.LINE_AA)
        out[name] = im
    return out
