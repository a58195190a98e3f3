"""The ``qcarlab`` command line: parse, call an experiment, print. Nothing else lives here."""

from __future__ import annotations

from qcarlab.cli.app import app, main
from qcarlab.cli import io_test  # noqa: F401  (registers io-test)
from qcarlab.cli.pending import register_pending

register_pending(built={"io-test"})

__all__ = ["app", "main"]
