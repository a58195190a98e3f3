"""The two kinds of failure a user can meet, and the exit codes the CLI maps them to.

- :class:`InputError` (exit 2): something the user typed or gave us is wrong: a bad argument,
  a malformed file, a non-finite command. The message names what is wrong and where.
- :class:`CarError` (exit 1): a runtime failure: the car is unreachable, a connection dropped.

Both are one-line messages; the CLI prints them without a traceback unless ``--debug`` is given.
"""

from __future__ import annotations


class QcarlabError(Exception):
    """Base class of every error qcarlab reports to a user."""

    exit_code = 1


class InputError(QcarlabError, ValueError):
    """Bad input: a CLI argument, a file, a command value. Exit code 2."""

    exit_code = 2


class CarError(QcarlabError, RuntimeError):
    """A runtime failure talking to the car. Exit code 1."""

    exit_code = 1


class NotBuiltError(QcarlabError):
    """A subcommand or capability that this version does not provide yet. Exit code 2."""

    exit_code = 2


class GraderFault(QcarlabError):
    """The grader's own failure while grading a task (its sandbox could not be set up, a helper
    died): never the student's. The task is run again, never scored 0. Exit code 75 (EX_TEMPFAIL)."""

    exit_code = 75
