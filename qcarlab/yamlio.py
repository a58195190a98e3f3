"""Reading the YAML files users write (car parameters, worlds, paths), with one-line errors.

    data = load_yaml("my_world.yaml", "world file")
    # -> InputError "my_world.yaml line 7: mapping values are not allowed here" on bad YAML
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from qcarlab.errors import InputError

MAX_BYTES = 64 * 2**20  #: a world, a sheet or a parameter file is kilobytes; a ROS map's YAML is a few lines


def parse_yaml(text: str, source: str) -> Any:
    """``yaml.safe_load`` whose syntax errors become one line naming ``source`` and the line.

    Parsed by libyaml's safe loader when PyYAML has it (``yaml.CSafeLoader``: the same objects,
    about 8x faster: a world file in ~1 ms instead of ~8), else by the pure-Python one; text
    libyaml rejects is parsed again by the pure-Python loader, whose messages are the errors'."""
    import yaml

    if len(text) > MAX_BYTES:
        raise InputError(f"{source}: {len(text):,} characters; a YAML file qcarlab reads is at most "
                         f"{MAX_BYTES // 2**20} MB")
    try:
        return yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    except (yaml.YAMLError, RecursionError):
        pass
    try:
        return yaml.safe_load(text)
    except RecursionError:
        raise InputError(f"{source}: nested too deep to read (lists or mappings inside each other "
                         "some thousand levels)") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or "malformed YAML"
        raise InputError(f"{source}{where}: {problem}") from None


def load_yaml(path: str | Path, what: str = "file") -> Any:
    """Read and parse a YAML file; a missing or unreadable file is one line too."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{p}: cannot read {what} ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{p}: the {what} is not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    return parse_yaml(text, str(p))
