"""``python -m qcarlab`` is the ``qcarlab`` command."""

from qcarlab.cli import main

main()
