"""A student's submission as the grader sees it, read without running any of it.

A submission is the folder ``qcarlab template LAB --out DIR`` made and the student filled: their
block files (``stop_sign.py``, ...), ``params.yaml`` (the ``lab:`` tunables) and ``answers.md``.
A repository with several labs keeps one folder per sheet, named like the sheet or the lab
(``stop-sign/``, ``path-following/`` or ``path-follow/``); :func:`folder_for` picks it (an
instructor's sheet that ``extends`` one finds the folder of the sheet it extends).

The grader reads the top-level ``*.py`` files (each at most 1 MB), ``params.yaml`` and
``answers.md``; it finds the blocks by parsing the files (``ast``), never by importing them: which
of the lab's blocks each file defines, and which are still the template's stub.
"""

from __future__ import annotations

import ast
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

from qcarlab.blocks import is_stub as _is_stub

from qcarlab.errors import InputError

_OWN = "a graded block must be your code (qcarlab's reference blocks are for your own runs, not for grading)"
MAX_FILE = 2**20  # bytes per file the grader takes from a submission
MAX_TOTAL = 8 * 2**20


@dataclass
class Submission:
    """The files of one student's submission for one sheet."""

    name: str  # the student (the folder's name)
    folder: Path
    files: dict[str, bytes] = field(default_factory=dict)  # *.py and params.yaml, by name
    answers: str | None = None
    problems: list[str] = field(default_factory=list)  # files left out, with why

    def defined(self) -> dict[str, str]:
        """Top-level function and class names -> the file that defines them (the last file in
        name order wins, as ``--use DIR`` does)."""
        out: dict[str, str] = {}
        for fname in sorted(self.files):
            if not fname.endswith(".py"):
                continue
            tree = self._tree(fname)
            if tree is None:
                continue
            for node in tree.body:
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    out[node.name] = fname
        return out

    def _tree(self, fname: str) -> ast.Module | None:
        try:
            return ast.parse(self.files[fname].decode("utf-8"), filename=fname)
        except (SyntaxError, ValueError, UnicodeDecodeError):
            return None

    def syntax_errors(self) -> list[str]:
        """One line per .py file that does not parse."""
        out = []
        for fname in sorted(self.files):
            if not fname.endswith(".py"):
                continue
            try:
                ast.parse(self.files[fname].decode("utf-8"), filename=fname)
            except SyntaxError as exc:
                out.append(f"{fname} line {exc.lineno}: syntax error: {exc.msg}")
            except (ValueError, UnicodeDecodeError) as exc:
                out.append(f"{fname}: cannot be read as Python ({exc})")
        return out

    def unfilled(self, name: str) -> bool:
        """Whether ``name`` is still the template's stub (a body that only raises NotImplementedError)."""
        fname = self.defined().get(name)
        if fname is None:
            return False
        tree = self._tree(fname)
        return tree is not None and _is_stub(tree, name)

    def borrowed(self, name: str) -> str | None:
        """Why block ``name`` is not the student's own (None when it is): a file of the submission
        imports qcarlab's reference ``name`` (``from qcarlab.control.stop_sign import stop_sign``,
        ``import qcarlab.control.stop_sign``, or ``q.stop_sign`` of a module ``q`` imported from
        qcarlab). A graded block must be the student's code; a lab run of their own may use
        qcarlab's. (What this cannot see, a dynamic import, docs/explanation/grading-sandbox.md's threat model says.)"""
        for fname in sorted(self.files):
            tree = self._tree(fname) if fname.endswith(".py") else None
            if tree is None:
                continue
            bound: set[str] = set()  # names the file binds to qcarlab's modules and objects
            for node in ast.walk(tree):
                hit = False
                if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "qcarlab":
                    bound.update(a.asname or a.name for a in node.names)
                    hit = any(a.name in (name, "*") for a in node.names) or (node.module or "").split(".")[-1] == name
                elif isinstance(node, ast.Import):
                    mods = [a for a in node.names if a.name.split(".")[0] == "qcarlab"]
                    bound.update(a.asname or a.name.split(".")[0] for a in mods)
                    hit = any(a.name.split(".")[-1] == name for a in mods)
                if hit:
                    return f"{fname} line {node.lineno}: imports qcarlab's own {name}; {_OWN}"
            for node in ast.walk(tree):
                if isinstance(node, ast.Attribute) and node.attr == name:
                    root = node.value
                    while isinstance(root, ast.Attribute):
                        root = root.value
                    if isinstance(root, ast.Name) and root.id in bound:
                        return f"{fname} line {node.lineno}: uses qcarlab's own {name}; {_OWN}"
        return None

    def param_problem(self, name: str) -> str | None:
        """Why the submission's ``params.yaml`` does not give the tunable ``name`` a value in its
        ``lab:`` section (None when it does): a choice the sheet grades must be the student's."""
        from qcarlab.yamlio import parse_yaml

        raw = self.files.get("params.yaml")
        if raw is None:
            return f"your submission has no params.yaml: the task grades your {name} (lab: {name}: ...)"
        try:
            data = parse_yaml(raw.decode("utf-8"), "params.yaml")
        except (InputError, UnicodeDecodeError) as exc:
            return f"params.yaml: {exc}"
        lab = data.get("lab") if isinstance(data, dict) else None
        if not isinstance(lab, dict) or lab.get(name) is None:
            return f"params.yaml: lab: {name} is empty: the task grades your choice of it (fill it in)"
        return None

    def block_problem(self, name: str) -> str | None:
        """Why the submission cannot be graded on block ``name`` (None when it can)."""
        fname = self.defined().get(name)
        if fname is None:
            bad = self.syntax_errors()
            more = f"; {bad[0]}" if bad else ""
            return (f"your submission has no {name} (a function or class {name} in a .py file of "
                    f"{self.folder}){more}")
        if self.unfilled(name):
            return f"{fname}: {name} is not filled in yet (its body still raises NotImplementedError)"
        return None


def folder_for(root: Path, names: list[str | None]) -> Path:
    """The submission's folder for a sheet: ROOT/NAME for the first of ``names`` (the sheet's name,
    the sheet it extends, the lab's sheet and command) that is a folder there, else ROOT."""
    for name in names:
        if name and (root / name).is_dir():
            return root / name
    return root


def read_submission(root: str | Path, names: list[str | None], student: str | None = None) -> Submission:
    """The submission in ``root`` for a sheet (see :func:`folder_for`); files too large are left
    out and said so."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"--submission {root}: not a folder")
    folder = folder_for(root, names)
    sub = Submission(student or root.resolve().name, folder)
    if student is not None and root.is_symlink():  # a class's folder that is another student's
        sub.problems.append(f"{root.name}: a symbolic link, refused (hand in a folder of your own)")
        return sub
    if folder != root and folder.is_symlink():
        sub.problems.append(f"{folder.name}/: a symbolic link, refused (hand in the folder itself)")
        return sub
    total = 0
    for path in sorted(folder.iterdir()):
        if path.name.startswith("."):
            continue
        if not (path.suffix == ".py" or path.name in ("params.yaml", "answers.md")):
            continue
        if path.is_symlink() or not path.is_file():  # never follow a link (to a classmate's file)
            kind = "a symbolic link" if path.is_symlink() else "not a regular file"
            sub.problems.append(f"{path.name}: {kind}, refused (hand in the file itself)")
            continue
        try:
            data = _read_regular(path, MAX_FILE + 1)
            size = len(data)
            if size > MAX_FILE:
                sub.problems.append(f"{path.name}: larger than {MAX_FILE // 1024} KB, left out")
                continue
            if total + size > MAX_TOTAL:
                sub.problems.append(f"{path.name}: the submission is over {MAX_TOTAL // 2**20} MB, left out")
                continue
        except OSError as exc:
            sub.problems.append(f"{path.name}: unreadable ({exc.strerror or exc})")
            continue
        total += len(data)
        if path.name == "answers.md":
            sub.answers = data.decode("utf-8", errors="replace")
        else:
            sub.files[path.name] = data
    return sub


def _read_regular(path: Path, limit: int) -> bytes:
    """At most ``limit`` bytes of a regular file, opened without following a link (so a file
    swapped for a link after it was listed is refused too)."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(0, "not a regular file")
        with os.fdopen(fd, "rb", closefd=False) as f:
            return f.read(limit)
    finally:
        os.close(fd)


def class_folders(root: str | Path) -> list[tuple[str, Path]]:
    """The students of a class folder: (name, folder) of each sub-folder, in name order."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"--class {root}: not a folder")
    found = [(p.name, p) for p in sorted(root.iterdir()) if p.is_dir() and not p.name.startswith((".", "_"))]
    if not found:
        raise InputError(f"--class {root}: no sub-folder (one per student) in it")
    return found


__all__ = ["Submission", "class_folders", "folder_for", "read_submission"]
