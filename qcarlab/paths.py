"""Reference paths: the lab sheet's built-in shapes (section 4.2.1), their geometry, and path files.

A path is a ``numpy`` float array of shape ``(N, 2)``: one ``(x, y)`` waypoint per row, in metres,
in the world frame (X right, Y up). The car starts at ``(0, 0)`` heading ``-Y`` (yaw = -pi/2), so
every built-in path starts there::

    >>> from qcarlab import paths
    >>> paths.line(3, 4)                         # the sheet's p1
    array([[ 0.,  0.], [ 0., -1.], [ 0., -2.], [ 0., -3.]])
    >>> p4 = paths.builtin("butterfly", width=2, height=2)   # the sheet's p4
    >>> paths.summary(p4)["tight_spots"]         # four places tighter than the car can turn
    >>> paths.write_path(p4, "p4.csv")           # CSV with a header x,y

Files users touch are CSV (``x,y`` header), ``.npy`` or YAML (see :func:`read_path`). Bad input
raises :class:`~qcarlab.errors.InputError` with one line naming the file and the line or point.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from qcarlab.constants import DEFAULT_PARAMS
from qcarlab.errors import InputError

__all__ = [
    "BUILTIN",
    "builtin",
    "butterfly",
    "circle",
    "curvature",
    "line",
    "path_length",
    "read_path",
    "summary",
    "validate_path",
    "write_path",
]

FORMATS = ("csv", "npy", "yaml")
MAX_POINTS = 100_000  #: points of a built-in path at most (a lab's path has tens to thousands)
MAX_COORD = 10_000.0  #: m: a path's coordinates at most (a lab room is metres; a campus is kilometres)
_SUFFIX_FORMAT = {".csv": "csv", ".txt": "csv", ".npy": "npy", ".yaml": "yaml", ".yml": "yaml"}


# --------------------------------------------------------------------------------------------
# built-in shapes (sheet section 4.2.1)
# --------------------------------------------------------------------------------------------
def _positive(name: str, shape: str, value: Any) -> float:
    if isinstance(value, bool):
        raise InputError(f"path '{shape}': {name} must be a positive number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"path '{shape}': {name} must be a positive number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0.0:
        raise InputError(f"path '{shape}': {name} must be a positive number, got {value!r}")
    return v


def _colon_count(stop: float, step: float) -> int:
    """Number of samples of MATLAB's ``0:step:stop`` (floor(stop/step) + 1, with a rounding tolerance)."""
    return int(math.floor(stop / step + 1e-9)) + 1


def line(length: float = 3.0, points: int = 4) -> np.ndarray:
    """Straight ahead of the start pose (along -Y): Task 1, the sheet's ``p1``.

    ``x_k = 0, y_k = -length * k / (points - 1)`` for ``k = 0 .. points-1``;
    ``line(3, 4)`` is exactly ``[[0, 0], [0, -1], [0, -2], [0, -3]]``.
    """
    length = _positive("length", "line", length)
    if isinstance(points, bool) or not isinstance(points, (int, np.integer, float)) or int(points) != points:
        raise InputError(f"path 'line': points must be a whole number >= 2, got {points!r}")
    n = int(points)
    if not 2 <= n <= MAX_POINTS:
        raise InputError(f"path 'line': points must be a whole number from 2 to {MAX_POINTS:,}, got {points!r}")
    y = np.linspace(0.0, -length, n)
    return np.column_stack([np.zeros(n), y]) + 0.0


def circle(radius: float = 1.5, step: float = 0.1) -> np.ndarray:
    """A circle driven to the LEFT (counter-clockwise) from the start pose: Task 2, the sheet's ``p2``.

    The circle passes through the start (0, 0) tangent to -Y, its centre on the car's left at
    ``(r, 0)``. With ``theta = 0:step:2*pi`` (MATLAB colon: 63 samples for step 0.1)::

        x = r * (1 - cos(theta)),   y = -r * sin(theta)

    and, as the sheet does for ``p3``, the start point ``(0, 0)`` is put first, so the defaults
    give the sheet's 64 x 2 matrix. Rows 0 and 1 are therefore both ``(0, 0)`` (a zero-length first
    segment, harmless to the followers; :func:`read_path` drops it); consecutive rows from row 1 on
    are ``step`` rad apart about the centre, and the last sample (theta = 6.2) stops
    ``r * (2*pi - 6.2)`` = 0.12 m short of closing the loop.
    """
    radius = _positive("radius", "circle", radius)
    step = _positive("step", "circle", step)
    if step >= math.pi:
        raise InputError(f"path 'circle': step must be below pi rad, got {step!r}")
    if 2.0 * math.pi / step > MAX_POINTS:
        raise InputError(f"path 'circle': step {step!r} rad makes more than {MAX_POINTS:,} points; "
                         f"give at least {2.0 * math.pi / MAX_POINTS:.2g} rad")
    theta = np.arange(_colon_count(2.0 * math.pi, step)) * step
    pts = np.column_stack([radius * (1.0 - np.cos(theta)), -radius * np.sin(theta)])
    return np.vstack([[0.0, 0.0], pts]) + 0.0


def butterfly(width: float = 4.0, height: float = 4.0) -> np.ndarray:
    """The sheet's butterfly (Task 3): ``p3`` is ``butterfly(4, 4)``, ``p4`` is ``butterfly(2, 2)``.

    With ``freq = 2*pi/30``, ``Ts = 0.033`` and ``t = 0:Ts:30`` (MATLAB colon: 910 samples, the
    last at t = 29.997 s)::

        x = W * sin(freq * t),   y = -H * sin(2 * freq * t)

    prefixed with the start point ``(0, 0)`` (``p3 = [0 xRef; 0 yRef]'``): 911 points.

    ``width`` and ``height`` are the sheet's ``wingWidth`` and ``wingHeight``, i.e. the AMPLITUDES
    W and H: the path spans x in [-W, W] and y in [-H, H] (full extents 2W x 2H). This is the
    reading that agrees with the lab: its tightest radius is about W^2 / (8 H) (at the four
    extremes of y), 0.48 m for p3 (followable: the car's minimum turning radius is
    L / tan(0.5) = 0.469 m) and 0.24 m for p4 (too tight, at four places). Taking them as full
    extents would make even p3 (0.24 m) impossible to follow.
    """
    w = _positive("width", "butterfly", width)
    h = _positive("height", "butterfly", height)
    freq = 2.0 * math.pi / 30.0
    ts = 0.033
    t = np.arange(_colon_count(30.0, ts)) * ts
    pts = np.column_stack([w * np.sin(freq * t), -h * np.sin(2.0 * freq * t)])
    return np.vstack([[0.0, 0.0], pts]) + 0.0


BUILTIN: dict[str, Callable[..., np.ndarray]] = {"line": line, "circle": circle, "butterfly": butterfly}


def builtin(name: str, **options: Any) -> np.ndarray:
    """Generate a built-in path by name (``line``, ``circle``, ``butterfly``) with its options.

    ``builtin("butterfly", width=2, height=2)``; options left out (or given as ``None``) take the
    sheet's defaults. Unknown names or options and bad values raise :class:`InputError`.
    """
    func = BUILTIN.get(name)
    if func is None:
        raise InputError(f"unknown path '{name}' (built-in paths: {', '.join(BUILTIN)})")
    known = list(inspect.signature(func).parameters)
    for key in options:
        if key not in known:
            raise InputError(f"path '{name}': unknown option '{key}' (options: {', '.join(known)})")
    return func(**{k: v for k, v in options.items() if v is not None})


# --------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------
def path_length(path: np.ndarray) -> float:
    """Polyline length ``sum_k |p_{k+1} - p_k|`` in metres."""
    p = np.asarray(path, dtype=float)
    if len(p) < 2:
        return 0.0
    return float(np.hypot(*np.diff(p, axis=0).T).sum())


def _distinct_index(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the rows that differ from their predecessor, and each row's distinct-row number."""
    keep = np.ones(len(p), dtype=bool)
    keep[1:] = np.any(p[1:] != p[:-1], axis=1)
    return np.flatnonzero(keep), np.cumsum(keep) - 1


def curvature(path: np.ndarray) -> np.ndarray:
    """Signed discrete curvature at each vertex (1/m, positive = turning left), shape ``(N,)``.

    For the triple ``a, b, c`` of consecutive distinct points it is the curvature of their
    circumcircle, ``kappa = 2 * cross(b - a, c - b) / (|b - a| * |c - b| * |c - a|)``. Repeated
    points take the value of the point they repeat; the end points are 0; a reversal in place
    (``a == c``) is ``inf``.
    """
    p = np.asarray(path, dtype=float).reshape(-1, 2)
    n = len(p)
    if n == 0:
        return np.zeros(0)
    idx, group = _distinct_index(p)
    q = p[idx]
    k = np.zeros(len(q))
    if len(q) >= 3:
        a, b, c = q[:-2], q[1:-1], q[2:]
        ab, bc, ac = b - a, c - b, c - a
        cross = ab[:, 0] * bc[:, 1] - ab[:, 1] * bc[:, 0]
        denom = np.hypot(*ab.T) * np.hypot(*bc.T) * np.hypot(*ac.T)
        with np.errstate(divide="ignore", invalid="ignore"):
            inner = np.where(denom > 0.0, 2.0 * cross / np.where(denom > 0.0, denom, 1.0), np.inf)
        k[1:-1] = inner
    return k[group]


def summary(path: np.ndarray, min_radius: float | None = None) -> dict[str, Any]:
    """Numbers a student wants before driving a path, JSON-ready.

    Returns ``points``, ``length_m``, ``bbox`` ``[xmin, ymin, xmax, ymax]``, ``tightest_radius_m``
    (``1 / max|kappa|``, ``None`` for a straight path) and ``tight_spots``: one entry per run of
    consecutive vertices whose radius ``1/|kappa|`` is below ``min_radius`` (default: the car's
    minimum turning radius L / tan(delta_max) = 0.469 m), each a dict ``index``, ``x``, ``y``,
    ``radius_m`` at the tightest vertex of the run, ``turn`` (``"left"`` or ``"right"``).
    """
    p = np.asarray(path, dtype=float).reshape(-1, 2)
    if min_radius is None:
        min_radius = DEFAULT_PARAMS.min_turning_radius
    k = curvature(p)
    kabs = np.abs(k)
    kmax = float(kabs.max()) if len(k) else 0.0
    tight = kabs * min_radius > 1.0
    spots: list[dict[str, Any]] = []
    if tight.any():
        edges = np.diff(np.concatenate([[0], tight.astype(np.int8), [0]]))
        for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
            i = int(start + np.argmax(kabs[start:stop]))
            spots.append(
                {
                    "index": i,
                    "x": float(p[i, 0]),
                    "y": float(p[i, 1]),
                    "radius_m": float(1.0 / kabs[i]) if math.isfinite(kabs[i]) else 0.0,
                    "turn": "left" if k[i] > 0 else "right",
                }
            )
    return {
        "points": int(len(p)),
        "length_m": path_length(p),
        "bbox": [float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max())]
        if len(p)
        else [0.0, 0.0, 0.0, 0.0],
        "tightest_radius_m": (float(1.0 / kmax) if math.isfinite(kmax) else 0.0) if kmax > 0 else None,
        "tight_spots": spots,
    }


# --------------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------------
def validate_path(data: Any, source: str = "path") -> np.ndarray:
    """Check and clean a path: shape ``(N, 2)``, finite, consecutive duplicates dropped, length > 0.

    ``source`` names the origin in the error message (a file name). Returns a new float array.
    """
    try:
        p = np.array(data, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{source}: expected numbers in rows of (x, y)") from None
    if p.ndim != 2 or p.shape[1] != 2:
        raise InputError(f"{source}: expected an array of shape (N, 2), got {p.shape}")
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise InputError(f"{source} point {int(np.argmax(bad)) + 1}: not a finite number")
    far = (np.abs(p) > MAX_COORD).any(axis=1)
    if far.any():
        k = int(np.argmax(far))
        raise InputError(f"{source} point {k + 1}: ({p[k, 0]:.6g}, {p[k, 1]:.6g}) m is beyond +-{MAX_COORD:,.0f} m "
                         "(a path is in metres, around the car)")
    if len(p) < 2:
        raise InputError(f"{source}: a path needs at least 2 points, got {len(p)}")
    idx, _ = _distinct_index(p)
    p = p[idx]
    if len(p) < 2:
        raise InputError(f"{source}: the path has zero length (all its points are the same)")
    return p


def _parse_number(cell: str, where: str) -> float:
    text = cell.strip()
    try:
        v = float(text)
    except ValueError:
        raise InputError(f"{where}: {text!r} is not a number") from None
    if not math.isfinite(v):
        raise InputError(f"{where}: {text!r} is not a finite number")
    return v


def _read_csv(text: str, name: str) -> list[list[float]]:
    rows: list[list[float]] = []
    first = True
    for lineno, raw in enumerate(text.splitlines(), start=1):
        stripped = raw.strip().lstrip("\ufeff")
        if not stripped or stripped.startswith("#"):
            continue
        cells = [c.strip() for c in stripped.split(",")]
        if first:
            first = False
            if [c.lower() for c in cells] == ["x", "y"]:
                continue  # the optional header
        where = f"{name} line {lineno}"
        if len(cells) != 2:
            raise InputError(f"{where}: expected two numbers x,y, got {len(cells)} values")
        rows.append([_parse_number(cells[0], where), _parse_number(cells[1], where)])
    return rows


def _read_yaml(text: str, name: str) -> list[list[float]]:
    from qcarlab.yamlio import parse_yaml

    data = parse_yaml(text, name)
    if isinstance(data, Mapping):
        if "path" not in data:
            raise InputError(f"{name}: a mapping needs the key 'path' (a list of [x, y] pairs)")
        data = data["path"]
    if data is None:
        raise InputError(f"{name}: no points (a path needs at least 2 points)")
    if not isinstance(data, list):
        raise InputError(f"{name}: expected a list of [x, y] pairs or a mapping with key 'path'")
    rows: list[list[float]] = []
    for i, item in enumerate(data, start=1):
        where = f"{name} point {i}"
        if not isinstance(item, (list, tuple)) or len(item) != 2:
            raise InputError(f"{where}: expected a pair [x, y], got {item!r}")
        pair = []
        for v in item:
            if isinstance(v, bool):
                raise InputError(f"{where}: {v!r} is not a number")
            if isinstance(v, (int, float)):
                if not math.isfinite(v):
                    raise InputError(f"{where}: {v!r} is not a finite number")
                pair.append(float(v))
            else:
                pair.append(_parse_number(str(v), where))
        rows.append(pair)
    return rows


def read_path(file: str | Path) -> np.ndarray:
    """Read a path file: ``.csv`` (or ``.txt``), ``.npy`` or ``.yaml``/``.yml``; returns ``(N, 2)``.

    - CSV: comma separated ``x,y`` per line in metres; the header line ``x,y`` is optional; blank
      lines and lines starting with ``#`` are ignored.
    - NPY: a numeric array of shape ``(N, 2)``.
    - YAML: a list of ``[x, y]`` pairs, or a mapping with the key ``path`` holding that list.

    Consecutive duplicate points are dropped. Raises :class:`InputError` (one line naming the file
    and the line or point) for a missing, empty or malformed file, a non-numeric or non-finite
    value, a row without exactly two values, fewer than 2 points, or a path of zero length.
    """
    p = Path(file)
    name = str(file)
    fmt = _SUFFIX_FORMAT.get(p.suffix.lower())
    if fmt is None:
        raise InputError(f"{name}: unknown path file type '{p.suffix}' (use .csv, .npy or .yaml)")
    if not p.exists():
        raise InputError(f"{name}: no such file")
    if p.is_dir():
        raise InputError(f"{name}: is a directory, not a path file")
    if fmt == "npy":
        try:
            data = np.load(p, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            if p.stat().st_size == 0:
                raise InputError(f"{name}: the file is empty") from None
            raise InputError(f"{name}: not a readable .npy array ({str(exc).splitlines()[0]})") from None
        if not isinstance(data, np.ndarray) or not np.issubdtype(data.dtype, np.number):
            raise InputError(f"{name}: expected a numeric array of shape (N, 2)")
        if data.ndim != 2 or data.shape[1] != 2:
            raise InputError(f"{name}: expected an array of shape (N, 2), got {data.shape}")
        return validate_path(data, name)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        reason = getattr(exc, "strerror", None) or "not a UTF-8 text file"
        raise InputError(f"{name}: cannot read ({reason})") from None
    if not text.strip():
        raise InputError(f"{name}: the file is empty (expected x,y rows)")
    rows = _read_csv(text, name) if fmt == "csv" else _read_yaml(text, name)
    if len(rows) == 0:
        raise InputError(f"{name}: no points (a path needs at least 2 points)")
    if len(rows) < 2:
        raise InputError(f"{name}: a path needs at least 2 points, got {len(rows)}")
    return validate_path(rows, name)


def write_path(path: np.ndarray, file: str | Path, fmt: str | None = None) -> Path:
    """Write a path as ``csv`` (header ``x,y``), ``npy`` or ``yaml`` (a list of ``[x, y]`` pairs).

    ``fmt`` defaults to the file's suffix (``csv`` when unknown). Numbers are written with the
    shortest repr that round-trips, so ``read_path(write_path(p, f))`` gives ``p`` back bit for bit
    (less consecutive duplicates). Parent folders are created. Returns the file written.
    """
    p = np.asarray(path, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2:
        raise InputError(f"{file}: expected a path of shape (N, 2), got {p.shape}")
    if fmt is None:
        fmt = _SUFFIX_FORMAT.get(Path(file).suffix.lower(), "csv")
    fmt = fmt.lower()
    if fmt not in FORMATS:
        raise InputError(f"unknown path format '{fmt}' (use {', '.join(FORMATS)})")
    out = Path(file)
    out.parent.mkdir(parents=True, exist_ok=True)
    p = p + 0.0  # no negative zeros in files
    if fmt == "npy":
        with out.open("wb") as fh:  # np.save would append .npy to other suffixes
            np.save(fh, p, allow_pickle=False)
    elif fmt == "csv":
        body = "".join(f"{float(x)!r},{float(y)!r}\n" for x, y in p)
        out.write_text("x,y\n" + body, encoding="utf-8")
    else:
        import yaml

        out.write_text(
            yaml.safe_dump([[float(x), float(y)] for x, y in p], default_flow_style=None, sort_keys=False),
            encoding="utf-8",
        )
    return out
