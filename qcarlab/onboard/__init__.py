"""The car side: ``car_server.py`` runs on the QCar as it ships (Python 3.6 / 3.8, the standard
library, the car's NumPy and Quanser's API); this package gives the laptop its file and copies it.

    from qcarlab.onboard import write_server
    write_server("qcarlab_car_server.py")     # what `qcarlab onboard --write FILE` does

``car_server.py`` imports nothing from qcarlab, so the one file is all the car needs.
"""

from __future__ import annotations

import os
from pathlib import Path

from qcarlab.errors import InputError

SERVER_FILE = Path(__file__).with_name("car_server.py")
DEFAULT_NAME = "qcarlab_car_server.py"
TOKEN_FILE = ".qcarlab_token"  # on the car, in the user's home, mode 600


def server_source() -> str:
    """The car-side server's source text (one standalone file)."""
    return SERVER_FILE.read_text(encoding="utf-8")


def write_server(path: str | os.PathLike, force: bool = False) -> Path:
    """Write the car-side server to ``path`` (a folder gets ``qcarlab_car_server.py``), executable."""
    target = Path(path)
    if target.is_dir():
        target = target / DEFAULT_NAME
    if target.exists() and not force:
        raise InputError(f"{target} exists; pass --force to replace it")
    if not target.parent.is_dir():
        raise InputError(f"{target.parent} is not a folder")
    try:
        target.write_text(server_source(), encoding="utf-8")
        target.chmod(0o755)
    except OSError as exc:
        raise InputError(f"cannot write {target}: {exc.strerror or exc}") from None
    return target
