"""``python -m qcarlab`` is the ``qcarlab`` command."""

import os

# as the qcarlab command sets it (qcarlab.warm.DEFAULT_ENV: one BLAS thread), before numpy's import
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from qcarlab.cli import main  # noqa: E402

main()
