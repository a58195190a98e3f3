"""What the command line needs of the simulator's worlds, through the experiments layer.

``cli/`` only parses, calls and prints, and never imports ``sim/`` itself: loading a world for
``--world``, listing the shipped ones, the top-down map under a figure and the CSI panorama come
from here.
"""

from __future__ import annotations

from qcarlab.sim.camera import stitch_panorama
from qcarlab.sim.render import render_topdown
from qcarlab.sim.world import list_worlds, load_world

__all__ = ["list_worlds", "load_world", "render_topdown", "stitch_panorama"]
