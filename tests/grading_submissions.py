"""Synthetic submissions for the grading tests and benchmarks/bench_grade.py.

:func:`correct_submission` writes what a student who did every lab right hands in
(:mod:`qcarlab.grading.reference`, which ``qcarlab labs check`` grades too); :func:`write_block`
then replaces one block with a wrong or misbehaving one (a body given as text).
"""

from __future__ import annotations

from qcarlab.grading.reference import LAB_OF, REFERENCE, write_block
from qcarlab.grading.reference import reference_submission as correct_submission

__all__ = ["LAB_OF", "REFERENCE", "correct_submission", "write_block"]
