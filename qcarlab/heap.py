"""A lab's large arrays reuse the heap's memory instead of asking the kernel for fresh pages.

glibc's ``malloc`` gives a block over its mmap threshold pages of their own (128 kB to start;
raised to the size of such a block when one is freed) and gives the heap's top back to the
kernel when more than twice that lies free there. A camera lab allocates and frees blocks of
0.3-1.2 MB many times a second (a frame's colour and depth, its HSV conversion and masks), and
with the threshold moving between them many of those blocks are new pages: in a `stop-sign` run
some 30,000 page faults, each a trap into the kernel and a page zeroed (0.07-0.1 s of its 0.8-0.9
s of CPU on the development machine; 7,700 with :func:`keep_heap`, as in the labs without a
camera, which are the pages a process touches once).

:func:`keep_heap` fixes the mmap threshold at 32 MB (glibc's largest: a frame and everything made
from it comes from the heap and goes back to it) and lets up to 128 MB lie free at the heap's top
before it is given back. A lab process is short and its working set steady, so what it keeps is
what it uses again. Linux with glibc only; elsewhere nothing changes.
"""

from __future__ import annotations

import sys

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt's parameters (malloc.h)
MMAP_THRESHOLD = 32 << 20  #: bytes: blocks up to this size come from the heap (glibc's maximum on 64-bit)
TRIM_THRESHOLD = 128 << 20  #: bytes free at the heap's top before it is given back to the kernel

_done: bool | None = None


def keep_heap() -> bool:
    """Set glibc's thresholds for this process (once; forked children inherit them). True when
    they are set."""
    global _done
    if _done is None:
        _done = False
        if sys.platform.startswith("linux"):
            try:
                import ctypes

                mallopt = ctypes.CDLL(None).mallopt  # (absent under musl: AttributeError)
                _done = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
                    mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
            except (OSError, AttributeError):
                pass
    return _done


__all__ = ["keep_heap"]
