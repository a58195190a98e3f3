"""A warm start for the commands a student types: the start-up paid once, not on every command.

A cold ``qcarlab stop-sign`` spends some 0.75 s before its first frame: the interpreter's imports
(numpy, OpenCV, typer, rich, the lab's modules) and numba's start-up with its compiled kernels
loaded from the cache. A student types such commands again and again. At a terminal, the
``qcarlab`` command therefore hands a lab command to a per-user *warm server* that did all of that
once (:func:`qcarlab.zygote.warm_up`) and forks a process for it::

    qcarlab stop-sign            --(Unix socket: the arguments, folder, environment, sys.path,
      (this module only:             stream settings; stdin/stdout/stderr themselves)-->  warm server
       some 40 ms of Python)                                                                |  fork
           <-- "pid N" ... "exit RC" ------------------------------------------------------+
                                                                          command process: setsid, the
                                                                          client's streams, folder and
                                                                          environment, then
                                                                          qcarlab.cli.main(ARGS)

The command process is a cold process's twin: it runs the same ``qcarlab.cli.main`` on the same
arguments, streams (a terminal stays a terminal: colours, width, live views), folder and
environment, and the server was started with the same values of every variable a module reads
when it is imported (:data:`IMPORT_ENV`); so its output and exit status are a cold run's. The
server itself never runs a command, so no command sees another's state. Ctrl-C, Ctrl-Z and
``kill`` on ``qcarlab`` are passed on to the command's process group; if ``qcarlab`` dies, the
server stops the command (SIGTERM: the car is stopped) as a cold process would have been stopped.

When: ``QCARLAB_WARM`` is unset (the default): for the lab commands (:data:`COMMANDS`) typed at a
terminal (stdin and stdout are terminals). The first such command runs cold and starts the server
in the background (so do ``qcarlab`` alone, its help and version, ``labs`` and ``template`` at a
terminal: what a student types before a lab's first command); it serves the later ones and
leaves after 20 idle minutes (``QCARLAB_WARM_IDLE``, seconds). After an install, numba's cache is
empty: the server compiles the simulator's kernels first (:mod:`qcarlab.precompile`, 15-30 s
in the background), so the labs typed once it is warm do not (some 13 s of a first
``stop-sign``); a simulator's lab typed meanwhile waits for it, saying so (at most 2 minutes),
rather than compile the same kernels beside it.
``QCARLAB_WARM=1``: for the lab commands whatever the streams (the first one starts the server
and waits for it). ``QCARLAB_WARM=0``: never. Scripts, pipes, CI and the grader therefore run cold unless they ask.
``qcarlab warm`` starts, shows or stops it.

A server is one user's (a folder only they may enter, ``$XDG_RUNTIME_DIR/qcarlab-warm`` or
``/tmp/qcarlab-warm-UID``, or ``QCARLAB_WARM_DIR``; the peer's uid is checked) and one install's:
its key hashes the interpreter, qcarlab's files (paths, sizes, modification times) and the
import-time environment. A client whose key differs (qcarlab was edited or reinstalled) is told
"stale": that server stops taking commands and leaves when its own are done, and the client
starts a new one. Linux only; elsewhere every command runs cold.
"""

from __future__ import annotations

import os
import socket
import sys

from qcarlab.zygote import Lines, reap

ENV = "QCARLAB_WARM"
DIR_ENV = "QCARLAB_WARM_DIR"
IDLE_ENV = "QCARLAB_WARM_IDLE"
IDLE = 1200.0  # s without a command before the server leaves
START_TIMEOUT = 300.0  # s to wait for a server that is starting (a cold numba cache compiles first: 20 s quiet)
REQUEST_TIMEOUT = 10.0  # s for a connection to send its request
MAX_REQUEST = 16 << 20  # bytes of JSON (the environment and sys.path are most of it)
KILL_AFTER = 20.0  # s after SIGTERM before a command whose client died is killed

#: The commands the warm server runs: the labs and their tools, whose start-up is most of a run.
#: (Not ``serve``/``onboard``, long-lived servers of their own; not ``grade``, which keeps student
#: code away from every process of the user's; not ``keyboard-drive``, interactive anyway.)
COMMANDS = frozenset({"io-test", "ping", "path-gen", "path-follow", "lidar-scan", "camera", "stop-sign",
                      "lane-follow", "avoid", "detect", "blocks", "replay"})

#: What a student types before a lab command: ``qcarlab`` alone, the help, the version, the sheets,
#: a lab's template. At a terminal these start the server too (after they ran), so that the
#: student's first lab command of a session is warm; ``blocks`` is one of :data:`COMMANDS` already.
PREPARES = frozenset({"labs", "template"})
HELP = frozenset({"-h", "--help", "--version"})

#: Variables a module may read when it is imported (colours, terminal, locale, numerical
#: libraries' threads, numba, OpenCV, matplotlib, Python itself): a server serves only clients
#: with the values it was started with, which are in its key.
IMPORT_ENV = ("TERM", "COLORTERM", "NO_COLOR", "FORCE_COLOR", "PY_COLORS", "CLICOLOR", "CLICOLOR_FORCE",
              "TTY_COMPATIBLE", "TTY_INTERACTIVE", "GITHUB_ACTIONS", "CI", "COLUMNS", "LINES", "JUPYTER_COLUMNS",
              "JUPYTER_LINES", "HOME", "TMPDIR", "LANG", "LANGUAGE", "TZ", "MPLBACKEND", "MPLCONFIGDIR", "DISPLAY",
              "WAYLAND_DISPLAY", "XDG_CACHE_HOME", "XDG_CONFIG_HOME", "XDG_DATA_HOME")
IMPORT_PREFIXES = ("LC_", "PYTHON", "NUMBA_", "OPENCV_", "OMP_", "OPENBLAS_", "GOTO_", "MKL_", "NUMEXPR_",
                   "TYPER_", "_TYPER", "RICH_")  # (qcarlab reads no QCARLAB_ variable at import)
_NOT_KEYED = (ENV, DIR_ENV, IDLE_ENV)
#: What the command sets where the user has not (:func:`main`; ``python -m qcarlab`` too), keyed as
#: set: one BLAS thread, as numpy's OpenBLAS otherwise starts one per core at import, each spinning
#: some 0.1 s of CPU before it sleeps (``python -c "import numpy"``: 0.17-0.21 s of CPU against
#: 0.07-0.09 s, 2-core VM), for matrices of 2x2 to 4x4 here.
DEFAULT_ENV = {"OPENBLAS_NUM_THREADS": "1"}
_MAGIC = b"QWRM"


# --------------------------------------------------------------------------------------------
# the client: the ``qcarlab`` command
# --------------------------------------------------------------------------------------------
def main() -> None:
    """The ``qcarlab`` command: a lab command through the warm server when :func:`wanted` (and a
    server answers), else the CLI in this process as always."""
    for name, value in DEFAULT_ENV.items():  # before any import; a user's own setting wins
        os.environ.setdefault(name, value)
    argv = sys.argv[1:]
    later: list[Place] = []  # a server to start once this command has run cold
    try:
        code = run(argv, later) if wanted(argv) else None
        if prepares(argv):  # (never a command that went warm: prepares and wanted exclude each other)
            where = place()
            if where is not None:
                later.append(where)  # (start_server: not when one is up or starting)
    except KeyboardInterrupt:  # while waiting for a server to start: nothing ran
        sys.stderr.write(f"{(argv or ['qcarlab'])[0]}: interrupted\n")
        sys.exit(130)
    if code is None:
        from qcarlab.cli import main as cold

        try:
            cold(argv)
        finally:
            for where in later:  # after the command, so its warm-up does not slow this one down
                start_server(where)
        return
    _exit_as(code)


def _mode() -> str:
    value = os.environ.get(ENV, "").strip().lower()
    if value in ("0", "off", "no", "false"):
        return "off"
    return "on" if value in ("1", "on", "yes", "true") else "auto"


def wanted(argv: list[str]) -> bool:
    """Whether ``qcarlab ARGV`` goes to the warm server: a lab command (:data:`COMMANDS`), on
    Linux, not shell completion, and ``QCARLAB_WARM=1`` or (unset) at a terminal."""
    mode = _mode()
    if mode == "off" or not argv or argv[0] not in COMMANDS or not _possible():
        return False
    return mode == "on" or _at_terminal()


def prepares(argv: list[str]) -> bool:
    """Whether ``qcarlab ARGV`` is what a student types before a lab's first command (``qcarlab``
    alone, its help, :data:`PREPARES`) where a lab command would go warm (at a terminal, or
    ``QCARLAB_WARM=1``): then the server is started after it (in the background, not waited
    for), as after a first lab command at a terminal, and that command finds it warm."""
    mode = _mode()
    if mode == "off" or (argv and argv[0] not in PREPARES and argv[0] not in HELP):
        return False
    return _possible() and (mode == "on" or _at_terminal())


def _possible() -> bool:
    """Linux with fd passing and pidfds, not shell completion, the standard streams open."""
    if not sys.platform.startswith("linux") or not hasattr(socket, "send_fds") or not hasattr(os, "pidfd_open"):
        return False
    return not any(k.endswith("_COMPLETE") for k in os.environ) and _streams_open()


def _streams_open() -> bool:
    """Whether fds 0, 1 and 2 are open (``qcarlab ... <&-`` closes one: the client's own socket
    would then take its number and be handed to the command as its stdin)."""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            return False
    return True


def _at_terminal() -> bool:
    try:
        return os.isatty(0) and os.isatty(1)
    except OSError:
        return False


class Place:
    """Where this install's server lives: its folder, socket, lock file and key."""

    def __init__(self, folder: str, key: str):
        self.folder, self.key = folder, key
        lineage = key.split("-", 1)[0]
        self.socket = os.path.join(folder, f"{lineage}.sock")
        self.lock = os.path.join(folder, f"{lineage}.lock")
        self.log = os.path.join(folder, f"{lineage}.log")


def place() -> Place | None:
    """This user's and this install's server place, or None (no private folder can be made)."""
    folder = _folder()
    return Place(folder, install_key()) if folder else None


def _folder() -> str | None:
    import stat
    import tempfile

    uid = os.getuid()
    chosen = os.environ.get(DIR_ENV)
    if not chosen:
        runtime = os.environ.get("XDG_RUNTIME_DIR", "")
        base = runtime if runtime and os.path.isdir(runtime) and os.stat(runtime).st_uid == uid else tempfile.gettempdir()
        chosen = os.path.join(base, f"qcarlab-warm-{uid}" if base != runtime else "qcarlab-warm")
    try:
        os.mkdir(chosen, 0o700)
    except FileExistsError:
        pass
    except OSError:
        return None
    try:
        st = os.lstat(chosen)
    except OSError:
        return None
    # ours alone: a folder someone else made (or a link to one) is not used
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != uid or st.st_mode & 0o077:
        return None
    return chosen


def install_key() -> str:
    """``LINEAGE-CONTENT``. The lineage names a server: the interpreter and its environment (venv),
    qcarlab's folder and the import-time environment (:data:`IMPORT_ENV`, which a server must
    share with its clients), so two terminals with different colours get a server each. The content hashes qcarlab's files
    (path, size, modification time): a server whose content differs from a client's is stale."""
    import hashlib

    root = os.path.dirname(os.path.abspath(__file__))
    environ = {**DEFAULT_ENV, **os.environ}
    env = "".join(f"{name}={environ[name]}\0" for name in sorted(environ)
                  if name not in _NOT_KEYED and (name in IMPORT_ENV or name.startswith(IMPORT_PREFIXES)))
    python = f"{os.path.realpath(sys.executable)}\0{sys.prefix}\0{sys.version}"  # bin/python = bin/python3
    lineage = hashlib.sha256(f"{python}\0{root}\0{env}".encode()).hexdigest()[:16]
    h = hashlib.sha256()
    for folder, dirs, files in os.walk(root):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for name in sorted(files):
            if name.endswith((".py", ".yaml", ".yml", ".json", ".npz", ".png", ".pgm")):
                try:
                    st = os.stat(os.path.join(folder, name))
                except OSError:
                    continue
                h.update(f"{folder}/{name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    for entry in sys.path:  # a package installed, upgraded or removed changes its folder's entries
        if not entry.endswith(("site-packages", "dist-packages")):
            continue  # (not the working folder: the files a command writes would change the key)
        try:
            h.update(f"{entry}\0{os.stat(entry).st_mtime_ns}\n".encode())
        except OSError:
            continue
    return f"{lineage}-{h.hexdigest()[:24]}"


def connect(where: Place) -> socket.socket | None:
    """A connection to the server at ``where``, or None when none listens there."""
    conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        conn.connect(where.socket)
    except OSError:
        conn.close()
        return None
    return conn


def running(where: Place) -> bool:
    """Whether a server holds this install's lock (ready or still starting)."""
    import fcntl

    try:
        fd = os.open(where.lock, os.O_RDWR | os.O_CREAT, 0o600)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # closing drops a lock we took
    return False


def start_server(where: Place) -> bool:
    """Start a server for ``where`` in the background (its own session, no terminal, the
    environment of this process); it answers once it is warm. The install's lock is taken here
    and handed to the server, so there is never a moment when a starting server does not hold it
    (and never two servers). False when another holds it (one runs or is starting)."""
    import fcntl
    import subprocess

    try:
        lock = os.open(where.lock, os.O_RDWR | os.O_CREAT, 0o600)
    except OSError:
        return False
    if lock < 3:  # a standard stream was closed: Popen would put /dev/null over the lock's fd
        lock, low = fcntl.fcntl(lock, fcntl.F_DUPFD_CLOEXEC, 3), lock
        os.close(low)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(lock)
        return False
    env = {k: v for k, v in os.environ.items() if k != ENV}
    try:
        log = os.open(where.log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    except OSError:
        log = subprocess.DEVNULL
    try:
        subprocess.Popen([sys.executable, "-m", "qcarlab.warm", "serve", where.folder, where.key, str(lock)],
                         stdin=subprocess.DEVNULL, stdout=log, stderr=log, cwd="/", env=env,
                         start_new_session=True, close_fds=True, pass_fds=(lock,))
        return True
    except OSError:
        return False
    finally:
        os.close(lock)  # the server's copy holds the lock now (or, not started, it is free again)
        if isinstance(log, int) and log >= 0:
            os.close(log)


def wait_ready(where: Place, timeout: float = START_TIMEOUT) -> socket.socket | None:
    """A connection to the server once it answers (None: no server holds the lock, so none is
    starting; or not in ``timeout``)."""
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        conn = connect(where)
        if conn is not None:
            return conn
        if not running(where):
            return connect(where)
        time.sleep(0.02)
    return None


#: what the server's log says while it compiles the kernels (:func:`_precompile`)
COMPILING = "compiling the simulator's kernels first"
#: the commands that draw the simulator's frames or step its car by default: typed while the
#: server compiles the kernels, a cold run would compile the same ones beside it
SIMULATES = frozenset({"io-test", "path-follow", "lidar-scan", "camera", "stop-sign", "lane-follow", "avoid"})
COMPILE_WAIT = 120.0  # s a lab at a terminal waits for a compiling server before it runs without it


def compiling(where: Place) -> bool:
    """Whether the server starting at ``where`` compiles the kernels (its log says so) and serves
    this client's install (its key: one of a changed install's would only say "stale" when ready)."""
    return _says(where.log, f"{COMPILING} ", f"key {where.key}")


def wait_starting(where: Place, timeout: float = START_TIMEOUT, hint: str = "") -> socket.socket | None:
    """:func:`wait_ready`, saying at a terminal (stdin, stdout and stderr) why while the server
    compiles the kernels (once after an install, 15-30 s): ``qcarlab: waiting for the warm
    server, which compiles ...`` and, when it answers, ``ready after N s`` (or ``gave up``). A
    server that warms up without compiling (a second or two) is waited for without a word.
    ``hint``: what else the user may do, in the line's brackets. Ctrl-C ends the line and goes
    on (KeyboardInterrupt): nothing ran."""
    import time

    started = time.monotonic()
    deadline = started + timeout
    tell = _at_terminal() and os.isatty(2)
    said = False
    try:  # (from the line's first byte on: a Ctrl-C as it appears still ends it)
        while True:
            conn = wait_ready(where, max(0.0, min(0.25, deadline - time.monotonic())))
            if conn is not None or time.monotonic() >= deadline or not running(where):
                break
            if tell and not said and compiling(where):
                said = True
                sys.stderr.write("qcarlab: waiting for the warm server, which compiles the simulator's kernels once "
                                 f"after an install (15-30 s; Ctrl-C stops{hint})...")
                sys.stderr.flush()
    except KeyboardInterrupt:
        if said:
            sys.stderr.write("\n")  # (the caller says it was interrupted)
        raise
    if said:
        how = "ready" if conn is not None else "gave up"
        sys.stderr.write(f" {how} after {time.monotonic() - started:.0f} s\n")
        sys.stderr.flush()
    return conn


def _says(path: str, *texts: str) -> bool:
    """Whether the first 4 kB of the file at ``path`` hold every one of ``texts`` (read once)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return all(text.encode() in head for text in texts)


def ask(conn: socket.socket, request: dict, fds: list[int] | None = None) -> None:
    """Send ``request`` (JSON), with ``fds`` passed alongside (SCM_RIGHTS)."""
    import json

    payload = json.dumps(request).encode()
    socket.send_fds(conn, [_MAGIC + len(payload).to_bytes(4, "big")], fds or [])
    conn.sendall(payload)


def run(argv: list[str], later: list[Place]) -> int | None:
    """Run ``qcarlab ARGV`` in a process forked by the warm server: its exit status (negative: the
    signal that ended it), or None when it was not run there (the caller runs it cold). With no
    server up, ``QCARLAB_WARM=1`` starts one and waits for it; at a terminal (the default) the
    command runs cold and the place goes to ``later`` (the caller starts the server after it).
    At a terminal a simulator's command (:data:`SIMULATES`) typed while the server compiles the
    kernels after an install waits for it (at most :data:`COMPILE_WAIT`), saying so."""
    mode = _mode()
    where = place()
    if where is None:
        return None
    for attempt in range(2):  # the second after a stale server gave way
        conn = connect(where)
        if conn is None and mode != "on" and argv[0] in SIMULATES and running(where) and compiling(where):
            # the server compiles the kernels this command would compile itself: it answers sooner
            conn = wait_starting(where, COMPILE_WAIT, hint=", QCARLAB_WARM=0 runs without it")
        if conn is None:
            if mode != "on":
                later.append(where)
                return None  # this one cold; the next finds the server warm
            start_server(where)  # unless one runs or is starting
            conn = wait_starting(where)
            if conn is None:
                return None
        code = _run_on(conn, argv, where)
        if code != "stale":
            return code
    return None


#: the resource limits a shell's ``ulimit`` sets that a command must keep (the server's may differ)
LIMITS = ("RLIMIT_AS", "RLIMIT_CPU", "RLIMIT_DATA", "RLIMIT_FSIZE", "RLIMIT_NOFILE", "RLIMIT_CORE", "RLIMIT_STACK",
          "RLIMIT_NPROC")


def _limits() -> dict[str, list[int]]:
    import resource

    return {name: list(resource.getrlimit(getattr(resource, name))) for name in LIMITS if hasattr(resource, name)}


def _streams() -> list[list]:
    out = []
    for stream in (sys.stdin, sys.stdout, sys.stderr):
        out.append([getattr(stream, "encoding", None) or "utf-8", getattr(stream, "errors", None) or "strict",
                    bool(getattr(stream, "line_buffering", False)), bool(getattr(stream, "write_through", False))])
    return out


def _run_on(conn: socket.socket, argv: list[str], where: Place) -> int | str | None:
    import signal

    try:
        cwd = os.getcwd()
    except OSError:
        conn.close()
        return None
    umask = os.umask(0o022)
    os.umask(umask)
    request = {"kind": "run", "key": where.key, "argv": argv, "argv0": sys.argv[0] if sys.argv else "qcarlab",
               "cwd": cwd, "env": dict(os.environ), "path": list(sys.path), "umask": umask, "streams": _streams(),
               "limits": _limits()}
    child: list[int] = []
    pending: list[int] = []

    def forward(signum: int, frame: object) -> None:
        if not child:
            pending.append(signum)
            return
        if signum == signal.SIGTSTP:  # Ctrl-Z: the command stops, then this process
            # SIGSTOP: the command's group has no parent in its session (an orphaned group), and
            # the kernel drops a SIGTSTP sent to one
            _signal_group(child[0], signal.SIGSTOP)
            os.kill(os.getpid(), signal.SIGSTOP)  # (this one too: never dropped, the shell sees a stop)
            _signal_group(child[0], signal.SIGCONT)  # here again after fg/bg: so is the command
            return
        _signal_group(child[0], signum)

    forwarded = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGTSTP, signal.SIGWINCH)
    previous = {s: signal.signal(s, forward) for s in forwarded}
    lines = Lines(conn)
    try:
        try:
            ask(conn, request, [0, 1, 2])
            first = lines.next()
        except OSError:
            return None
        if first == "stale":
            return "stale"
        if not first.startswith("pid "):
            return None  # refused before anything ran: the caller runs it cold
        child.append(int(first.split()[1]))
        for signum in pending:
            forward(signum, None)
        try:
            last = lines.next()
        except OSError:
            last = ""
        if last.startswith("exit "):
            return int(last.split()[1])
        _wait_gone(child[0])  # the server died (killed): the command may still run; its status is lost
        sys.stderr.write("qcarlab: the warm server was killed under the command; its exit status is lost\n")
        return 1
    finally:
        conn.close()
        for s, handler in previous.items():
            signal.signal(s, handler)


def _wait_gone(pid: int) -> None:
    """Until process ``pid`` (not ours: no status) has ended."""
    import select

    try:
        fd = os.pidfd_open(pid)
    except OSError:
        return
    try:
        while not select.select([fd], [], [], None)[0]:
            pass
    finally:
        os.close(fd)


def _signal_group(pid: int, signum: int) -> None:
    for kill in (os.killpg, os.kill):
        try:
            kill(pid, signum)
            return
        except (ProcessLookupError, PermissionError):
            continue


def _exit_as(code: int) -> None:
    """Exit with ``code``; a negative one is the signal that ended the command: end by it too (a
    shell then sees what it would have seen), else 128 + the signal."""
    if code < 0:
        import signal

        sys.stdout.flush()
        signal.signal(-code, signal.SIG_DFL)
        os.kill(os.getpid(), -code)
        code = 128 - code
    sys.exit(code)


# --------------------------------------------------------------------------------------------
# the server: ``python -m qcarlab.warm serve FOLDER KEY``
# --------------------------------------------------------------------------------------------
def serve(folder: str, key: str, lock: int | None = None) -> int:
    """Warm up, then fork a process for each command until idle (or stale, or asked to stop).
    ``lock``: the install's lock, already taken by the starter (:func:`start_server`)."""
    import fcntl
    import gc
    import threading
    import time

    where = Place(folder, key)
    if lock is None:
        lock = os.open(where.lock, os.O_RDWR | os.O_CREAT, 0o600)
        for _ in range(50):  # a client's look (:func:`running`) holds it for microseconds; a server for good
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError:
                time.sleep(0.01)
        else:
            return 0  # another server has this install
    os.set_inheritable(lock, False)
    started = time.monotonic()
    _precompile(key)
    consoles = _Consoles()
    from qcarlab.zygote import MODULES, lab_modules, warm_up

    warm_up(MODULES + lab_modules())
    consoles.stop()
    gc.collect()
    gc.freeze()  # what the server loaded stays out of every command's collections
    if threading.active_count() > 1:
        print("not warm: the warm-up started a thread", flush=True)
        return 1
    try:
        os.unlink(where.socket)  # a dead server's (the lock is ours)
    except FileNotFoundError:
        pass
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(where.socket)
    listener.listen(16)
    ready = time.monotonic() - started
    print(f"warm in {ready:.2f} s: pid {os.getpid()}, {where.socket}", flush=True)
    return _Server(where, listener, lock, consoles, ready).loop()


def _precompile(key: str) -> None:
    """After an install numba's cache is empty: the simulator's kernels are compiled now, in a
    process of their own (:mod:`qcarlab.precompile`: it draws frames, with OpenCV, which a
    server that forks must not run), so the labs typed once it is warm do not compile them (some
    13 s of a first ``stop-sign``). Its lines go to the server's log; it ends with the server (a
    killed server leaves no compile running). Whatever fails here is left to the labs, which
    compile what they use themselves."""
    import signal
    import subprocess

    try:
        from qcarlab import precompile

        if not precompile.needs_compiling():
            return
        print(f"{COMPILING} (once after an install): pid {os.getpid()}, key {key}", flush=True)

        from qcarlab.sandbox import jail

        jail.libc()  # (found here: find_library runs ldconfig, no work for a child between fork and exec)

        def with_server() -> None:  # (in the child, before exec: this server has no thread yet)
            jail.prctl(jail.PR_SET_PDEATHSIG, signal.SIGTERM)

        path = os.pathsep.join(p for p in sys.path if p)  # (this server's qcarlab, whose kernels it loads)
        subprocess.run([sys.executable, "-m", "qcarlab.precompile"], stdin=subprocess.DEVNULL,
                       env={**os.environ, "PYTHONPATH": path}, timeout=precompile.TIMEOUT, check=False,
                       preexec_fn=with_server if sys.platform.startswith("linux") else None)
    except Exception as exc:  # noqa: BLE001
        print(f"the kernels were not compiled ahead: {exc}", flush=True)


class _Consoles:
    """The rich consoles made during the warm-up, with their arguments: a forked command makes each
    again on its own streams and environment (a console settles its colours when it is made)."""

    def __init__(self) -> None:
        from rich.console import Console

        self.made: list[tuple] = []
        self.original = Console.__init__
        made, original = self.made, self.original

        def recording(console, *args, **kwargs):
            original(console, *args, **kwargs)
            made.append((console, args, kwargs))

        Console.__init__ = recording

    def stop(self) -> None:
        from rich.console import Console

        Console.__init__ = self.original

    def remake(self) -> None:
        for console, args, kwargs in self.made:
            self.original(console, *args, **kwargs)


class _Server:
    def __init__(self, where: Place, listener: socket.socket, lock: int, consoles: _Consoles, ready: float):
        import selectors
        import time

        self.where, self.listener, self.lock, self.consoles, self.ready = where, listener, lock, consoles, ready
        self.bound = os.stat(where.socket).st_ino  # the socket file this server made
        self.started = time.time()
        self.sel = selectors.DefaultSelector()
        self.sel.register(listener, selectors.EVENT_READ, ("accept", None))
        self.commands: dict[int, dict] = {}  # pid -> {"conn", "pidfd"}
        self.served = 0
        self.accepting = True
        self.idle = float(os.environ.get(IDLE_ENV) or IDLE)
        self.pending: dict[socket.socket, dict] = {}  # connections whose request is still coming
        self.kill_at: dict[int, float] = {}  # commands told to stop (their client died): when to kill them

    def loop(self) -> int:
        import selectors
        import signal
        import time

        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
        # SIGTERM (a logout, ``kill``): no new commands; those running finish and report as before
        wake_r, wake_w = socket.socketpair()
        wake_r.setblocking(False)
        wake_w.setblocking(False)
        self.wake = (wake_r, wake_w)
        signal.set_wakeup_fd(wake_w.fileno())
        signal.signal(signal.SIGTERM, lambda signum, frame: None)
        self.sel.register(wake_r, selectors.EVENT_READ, ("signal", None))
        self.last = time.monotonic()  # the last command's start or end: the idle time counts from it
        while self.accepting or self.commands:
            now = time.monotonic()
            deadlines = [t for t in self.kill_at.values()] + [r["until"] for r in self.pending.values()]
            if not self.commands:
                deadlines.append(self.last + self.idle)
            events = self.sel.select(max(0.0, min(deadlines) - now) if deadlines else None)
            now = time.monotonic()
            if not events and not self.commands and not self.pending and now - self.last >= self.idle:
                break
            for key, _ in events:
                what, data = key.data
                if what == "accept":
                    self._accept()
                elif what == "request":
                    self._read(key.fileobj, data)
                elif what == "hangup":  # the client went away (killed): stop its command as Ctrl-C would
                    try:
                        gone = not key.fileobj.recv(64)
                    except OSError:
                        gone = True
                    if gone:
                        self.sel.unregister(key.fileobj)
                        if data in self.commands:
                            _signal_group(data, signal.SIGTERM)
                            self.kill_at[data] = now + KILL_AFTER
                elif what == "exit":
                    self._reap(data)
                elif what == "signal":
                    try:
                        got = key.fileobj.recv(64)
                    except OSError:
                        got = b""
                    if signal.SIGTERM in got:
                        self._stop_taking()
            for pid, t in list(self.kill_at.items()):
                if now >= t and pid in self.commands:  # it did not stop: as ``kill -9``
                    _signal_group(pid, signal.SIGKILL)
                    del self.kill_at[pid]
            for conn, r in list(self.pending.items()):
                if now >= r["until"]:  # a connection that sends no request in time holds nothing up
                    self._drop(conn)
        self._stop_taking()
        return 0

    def _accept(self) -> None:
        import selectors
        import struct
        import time

        try:
            conn, _ = self.listener.accept()
        except OSError:
            return
        try:
            creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
            if struct.unpack("3i", creds)[1] != os.getuid():
                raise ValueError("another user")
            conn.setblocking(False)
        except (OSError, ValueError):
            conn.close()
            return
        state = {"until": time.monotonic() + REQUEST_TIMEOUT, "size": None, "fds": [], "payload": bytearray()}
        self.pending[conn] = state
        self.sel.register(conn, selectors.EVENT_READ, ("request", state))

    def _drop(self, conn: socket.socket) -> None:
        state = self.pending.pop(conn, None)
        if state is not None:
            for fd in state["fds"]:
                os.close(fd)
            state["fds"] = []
        try:
            self.sel.unregister(conn)
        except (KeyError, ValueError):
            pass
        conn.close()

    def _read(self, conn: socket.socket, state: dict) -> None:
        """Read what has come of a request (never waiting): the head (magic, size, the fds), then
        the JSON; a whole request is answered or forked. Anything malformed closes the connection."""
        import json

        try:
            if state["size"] is None:
                head, fds, _, _ = socket.recv_fds(conn, 8, 3)
                state["fds"] = list(fds)
                if len(head) != 8 or head[:4] != _MAGIC:
                    raise ValueError("not a client of ours")
                state["size"] = int.from_bytes(head[4:], "big")
                if state["size"] > MAX_REQUEST:
                    raise ValueError("too large")
            want = state["size"] - len(state["payload"])
            if want > 0:
                chunk = conn.recv(min(1 << 20, want))
                if not chunk:
                    raise ValueError("short request")
                state["payload"] += chunk
                if len(chunk) < want:
                    return
            request = json.loads(bytes(state["payload"]))
            if not isinstance(request, dict):
                raise ValueError("not a request")
        except BlockingIOError:
            return
        except Exception:  # noqa: BLE001 - whatever a peer sends, the server goes on
            self._drop(conn)
            return
        fds = state["fds"]
        state["fds"] = []
        self.pending.pop(conn, None)
        self.sel.unregister(conn)
        try:
            conn.setblocking(True)
            conn.settimeout(5.0)
            self._answer(conn, request, fds)
        except Exception:  # noqa: BLE001
            for fd in fds:
                try:
                    os.close(fd)
                except OSError:
                    pass
            conn.close()

    def _answer(self, conn: socket.socket, request: dict, fds: list[int]) -> None:
        import json

        kind = request.get("kind")
        if kind == "status":
            conn.sendall((json.dumps(self.status()) + "\n").encode())
            raise ValueError("answered")
        if kind == "stop":
            self._stop_taking()  # first: the lock is free when the client hears it
            conn.sendall(b"stopping\n")
            raise ValueError("answered")
        fields = ("key", "argv", "argv0", "cwd", "env", "path", "umask", "streams")
        if kind != "run" or len(fds) != 3 or any(f not in request for f in fields):
            raise ValueError("not a command")
        if not self.accepting or request["key"] != self.where.key:  # a client of a changed install
            self._stop_taking()
            conn.sendall(b"stale\n")
            raise ValueError("stale")
        self._fork(conn, request, fds)

    def _fork(self, conn: socket.socket, request: dict, fds: list[int]) -> None:
        import selectors
        import time

        keep = [self.listener.fileno(), self.sel.fileno(), self.lock, conn.fileno()] + [w.fileno() for w in self.wake]
        keep += [c["pidfd"] for c in self.commands.values()] + [c["conn"].fileno() for c in self.commands.values()]
        keep += [c.fileno() for c in self.pending] + [fd for r in self.pending.values() for fd in r["fds"]]
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _command(request, fds, keep, self.consoles)  # never returns
        for fd in fds:
            os.close(fd)
        self.served += 1
        self.last = time.monotonic()
        pidfd = os.pidfd_open(pid)
        self.commands[pid] = {"conn": conn, "pidfd": pidfd}
        try:
            conn.sendall(f"pid {pid}\n".encode())
        except OSError:
            pass
        self.sel.register(pidfd, selectors.EVENT_READ, ("exit", pid))
        self.sel.register(conn, selectors.EVENT_READ, ("hangup", pid))

    def _reap(self, pid: int) -> None:
        import time

        command = self.commands.pop(pid)
        self.kill_at.pop(pid, None)
        self.last = time.monotonic()
        reap(self.sel, pid, command["pidfd"], command["conn"])
        if not self.commands:  # between commands: what a command compiled since is loaded for the next ones
            from qcarlab.zygote import load_cached_kernels

            if load_cached_kernels():
                import gc

                gc.freeze()

    def status(self) -> dict:
        return {"pid": os.getpid(), "key": self.where.key, "socket": self.where.socket, "warm_in_s": round(self.ready, 3),
                "since": self.started, "served": self.served, "commands_running": len(self.commands), "idle_s": self.idle,
                "python": sys.executable}

    def _stop_taking(self) -> None:
        """Take no more commands: the socket and the lock go (a new server may start now); the
        commands running finish and report as before."""
        if not self.accepting:
            return
        self.accepting = False
        try:
            if os.stat(self.where.socket).st_ino == self.bound:  # ours, not a newer server's
                os.unlink(self.where.socket)
        except OSError:
            pass
        try:
            self.sel.unregister(self.listener)
        except (KeyError, ValueError):
            pass
        self.listener.close()
        os.close(self.lock)


def _command(request: dict, fds: list[int], inherited: list[int], consoles: _Consoles) -> None:
    """In the forked command process: the client's session-free twin (its own process group), its
    streams, folder, environment and sys.path, then ``qcarlab.cli.main(ARGS)``; exits like the
    interpreter. Never returns."""
    import signal

    from qcarlab.zygote import after_fork, run_as_interpreter

    try:
        os.setsid()
        after_fork()
        _name(f"qcarlab {request['argv'][0] if request['argv'] else ''}")
        signal.set_wakeup_fd(-1)
        for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGTSTP, signal.SIGCHLD):
            signal.signal(s, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)  # as the interpreter sets it
        for fd in inherited:
            try:
                os.close(fd)
            except OSError:
                pass
        for target, fd in enumerate(fds):
            os.dup2(fd, target)
            os.close(fd)
        os.chdir(request["cwd"])
        os.umask(int(request["umask"]))
        _limits_on(request.get("limits", {}))
        os.environ.clear()
        os.environ.update(request["env"])
        sys.argv = [request["argv0"], *request["argv"]]
        sys.path[:] = request["path"]
        _streams_on(request["streams"])
        consoles.remake()
        from qcarlab.cli import main
    except BaseException:  # noqa: BLE001
        os._exit(1)
    run_as_interpreter(lambda: main(list(request["argv"])))


def _name(text: str) -> None:
    """The process's name as ``ps -e``, ``top`` and ``pkill`` show it (15 bytes: "qcarlab stop-si"),
    instead of the server's "python3"."""
    try:
        from qcarlab.sandbox.jail import libc

        libc().prctl(15, text.encode()[:15], 0, 0, 0)  # PR_SET_NAME
    except Exception:  # noqa: BLE001 - a name only
        pass


def _limits_on(limits: dict[str, list[int]]) -> None:
    """The client's resource limits (a limit above what the server may have stays the server's)."""
    import resource

    for name, (soft, hard) in limits.items():
        which = getattr(resource, name, None)
        if which is None:
            continue
        try:
            resource.setrlimit(which, (soft, hard))
        except (ValueError, OSError):
            try:
                resource.setrlimit(which, (soft, resource.getrlimit(which)[1]))
            except (ValueError, OSError):
                pass


def _streams_on(settings: list[list]) -> None:
    """sys.stdin, sys.stdout and sys.stderr on fds 0, 1, 2 as the client's interpreter made them."""
    import io

    made = []
    for fd, (encoding, errors, line_buffering, write_through) in enumerate(settings):
        raw = io.FileIO(fd, "rb" if fd == 0 else "wb", closefd=False)
        raw.name = ("<stdin>", "<stdout>", "<stderr>")[fd]
        buffered = io.BufferedReader(raw) if fd == 0 else io.BufferedWriter(raw)
        made.append(io.TextIOWrapper(buffered, encoding=encoding, errors=errors, newline="\n",
                                     line_buffering=line_buffering, write_through=write_through))
    sys.stdin, sys.stdout, sys.stderr = made
    sys.__stdin__, sys.__stdout__, sys.__stderr__ = made


# --------------------------------------------------------------------------------------------
# ``qcarlab warm``: start, show, stop
# --------------------------------------------------------------------------------------------
def status(where: Place) -> dict | None:
    """The server's own account (pid, socket, how long its warm-up took, commands served), or None."""
    import json

    line = _ask_line(where, {"kind": "status"})
    try:
        return json.loads(line) if line else None
    except ValueError:
        return None


def stop(where: Place) -> bool:
    """Ask the server to leave (it finishes the commands it runs); False when none answered."""
    return _ask_line(where, {"kind": "stop"}) == "stopping"


def _ask_line(where: Place, request: dict) -> str | None:
    """The server's one-line answer to ``request``, or None (none listens, or it did not answer)."""
    conn = connect(where)
    if conn is None:
        return None
    try:
        conn.settimeout(5.0)
        ask(conn, request)
        return Lines(conn).next()
    except OSError:
        return None
    finally:
        conn.close()


if __name__ == "__main__":
    if len(sys.argv) in (4, 5) and sys.argv[1] == "serve":
        sys.exit(serve(sys.argv[2], sys.argv[3], int(sys.argv[4]) if len(sys.argv) == 5 else None))
    sys.stderr.write("usage: python -m qcarlab.warm serve FOLDER KEY [LOCK_FD] (qcarlab starts it: 'qcarlab warm')\n")
    sys.exit(2)
