"""The ``qcarlab`` command line: parse, call an experiment, print. Nothing else lives here.

Each module below registers its subcommands on ``app``; a new lab adds a module and one line here.
"""

from __future__ import annotations

from qcarlab.cli.app import app, main
from qcarlab.cli import io_test  # noqa: F401  (io-test)
from qcarlab.cli import net  # noqa: F401  (serve, ping)
from qcarlab.cli import drive  # noqa: F401  (keyboard-drive)
from qcarlab.cli import paths  # noqa: F401  (path-gen, path-follow)
from qcarlab.cli import sensors  # noqa: F401  (lidar-scan, camera)
from qcarlab.cli import stop_sign  # noqa: F401  (stop-sign)
from qcarlab.cli import lane_follow  # noqa: F401  (lane-follow)
from qcarlab.cli import avoid  # noqa: F401  (avoid)
from qcarlab.cli import grade  # noqa: F401  (grade, labs)
from qcarlab.cli import lab  # noqa: F401  (blocks, template)
from qcarlab.cli import replay  # noqa: F401  (replay info)
from qcarlab.cli import onboard  # noqa: F401  (onboard, deploy)
from qcarlab.cli import detect  # noqa: F401  (detect lanes, detect stop-sign)

__all__ = ["app", "main"]
