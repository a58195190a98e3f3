"""The commands a student types, timed whole, beside the code before (issue 28's targets).

    python benchmarks/bench_commands.py                          # every command, 3 runs each
    python benchmarks/bench_commands.py --against /tmp/before    # alternated with the checkout in DIR
    python benchmarks/bench_commands.py --only stop-sign --reps 5
    python benchmarks/bench_commands.py --first --against /tmp/before     # a student's first lab after an install

``--first``: the first ``stop-sign`` after an install (numba's cache and qcarlab's raster cache
empty, fresh folders each run): ``cold`` is ``python -m qcarlab stop-sign`` (it compiles the
simulator's kernels); ``ours`` is a student at a terminal who typed ``qcarlab template stop-sign``
before it (its warm server compiles the kernels in the background; the wait for it is printed,
then the lab is timed); ``before`` is the checkout in DIR's first ``stop-sign``.

Each command first runs once untimed on each side (as a student's second run: the bytecode
written, numba's cache and the simulator's rasters on disk). Each timed run is a fresh process
with the defaults and ``--json`` (only to read the simulated duration from the results; the
table it replaces costs nothing measurable), timed by the wall clock from the start of the
process to its end, imports and all. Three sides:

- ``ours``: the ``qcarlab`` command as a student at a terminal runs it after their first lab
  command (:mod:`qcarlab.warm`: the console script's code, ``QCARLAB_WARM=1`` standing in for the
  terminal; the warm server is started once before the timing, and its start is printed);
- ``cold``: ours without the warm server (``python -m qcarlab``): a student's first command,
  and scripts, pipes and CI, which run cold unless they ask;
- ``before``: ``python -m qcarlab`` of the checkout in ``--against DIR``.

The targets are judged on ``ours``; ``cold`` is printed beside it. The real-time
factor is the simulated seconds over those wall seconds. ``serve`` is the time from starting
``qcarlab serve --port 0`` until a client's first readout comes back. With ``--against DIR`` the
same runs of the checkout in DIR (``PYTHONPATH=DIR``, the same interpreter and packages)
alternate with ours, so a change of the machine's load hits both. A figure a run did not
measure says "not measured", never "met".

Run it with the Python of a student's install (``pip install .``, no extras): with scipy present
(the ``bench`` extra brings it) numba imports ``scipy.linalg`` when the camera's kernels load, some
0.1-0.2 s a run that a student's install does not pay; the script says so when it sees scipy.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import load_note, machine  # noqa: E402

# name -> (the words after "qcarlab", target: real-time factor, or wall seconds for --help)
COMMANDS = {
    "--help": (["--help"], ("wall", 0.3)),
    "path-follow butterfly --size 2": (["path-follow", "butterfly", "--size", "2"], ("rtf", 80.0)),
    "stop-sign": (["stop-sign"], ("rtf", 10.0)),
    "avoid --world hallway --duration 60": (["avoid", "--world", "hallway", "--duration", "60"], ("rtf", 60.0)),
    "lane-follow --duration 60": (["lane-follow", "--duration", "60"], ("rtf", 30.0)),
    "serve ready": (None, ("wall", 1.0)),
}


#: the console script's code (``qcarlab`` as installed: pip writes these lines into bin/qcarlab)
CLIENT = "import sys; sys.argv[0] = 'qcarlab'; from qcarlab.warm import main; sys.exit(main())"
WARM_DIR = tempfile.mkdtemp(prefix="qw")  # this run's own warm server, stopped at the end


def env_for(against: str | None, how: str = "cold") -> dict[str, str]:
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    env.pop("PYTHONDONTWRITEBYTECODE", None)  # a student's Python keeps its bytecode (0.3 s a run otherwise)
    # this checkout or the one in DIR (an editable install may point at another checkout)
    env["PYTHONPATH"] = against or str(ROOT)
    env["QCARLAB_WARM"] = "1" if how == "warm" else "0"
    env["QCARLAB_WARM_DIR"] = WARM_DIR
    return env


def argv_for(how: str) -> list[str]:
    return [sys.executable, "-c", CLIENT] if how == "warm" else [sys.executable, "-m", "qcarlab"]


def run_command(words: list[str], against: str | None, cwd: Path, how: str = "cold") -> tuple[float, float | None]:
    """(wall seconds, simulated seconds or None) of one fresh ``qcarlab WORDS``."""
    json_words = [] if words == ["--help"] else ["--json"]
    t0 = time.perf_counter()
    done = subprocess.run([*argv_for(how), *words, *json_words], capture_output=True, text=True,
                          env=env_for(against, how), cwd=cwd)
    wall = time.perf_counter() - t0
    if done.returncode not in (0, 1):
        raise SystemExit(f"qcarlab {' '.join(words)} failed ({done.returncode}): {done.stderr[-400:]}")
    if not json_words:
        return wall, None
    return wall, float(json.loads(done.stdout)["duration_s"])


def serve_ready(against: str | None, cwd: Path) -> float:
    """Seconds from starting ``qcarlab serve --port 0`` to a client's first readout."""
    from qcarlab.car.tcp import TcpCar

    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "qcarlab", "serve", "--port", "0"], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env_for(against), cwd=cwd)
    try:
        port = None
        while port is None:
            line = proc.stdout.readline()
            if not line:
                raise SystemExit("qcarlab serve ended before it printed its address")
            for word in line.replace(",", " ").split():
                if word.startswith("tcp://") and ":" in word[6:]:
                    port = int(word.rsplit(":", 1)[1].strip(".)"))
        while True:
            try:
                with TcpCar("127.0.0.1", port) as car:
                    car.read()
                return time.perf_counter() - t0
            except Exception:  # noqa: BLE001 - not answering yet
                if time.perf_counter() - t0 > 60:
                    raise SystemExit("qcarlab serve did not answer within 60 s") from None
                time.sleep(0.01)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--only", action="append", help="a command's name (repeatable), e.g. stop-sign")
    ap.add_argument("--against", metavar="DIR", help="also the checkout in DIR, alternating")
    ap.add_argument("--first", action="store_true", help="the first stop-sign after an install (empty caches)")
    a = ap.parse_args()
    if a.first:
        return first_lab(a)
    chosen = {k: v for k, v in COMMANDS.items() if not a.only or k in a.only or k.split()[0] in a.only}
    sides = [("ours", None, "warm"), ("cold", None, "cold")] + ([("before", a.against, "before")] if a.against else [])
    print(machine())
    print(load_note(), flush=True)
    if importlib.util.find_spec("scipy") is not None:
        print("note: scipy is installed in this Python (a student's `pip install .` has none): numba imports "
              "scipy.linalg with the camera's kernels, 0.1-0.2 s a run more than a student's install pays")
    # a folder that holds no qcarlab: ``python -m`` puts the working folder first on the path, so
    # run from a checkout it would import that checkout's qcarlab whatever PYTHONPATH says
    cwd = Path(tempfile.mkdtemp(prefix="bench-commands-"))
    # as on a student's machine after the first run: the bytecode written, numba's cache and the
    # simulator's rasters on disk (one untimed run of each command on each side)
    for label, where, how in sides:
        src = Path(where or ROOT) / "qcarlab"
        subprocess.run([sys.executable, "-m", "compileall", "-q", str(src)], check=False, capture_output=True)
        if how == "warm":
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "qcarlab", "warm"], env=env_for(where, how), cwd=cwd, check=True,
                           capture_output=True)
            print(f"the warm server (qcarlab warm): ready in {time.perf_counter() - t0:.2f} s, once "
                  "(a student's first lab command at a terminal starts it; it stays 20 idle minutes)", flush=True)
        for name, (words, _) in chosen.items():
            serve_ready(where, cwd) if words is None else run_command(words, where, cwd, how)
    print("warm: bytecode written, numba's cache and the rasters on disk (one untimed run of each)", flush=True)
    try:
        measure(a, chosen, sides, cwd)
    finally:
        subprocess.run([sys.executable, "-m", "qcarlab", "warm", "--stop"], env=env_for(None, "warm"), cwd=cwd,
                       capture_output=True)


def first_lab(a) -> None:
    """``--first``: a fresh install's first ``stop-sign``, each run with empty caches of its own."""
    print(machine())
    print(load_note(), flush=True)
    sides = [("ours", None), ("cold", None)] + ([("before", a.against)] if a.against else [])
    walls: dict[str, list[float]] = {}
    for rep in range(a.reps):
        for label, where in sides if rep % 2 == 0 else sides[::-1]:
            fresh = Path(tempfile.mkdtemp(prefix="bench-first-"))
            try:
                wall, waited = _first_run(label, where, fresh)
            finally:
                shutil.rmtree(fresh, ignore_errors=True)
            walls.setdefault(label, []).append(wall)
            print(f"  {label:6s} first stop-sign {wall:6.2f} s{waited}   ({load_note()})", flush=True)
    print(f"\nmedians of {a.reps} ({load_note()}): " + ", ".join(
        f"{label} {statistics.median(walls[label]):.2f} s" for label, _ in sides) + " (the target: under 1 s)")


def _first_run(label: str, where: str | None, fresh: Path) -> tuple[float, str]:
    """One side's first stop-sign with the empty caches in ``fresh``: (wall seconds, what was waited)."""
    how = "warm" if label == "ours" else "cold"
    env = {**env_for(where, how), "NUMBA_CACHE_DIR": str(fresh / "numba"), "QCARLAB_CACHE": str(fresh / "qcarlab"),
           "QCARLAB_WARM_DIR": str(fresh / "warm")}
    (fresh / "warm").mkdir(mode=0o700)
    waited = ""
    try:
        if label == "ours":  # what a student types first: the lab's template (its warm server starts after it)
            subprocess.run([*argv_for(how), "template", "stop-sign", "--out", str(fresh / "lab")], env=env, cwd=fresh,
                           check=True, capture_output=True)
            t0 = time.perf_counter()
            while not list((fresh / "warm").glob("*.sock")):
                if time.perf_counter() - t0 > 600:
                    raise SystemExit("the warm server was not ready within 600 s")
                time.sleep(0.1)
            waited = f" (after the template, its server was ready in {time.perf_counter() - t0:.1f} s)"
        t0 = time.perf_counter()
        done = subprocess.run([*argv_for(how), "stop-sign", "--json"], env=env, cwd=fresh, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    finally:
        if label == "ours":
            subprocess.run([sys.executable, "-m", "qcarlab", "warm", "--stop"], env=env, cwd=fresh, capture_output=True)
    if done.returncode != 0:
        raise SystemExit(f"{label}: stop-sign failed ({done.returncode}): {done.stderr[-400:]}")
    return wall, waited


def measure(a, chosen, sides, cwd) -> None:
    walls: dict[tuple[str, str], list[float]] = {}
    sims: dict[tuple[str, str], float] = {}
    for rep in range(a.reps):
        for label, where, how in sides if rep % 2 == 0 else sides[::-1]:
            for name, (words, _) in chosen.items():
                if words is None:  # serve is no lab command: cold on every side
                    wall, sim = serve_ready(where, cwd), None
                else:
                    wall, sim = run_command(words, where, cwd, how)
                walls.setdefault((name, label), []).append(wall)
                if sim is not None:
                    sims[(name, label)] = sim
                rtf = f", {sim / wall:6.1f}x real time" if sim else ""
                print(f"  {label:6s} {name:38s} {wall:6.2f} s{rtf}   ({load_note()})", flush=True)
    print(f"\nmedians of {a.reps} ({load_note()}):")
    print(f"  {'command':38s} " + " | ".join(f"{label:>22s}" for label, _, _ in sides) + " | target")
    for name, (_, (kind, target)) in chosen.items():
        cells, verdict = [], "not measured"
        for label, _, _ in sides:
            got = walls.get((name, label))
            if not got:
                cells.append(f"{'not measured':>22s}")
                continue
            wall = statistics.median(got)
            if kind == "rtf":
                value = sims[(name, label)] / wall
                cells.append(f"{value:8.1f}x ({wall:5.2f} s)".rjust(22))
                ok = value >= target
            else:
                value = wall
                cells.append(f"{wall:8.2f} s".rjust(22))
                ok = value <= target
            if label == "ours":
                verdict = "met" if ok else "MISSED"
        shown = f">= {target:g}x" if kind == "rtf" else f"<= {target:g} s"
        print(f"  {name:38s} " + " | ".join(cells) + f" | {shown}: {verdict}")


if __name__ == "__main__":
    main()
