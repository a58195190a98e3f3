"""Grading a student's lab, or a class's, against the lab sheets (``qcarlab grade``).

- :mod:`.sheet`: the sheets (YAML in ``qcarlab/labs/``): scenario tasks and block tasks, criteria, points.
- :mod:`.checks`: pure checks of results and block outputs -> verdicts.
- :mod:`.submission`: a student's folder, read without running it.
- :mod:`.invocation`: the command a results file records, and the check that it is the task's.
- :mod:`.limits`, :mod:`.child`, :mod:`.runner`: each task in its own process under limits.
- :mod:`.schedule`: many tasks, serially, N at a time, or on Ray.
- :mod:`.grader`: planning the jobs and grading what came back.
- :mod:`.report`: grade.json, JUnit XML, the gradebook CSV, the HTML report.
"""

from qcarlab.grading.checks import Verdict, check_case, check_metrics, lookup, make_scan
from qcarlab.grading.sheet import CaseCriterion, MetricCriterion, Sheet, Task, find_sheet, load_sheet, shipped_sheets

__all__ = ["CaseCriterion", "MetricCriterion", "Sheet", "Task", "Verdict", "check_case", "check_metrics",
           "find_sheet", "load_sheet", "lookup", "make_scan", "shipped_sheets"]
