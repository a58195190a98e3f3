"""The car server: exposes any :class:`~qcarlab.car.base.Car` over the qcarlab protocol.

    from qcarlab.car.sim import SimCar
    from qcarlab.net.server import CarServer

    with SimCar(seed=1, realtime=True) as car, CarServer(car, "127.0.0.1", 18960) as server:
        server.serve_forever()          # request_stop() (a signal handler) ends it; the car is stopped

One thread per connection (blocking sockets, TCP_NODELAY). The rules (docs/protocol.md, section 6):

- **one controller**: the first client that says hello as ``control`` drives; others connect as
  ``monitor`` (read-only). A second controller is refused (``busy``), unless the controller has
  gone quiet: once the watchdog has stopped the car and the controller has sent nothing for
  ``controller_timeout`` seconds, the next control hello takes over (the old one gets
  ``control_lost``). One of the ``max_clients`` slots is kept for a controller.
- **watchdog**: its own thread, waiting on nothing but the deadline and the drive lock, which is
  only ever held for one quick backend call (never for a sensor reading): no command from the
  controller for ``watchdog`` seconds -> throttle 0, wheels straight, hazard and brake lamps (in
  lock-step any frame from the controller counts, since simulated time only moves when it says so).
- **lock-step runs start from the start state**: in lock-step each new controller starts from the
  car's start state (``reset()``: start pose, at rest, time 0, noise re-seeded), so the same client
  run twice gets the same numbers.
- **the watchdog is armed by the controller's first** ``COMMAND`` **or** ``STOP``: before it the car
  stands stopped anyway, and a client that reads its first (slow) sensor frame is not stopped for it.
- **dropped connection**: when the controller leaves (bye, close, reset, protocol error) the car is
  stopped before its socket is closed.
- **limits**: every command goes through ``Car.write`` (non-finite values refused and the car
  stopped, throttle and steering clamped to the car's limits whatever the client sends).
- **deadlines**: the whole HELLO within ``hello_timeout`` of the connection, every frame within
  ``io_timeout`` of its first byte, every reply sent within ``io_timeout``; at most
  ``max_pending`` connections may be waiting for their hello (the oldest is dropped for a new one).
- **token**: a server whose socket is bound to anything but a loopback address needs a token
  (16+ characters); wrong tokens from one address are slowed down (:mod:`qcarlab.net.guard`).
- **sensors**: read off the drive lock, shared, paced for monitors (:mod:`qcarlab.net.sensors`).
- **bad input**: an error frame (or an HTTP 400) and/or a closed connection; refusals are logged
  at a bounded rate; the server keeps serving everyone else.
"""

from __future__ import annotations

import errno
import ipaddress
import logging
import math
import os
import select
import socket
import sys
import threading
import time
from collections import deque
from dataclasses import fields as dc_fields
from typing import Any

from qcarlab.car.base import Car, Readout
from qcarlab.car.lamps import parse_lamps
from qcarlab.errors import CarError, InputError, NotBuiltError, QcarlabError
from qcarlab.heap import keep_heap
from qcarlab.wire import protocol as P
from qcarlab.net.guard import RefusalLog, TokenGuard, token_matches, token_problem
from qcarlab.wire.protocol import MsgType as M
from qcarlab.net.sensors import SENSORS, NoData, SensorHub
from qcarlab.onboard.car_server import Admission, ProgressWatch, SourceLog  # one implementation for both servers (standard library only)

log = logging.getLogger("qcarlab.net")


def _log(level: int, msg: str, *args: Any) -> None:
    """Log a line; a handler that fails (a terminal gone after SIGHUP, a closed pipe) never takes a
    server thread down with it."""
    try:
        log.log(level, msg, *args)
    except Exception:
        pass

WATCHDOG_LAMPS = parse_lamps(["hazard", "brake"])
CONTROL_ONLY = frozenset({int(M.COMMAND), int(M.STOP), int(M.ADVANCE)})
_BYE, FLAG_READ_BACK, FLAGS_KNOWN = int(M.BYE), P.FLAG_READ_BACK, P.FLAGS_KNOWN  # globals: fewer lookups per request
MAX_LOGGED_ERRORS = 5  # per connection; further ones are counted and summed up at disconnect
HOUSEKEEPING_S = 0.05  # period of the housekeeping thread (log lines, the real-time simulator's clock)
SWITCH_INTERVAL_S = 0.0005  # the interpreter's thread switch interval in a serving process


def process_settings() -> tuple[Any, ...]:
    """What :func:`tune_process` changes, to give back with :func:`restore_process`."""
    try:
        sched = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, os.getpriority(os.PRIO_PROCESS, 0))
    except (AttributeError, OSError):
        sched = None
    return sys.getswitchinterval(), sched


def restore_process(saved: tuple[Any, ...]) -> None:
    interval, sched = saved
    sys.setswitchinterval(interval)
    if sched is not None:
        try:
            os.sched_setscheduler(0, sched[0], os.sched_param(sched[1]))
            os.setpriority(os.PRIO_PROCESS, 0, sched[2])
        except (AttributeError, OSError):
            pass


def tune_process(priority: bool = True) -> str:
    """Settings for a process that serves a car (``qcarlab serve``; call it before any thread is
    started): a short thread switch interval, so that a busy thread (a monitor's frame) hands over
    to the controller's or the watchdog's thread within half a millisecond instead of five; and,
    where the system allows it (root, CAP_SYS_NICE), real-time round-robin priority 5 for this
    thread and every thread it starts (else nice -10), so that other processes' load cannot leave a
    thread that holds the interpreter lock waiting for a CPU while the watchdog (priority 12) or the
    controller's thread (10) waits for that lock. Connections without a hello are served at the
    ordinary priority, monitors' requests are rate-limited: no client can take the machine's CPUs
    from its other programs. Returns the priority set."""
    if sys.getswitchinterval() > SWITCH_INTERVAL_S:
        sys.setswitchinterval(SWITCH_INTERVAL_S)
    if not priority:
        return "normal"
    try:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(PRIORITY_CLIENT))  # Linux: inherited by new threads
        return f"real-time (SCHED_RR {PRIORITY_CLIENT})"
    except (AttributeError, OSError):
        pass
    try:
        if os.getpriority(os.PRIO_PROCESS, 0) > -10:
            os.setpriority(os.PRIO_PROCESS, 0, -10)
        return "nice -10"
    except (AttributeError, OSError):
        return "normal"


# real-time priorities of the server's threads, where the system allows them (see tune_process)
PRIORITY_WATCHDOG = 12
PRIORITY_CONTROLLER = 10
PRIORITY_CLIENT = 5  # monitors, housekeeping, the main thread
MONITOR_REQUESTS_PER_S = 1000.0  # a monitor's requests are served at most this often
MONITOR_BURST = 20.0  # ... after a burst of this many


def raise_thread_priority(level: int = PRIORITY_WATCHDOG) -> str:
    """Give the calling thread real-time round-robin priority ``level`` where the system allows it
    (Linux, root or CAP_SYS_NICE), else nice -10; returns what was set. Other processes' load then
    delays it less; without the privilege nothing changes."""
    try:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(level))  # 0: this thread, on Linux
        return f"real-time (SCHED_RR {level})"
    except (AttributeError, OSError):
        pass
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), -10)
        return "nice -10"
    except (AttributeError, OSError):
        return "normal"


def ordinary_thread_priority() -> None:
    """The ordinary scheduler for the calling thread (nice -10 where allowed): for the thread that
    accepts connections, and the threads of connections that have not said hello, so that a flood
    of connections cannot take the machine's CPUs from its other programs."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), -10)
    except (AttributeError, OSError):
        pass


def _addresses(host: str) -> list[str]:
    try:
        infos = socket.getaddrinfo(host or None, None, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (OSError, UnicodeError):
        return []
    return [i[4][0] for i in infos]


def address_is_loopback(addr: str) -> bool:
    """True for a numeric loopback address (127.0.0.0/8, ::1, ::ffff:127.x.x.x)."""
    try:
        ip = ipaddress.ip_address(addr.strip("[]").split("%")[0])
    except ValueError:
        return False
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_loopback


def is_loopback(host: str) -> bool:
    """True when every address ``host`` resolves to is a loopback address. Names are resolved, never
    trusted ("localhost" mapped elsewhere by a hosts file is not loopback); the server decides
    again by the address its socket is bound to."""
    if not host:
        return False
    addrs = _addresses(host)
    return bool(addrs) and all(address_is_loopback(a) for a in addrs)


class CarServer:
    """Serve ``car`` on ``host:port`` (port 0 picks a free port; see :attr:`address`)."""

    SPIN = 0.0002  # s to look for the controller's next request before blocking on it (``spin``)

    def __init__(
        self,
        car: Car,
        host: str = "127.0.0.1",
        port: int = P.DEFAULT_PORT,
        *,
        token: str | None = None,
        watchdog: float = 0.25,
        controller_timeout: float | None = None,
        lockstep: bool | None = None,
        max_clients: int = 24,
        max_pending: int = 16,
        max_silent: int = 256,
        hello_timeout: float = 2.0,
        io_timeout: float = 5.0,
        monitor_rate: float = 10.0,
        spin: float = SPIN,
        prepare: bool = False,
        render_process: bool = False,
        priority: bool = True,
        tls: Any = None,
    ):
        if not (isinstance(port, int) and 0 <= port < 65536):
            raise InputError(f"--port must be in 0-65535, got {port!r}")
        if not (math.isfinite(watchdog) and 0.01 <= watchdog <= 60.0):
            raise InputError(f"--watchdog must be between 0.01 and 60 s, got {watchdog}")
        if controller_timeout is None:
            controller_timeout = 4.0 * watchdog
        if not (math.isfinite(controller_timeout) and 0.01 <= controller_timeout <= 3600.0):
            raise InputError(f"--controller-timeout must be between 0.01 and 3600 s, got {controller_timeout}")
        if token is not None and token != "":
            problem = token_problem(token)
            if problem:
                raise InputError(problem)
        if not 2 <= max_clients <= 1024:
            raise InputError(f"--max-clients must be in 2-1024 (one slot is kept for the controller), got {max_clients}")
        if not 1 <= max_pending <= 1024:
            raise InputError(f"max pending connections must be in 1-1024, got {max_pending}")
        if not 1 <= max_silent <= 4096:
            raise InputError(f"max silent connections must be in 1-4096, got {max_silent}")
        if not (math.isfinite(monitor_rate) and 0.1 <= monitor_rate <= 1000.0):
            raise InputError(f"--monitor-rate must be between 0.1 and 1000 Hz, got {monitor_rate}")
        self.car = car
        self.host = host
        self.port = port
        self.token = token or None
        self.watchdog = float(watchdog)
        self.controller_timeout = float(controller_timeout)
        self.lockstep = bool(car.stepped) if lockstep is None else bool(lockstep)
        if self.lockstep and not car.stepped:
            raise InputError("lock-step serving needs a stepped car (the simulator without --realtime)")
        if not self.lockstep and car.stepped:
            raise InputError("a stepped simulator can only be served in lock-step (its time moves only on advance)")
        self.max_clients = max_clients
        self.max_pending = max_pending  # connections reading their hello on a thread at once
        self.max_silent = max_silent  # connections waiting for their first bytes, without a thread
        self.admission: Admission | None = None  # holds connections before their hello (once started)
        self.hello_timeout = float(hello_timeout)
        self.io_timeout = float(io_timeout)
        self.monitor_rate = float(monitor_rate)
        self.spin = max(0.0, float(spin))
        self.prepare = prepare
        self.render_process = render_process
        self.priority = priority  # ask for real-time priority for the watchdog's and the controller's threads
        self.tls = tls  # an ssl.SSLContext (qcarlab.wire.tls.server_context): every connection speaks TLS
        self.tuned = False  # tune_process() ran: every thread is real-time, monitors stay so after their hello
        self.worker: Any = None  # the RenderWorker drawing a real-time simulator's frames, once started

        # the drive lock: held only around one quick backend call (write, read, stop, time, truth,
        # advance, fixing a sensor frame's pose); never around a sensor reading or a socket call
        self.drive_lock = threading.Lock()
        self.state_lock = threading.Lock()  # who is connected, in which role
        self.control_free = threading.Condition(self.state_lock)
        self.controller: _Session | None = None
        self.sessions: set[_Session] = set()
        self.monitors: set[_Session] = set()
        self.last_feed = time.monotonic()
        self.tripped = False
        self.trip_time = 0.0
        self.armed = False  # the watchdog guards from the controller's first command on
        self.trips = 0
        self.watchdog_priority = "normal"  # what raise_thread_priority() got for the watchdog thread
        self.trip_delays: deque[float] = deque(maxlen=1000)  # s from the last command to each stop
        self.takeovers = 0
        self.stopping = False
        self._stop_evt = threading.Event()
        self._stop_requested = False  # set by request_stop (a signal handler): a plain flag
        self._kick = threading.Event()  # wakes the watchdog: a controller came or went
        self._notes: deque[tuple[int, str, tuple[Any, ...]]] = deque(maxlen=1000)
        self.refusals = RefusalLog(log)
        self.clientlog = SourceLog(_log)  # lines about clients, at a bounded rate per address
        self.tokens = TokenGuard()
        self.sensors = SensorHub(car, self.drive_lock, lockstep=self.lockstep, monitor_rate=self.monitor_rate,
                                 stop_event=self._stop_evt)
        self.cache_readout: Readout | None = None  # lock-step: the controller's last readout
        self._listener: socket.socket | None = None
        self._threads: list[threading.Thread] = []
        self._started = False
        self._bound: tuple[str, int] | None = None
        self.welcome_base = self._welcome_base()

    # --- identity ---------------------------------------------------------------------------------
    def _welcome_base(self) -> dict[str, Any]:
        ident = self.car.identity()
        caps = [c for c in ident.capabilities if c != "lockstep"]  # the backend says what it has
        if self.lockstep:
            caps.append("lockstep")
        params = {f.name: getattr(self.car.params, f.name) for f in dc_fields(self.car.params)}
        from qcarlab import __version__

        return {
            "protocol": P.VERSION,
            "server": f"qcarlab {__version__}",
            "identity": {"name": ident.name, "backend": ident.backend, "capabilities": caps, "extra": ident.extra},
            "lockstep": self.lockstep,
            "watchdog_s": self.watchdog,
            "controller_timeout_s": self.controller_timeout,
            "throttle_limit": self.car.throttle_limit,
            "steering_limit": self.car.steering_limit,
            "max_request": P.MAX_REQUEST,
            "max_clients": self.max_clients,
            "monitor_rate_hz": self.monitor_rate,
            "hello_timeout_s": self.hello_timeout,
            "frame_timeout_s": self.io_timeout,
            "params": params,
        }

    @property
    def capabilities(self) -> list[str]:
        return list(self.welcome_base["identity"]["capabilities"])

    # --- lifecycle --------------------------------------------------------------------------------
    @property
    def address(self) -> tuple[str, int]:
        """(host, port) actually bound (the port is the real one when 0 was asked)."""
        if self._bound is not None:
            return self._bound
        return self.host, self.port

    @property
    def uri(self) -> str:
        host, port = self.address
        scheme = "tcps" if self.tls is not None else "tcp"
        return f"{scheme}://{'[' + host + ']' if ':' in host else host}:{port}"

    @property
    def loopback(self) -> bool:
        """True when the listening socket is bound to a loopback address (known after start)."""
        return self._bound is not None and address_is_loopback(self._bound[0])

    def start(self) -> CarServer:
        """Bind, get the car ready (its sensors, the compiled physics), then listen and start serving in
        background threads; returns self. Nothing listens before the car can answer."""
        if self._started:
            return self
        keep_heap()  # the frames it reads and sends from the heap, not fresh pages each (qcarlab.heap)
        listener = self._bind()
        bound = listener.getsockname()
        if not address_is_loopback(bound[0]) and not self.token:
            listener.close()
            shown = f"{self.host} ({bound[0]})" if self.host and self.host != bound[0] else (self.host or "all interfaces")
            raise InputError(
                f"refusing to serve on {shown} without a token: that address is not loopback, anyone on its "
                "network could drive the car; set QCARLAB_TOKEN (qcarlab serve --new-token makes one), or bind to 127.0.0.1"
            )
        if self.render_process and not self.lockstep and callable(getattr(self.car, "sensor_recipe", None)):
            # (a wrapper that records frames sees them pass: its sensor job's ``drawn`` hook)
            self._start_worker()
        if self.prepare and self.worker is None:
            try:
                self.car.prepare_sensors()
            except Exception as exc:  # a sensor that cannot be built fails its requests later, not the server
                _log(logging.WARNING, "could not prepare the sensors: %s", _one_line(str(exc)))
        if self.worker is None and not self.lockstep and callable(getattr(self.car, "warm_physics", None)):
            self.car.warm_physics()  # a first-use cost paid now, not under the drive lock later
        listener.listen(128)  # ready: a client that connects from now on is answered at once
        self._listener = listener
        self._bound = (bound[0], bound[1])
        self.admission = Admission(listener, self._start_session, self._refused_early, self.hello_timeout,
                                   self.max_pending, self.max_silent, plain=self.tls is None)
        self._started = True
        try:
            self.tuned = os.sched_getscheduler(0) != os.SCHED_OTHER
        except (AttributeError, OSError):
            self.tuned = False
        self._spawn(self._watchdog_loop, "qcarlab-watchdog")
        self._spawn(self._housekeeping_loop, "qcarlab-housekeeping")
        self._spawn(self._accept_loop, "qcarlab-accept")
        return self

    def _start_worker(self) -> None:
        from qcarlab.net.render_worker import KINDS, RenderWorker, WorkerGone

        kinds = tuple(k for k in KINDS if k in self.capabilities)
        if not kinds:
            return
        try:
            self.worker = RenderWorker(self.car.sensor_recipe(), kinds, build=self.prepare)
        except (WorkerGone, OSError, Exception) as exc:  # serving goes on, drawing in this process
            _log(logging.WARNING, "sensor frames are drawn in the server's own process: %s", _one_line(str(exc)))
            return
        self.sensors.worker = self.worker

    def _bind(self) -> socket.socket:
        where = f"{self.host or '*'}:{self.port}"
        try:
            infos = socket.getaddrinfo(self.host or None, self.port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        except (socket.gaierror, UnicodeError):
            raise InputError(f"--host {self.host!r}: unknown host name") from None
        if not infos:
            raise InputError(f"--host {self.host!r}: unknown host name")
        family, _, _, _, sockaddr = infos[0]
        # bind the resolved numeric address (that address, not the name, decides what is loopback); it
        # listens only when start() has the car ready to answer, so no client waits in the backlog
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            if os.name == "posix":
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(sockaddr)
            return sock
        except OSError as exc:
            sock.close()
            if exc.errno == errno.EADDRINUSE:
                raise CarError(f"cannot listen on {where}: the port is in use (another qcarlab serve?); pick another --port") from None
            if exc.errno in (errno.EACCES, errno.EPERM):
                raise CarError(f"cannot listen on {where}: permission denied (ports below 1024 need privileges)") from None
            if exc.errno == errno.EADDRNOTAVAIL:
                raise InputError(f"--host {self.host!r}: this machine has no such address") from None
            raise CarError(f"cannot listen on {where}: {exc.strerror or exc}") from None

    def _spawn(self, target: Any, name: str, *args: Any) -> threading.Thread:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads.append(thread)
        thread.start()
        return thread

    def serve_forever(self) -> None:
        """Serve until :meth:`request_stop` or :meth:`stop` is called (another thread, a signal handler)."""
        self.start()
        while not self._stop_requested and not self._stop_evt.wait(0.1):
            pass

    def request_stop(self) -> None:
        """Make :meth:`serve_forever` return within 0.1 s; then call :meth:`stop`. Safe from a signal
        handler: it only sets a flag (Event.set takes a lock that the interrupted main thread may be
        holding, inside Event.wait: a signal there deadlocked the server)."""
        self._stop_requested = True

    def stop(self) -> None:
        """Stop serving: the car is stopped, every client is told bye and disconnected."""
        if self.stopping:
            return
        self.stopping = True
        self._stop_evt.set()
        self._kick.set()
        self.safe_stop("server stopping")  # first: nothing below may delay it
        if self.admission is not None:
            self.admission.wake()
        with self.state_lock:
            sessions = list(self.sessions)
            self.control_free.notify_all()
        for s in sessions:
            s.interrupt()
        for thread in list(self._threads):
            if thread is not threading.current_thread():
                thread.join(timeout=3.0)
        for s in sessions:
            s.close_socket()
        for sock in (self._listener,):
            if sock is not None:
                try:
                    sock.close()
                except OSError:
                    pass
        self.safe_stop("server stopped")
        if self.worker is not None:
            self.worker.close()
        self._flush_notes()
        self.refusals.flush(math.inf)
        self.clientlog.flush(force=True)

    def __enter__(self) -> CarServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- the car ----------------------------------------------------------------------------------
    def safe_stop(self, why: str) -> bool:
        """Stop the car; a failing backend is logged, never raised."""
        try:
            with self.drive_lock:
                self.car.stop()
            return True
        except Exception as exc:  # the backend failed to stop: say so loudly
            _log(logging.ERROR, "could not stop the car (%s): %s", why, exc)
            return False

    def feed(self) -> None:
        self.last_feed = time.monotonic()
        if self.tripped:
            self.tripped = False
            self._kick.set()  # the watchdog waits for a new deadline

    def status(self) -> int:
        bits = 0
        if self.tripped:
            bits |= P.STATUS_WATCHDOG
        if self.controller is not None:
            bits |= P.STATUS_CONTROLLED
        if self.lockstep:
            bits |= P.STATUS_LOCKSTEP
        return bits

    def arm(self) -> None:
        """The controller's first command arms the watchdog (at once: the watchdog may be waiting)."""
        if not self.armed:
            self.armed = True
            self._kick.set()

    def note(self, level: int, msg: str, *args: Any) -> None:
        """A log line from a thread that must never block on a write (the watchdog)."""
        self._notes.append((level, msg, args))

    def _flush_notes(self) -> None:
        while self._notes:
            level, msg, args = self._notes.popleft()
            _log(level, msg, *args)

    # --- the watchdog: its own thread, the deadline and the drive lock only ------------------------
    def _watchdog_loop(self) -> None:
        self.watchdog_priority = raise_thread_priority(PRIORITY_WATCHDOG) if self.priority else "normal"
        while not self.stopping:
            self._kick.clear()
            ctl = self.controller
            now = time.monotonic()
            if ctl is None or self.tripped or not self.armed:
                self._kick.wait(0.1)
                continue
            due = self.last_feed + self.watchdog
            if self.lockstep and ctl.busy:  # in lock-step its request in progress is a sign of life
                due = max(due, now + self.watchdog)
            if now < due:
                self._kick.wait(due - now)
                continue
            with self.drive_lock:  # re-check under the lock: a command may have just arrived
                now = time.monotonic()
                if self.controller is not ctl or self.tripped or now - self.last_feed <= self.watchdog:
                    continue
                if self.lockstep and ctl.busy:
                    continue
                failed = None
                try:
                    self.car.write(0.0, 0.0, WATCHDOG_LAMPS)
                except Exception as exc:
                    failed = exc
                    try:
                        self.car.stop()
                    except Exception:
                        pass
                self.tripped = True
                self.trip_time = now
                self.trips += 1
                self.trip_delays.append(now - self.last_feed)  # the stop's true lateness, for benchmarks
            if failed is not None:
                self.note(logging.ERROR, "watchdog could not stop the car: %s", failed)
            self.note(logging.WARNING, "watchdog: no command from %s for %.3g s; car stopped (throttle 0, hazard lamps)",
                      ctl.peer, self.watchdog)

    def controller_stale(self, ctl: _Session, now: float) -> bool:
        """The controller has lost its claim: the car is stopped (the watchdog stopped it, or it
        never sent a command) and it has sent nothing for ``controller_timeout`` s."""
        return (self.tripped or not self.armed) and now - ctl.last_frame >= self.controller_timeout

    # --- housekeeping: log lines, the real-time simulator's clock ---------------------------------
    def _housekeeping_loop(self) -> None:
        next_sync = next_check = 0.0
        heartbeat = getattr(self.car, "heartbeat", None)
        while not self._stop_evt.wait(HOUSEKEEPING_S):
            now = time.monotonic()
            if not self.lockstep and now >= next_sync:
                # keep a real-time simulator's physics current, so that a request after a long
                # idle spell does not have to catch up on hours of steps under the drive lock
                next_sync = now + 0.1
                try:
                    with self.drive_lock:
                        self.car.time
                except Exception:
                    pass
            if heartbeat is not None:  # a recorded car (serve --live): its pose, whoever drives it
                try:
                    with self.drive_lock:
                        heartbeat()
                except Exception as exc:
                    _log(logging.WARNING, "live view: %s", _one_line(str(exc)))
                    heartbeat = None
            if now >= next_check:  # replies left unread: the no-progress rule (docs/protocol.md, section 6)
                next_check = now + 0.25
                with self.state_lock:
                    clients = [s for s in self.sessions if s.role is not None and s.stalled is None]
                for s in clients:
                    if s.progress.stalled(s.sock, now):
                        s.cut(f"not reading its replies: none of them taken for {self.io_timeout:g} s")
            self._flush_notes()
            self.refusals.flush(now)
            self.clientlog.flush(now)

    # --- connections ------------------------------------------------------------------------------
    def _accept_loop(self) -> None:
        """Connections before their hello: qcarlab.onboard.car_server.Admission (a flood of silent
        sockets costs no threads and cannot push out a client whose bytes have come)."""
        assert self.admission is not None
        ordinary_thread_priority()  # and so are the connections it starts, until they say hello
        self.admission.run(lambda: self.stopping)

    @property
    def evicted(self) -> int:
        """Connections before their hello dropped to make room for others."""
        return 0 if self.admission is None else self.admission.evicted + self.admission.dropped

    @property
    def pending(self) -> int:
        return 0 if self.admission is None else self.admission.pending

    def _refused_early(self, code: str, peer: str, detail: str) -> None:
        self.refusals.refused(code, "%s (no hello) disconnected: %s", peer, _one_line(detail))

    def _start_session(self, sock: socket.socket, addr: Any, deadline: float) -> _Session:
        """A connection whose first bytes came (Admission): its own thread reads the hello by ``deadline``."""
        if self.tls is not None:  # wrapped here (no I/O); the handshake runs on the connection's thread
            from qcarlab.wire.tls import TLSSocket

            sock = TLSSocket(self.tls.wrap_socket(sock, server_side=True, do_handshake_on_connect=False))
        session = _Session(self, sock, addr, deadline)
        with self.state_lock:
            self.sessions.add(session)
        try:
            session.thread = self._spawn(session.run, f"qcarlab-client-{session.peer}")
        except RuntimeError:
            with self.state_lock:
                self.sessions.discard(session)
            raise
        self._threads = [t for t in self._threads if t.is_alive()]
        return session

    def claim_control(self, session: _Session) -> str | None:
        """Make ``session`` the controller; returns None, or the refusal's message (``busy``)."""
        wait_until = time.monotonic() + 1.0
        revoke = None
        with self.control_free:
            while True:
                holder = self.controller
                now = time.monotonic()
                if holder is None or holder is session:
                    break
                if self.controller_stale(holder, now):
                    revoke = holder
                    break
                if (holder.ending or holder.peer_gone()) and now < wait_until and not self.stopping:
                    self.control_free.wait(wait_until - now)  # it is leaving: wait for it to be gone
                    continue
                quiet = now - holder.last_frame
                return (f"the car is controlled by {holder.peer} (last heard {quiet:.2g} s ago; control passes on "
                        f"once the watchdog has stopped the car and it has been silent for {self.controller_timeout:g} s); "
                        "connect as a monitor to watch")
            self.controller = session
            self.feed()
            if revoke is not None:
                self.takeovers += 1
        self._kick.set()
        if revoke is not None:
            revoke.revoke(
                f"control passed to {session.peer}: nothing was heard from this connection for "
                f"{time.monotonic() - revoke.last_frame:.2g} s after the watchdog stopped the car"
            )
            _log(logging.WARNING, "%s (control) was silent for %.2g s after the watchdog stopped the car; control passed to %s",
                        revoke.peer, time.monotonic() - revoke.last_frame, session.peer)
        return None

    def release(self, session: _Session) -> bool:
        """``session`` leaves; True if it was the controller (then the car was stopped)."""
        was = False
        if self.admission is not None:
            self.admission.done(session)
        with self.state_lock:
            self.monitors.discard(session)
            self.sessions.discard(session)
            if self.controller is session:
                was = True
        if was:
            ok = self.safe_stop(f"{session.peer} left")
            with self.control_free:
                if self.controller is session:
                    self.controller = None
                    self.tripped = False
                self.control_free.notify_all()
            self._kick.set()
            return ok
        return False


def _one_line(text: str) -> str:
    """Text for a log line: one line, printable, not too long."""
    flat = " ".join(str(text).split())
    flat = "".join(ch if ch.isprintable() else "?" for ch in flat)
    return flat if len(flat) <= 300 else flat[:297] + "..."


def _peer_name(addr: Any) -> str:
    if isinstance(addr, tuple) and len(addr) >= 2:
        host = addr[0]
        return f"[{host}]:{addr[1]}" if ":" in host else f"{host}:{addr[1]}"
    return str(addr)


class _End(Exception):
    """End this connection; ``reason`` goes into the disconnect log line."""

    def __init__(self, reason: str, code: str | None = None):
        super().__init__(reason)
        self.reason = reason
        self.code = code


_POLL_GONE = getattr(select, "POLLRDHUP", 0) | select.POLLHUP | select.POLLERR if hasattr(select, "poll") else 0


class _Session:
    """One client connection, served by its own thread."""

    def __init__(self, server: CarServer, sock: socket.socket, addr: Any, deadline: float | None = None):
        self.server = server
        self.car = server.car
        self.sock = sock
        self.addr = str(addr[0]) if isinstance(addr, tuple) and addr else str(addr)
        self.peer = _peer_name(addr)
        self.role: str | None = None
        self.client = "?"
        self.rx_seq = 0
        self.tx_seq = 0
        self.errors = 0
        self.thread: threading.Thread | None = None
        self.bye_ref: int | None = None
        self.accepted = time.monotonic()
        self.last_frame = self.accepted
        self.busy = False  # a request is being served (lock-step watchdog)
        self.ending = False
        self.evicted = False
        self.stalled: str | None = None  # why another thread ended this connection (not reading its replies)
        self.progress = ProgressWatch(server.io_timeout)
        self.revoked: str | None = None
        self.refusal: str | None = None  # the error code this connection was refused with
        self.pace: dict[int, float] = {}  # a monitor's next sensor slots
        self.tokens = MONITOR_BURST  # a monitor's request budget (token bucket)
        self.tokens_at = self.accepted
        self.send_timeout = server.io_timeout
        sock.settimeout(0.0)  # non-blocking: every wait goes through the waiter, with its deadline
        self.waiter = P.Waiter(sock)
        self.writer = P.FrameWriter(sock, self.waiter, self.send_timeout)  # one preallocated buffer for replies
        self.reader = P.FrameReader(sock, P.MAX_REQUEST, bufsize=P.MAX_REQUEST + P.HEADER_SIZE + 4096,
                                    frame_timeout=server.io_timeout, waiter=self.waiter)
        # the hello's deadline: from the accept, not counting time the server kept its bytes waiting
        self.reader.deadline = self.accepted + server.hello_timeout if deadline is None else deadline
        self.handlers = {
            M.COMMAND: self._command,
            M.STOP: self._stop,
            M.READ: self._read,
            M.GET_TRUTH: self._truth,
            M.GET_TIME: self._time,
            M.ADVANCE: self._advance,
            M.GET_LIDAR: self._sensor,
            M.GET_RGBD: self._sensor,
            M.GET_CSI: self._sensor,
            M.PING: self._ping,
        }

    @property
    def is_controller(self) -> bool:
        return self.server.controller is self

    # --- sending ----------------------------------------------------------------------------------
    def send(self, mtype: int, ref: int, *parts: Any, framed: Any = None, values: tuple[Any, ...] = ()) -> None:
        """One reply: ``parts`` its payload's bytes; or ``framed`` (:func:`P.framed` of the
        payload's struct) and the payload's ``values``, packed with the header into the writer's
        buffer (values that do not pack raise struct.error before anything is sent or counted)."""
        seq = self.tx_seq + 1
        try:
            if framed is None:
                self.writer.send(mtype, seq, ref, *parts)
            else:
                self.writer.send_struct(framed, mtype, seq, ref, values)
        except TimeoutError:
            self.tx_seq = seq
            raise _End(f"not reading its replies: a reply could not be sent for {self.send_timeout:g} s") from None
        except OSError as exc:
            self.tx_seq = seq
            raise _End(f"connection error: {exc.strerror or exc}") from None
        self.tx_seq = seq

    def error(self, code: str, message: str, ref: int) -> None:
        """Answer an error frame; non-fatal ones are logged here (one line, rate limited)."""
        self.send(M.ERROR, ref, P.error_payload(code, message))
        if code in P.FATAL_CODES or code in ("unsupported", "no_data", "not_lockstep"):
            return
        self.errors += 1
        if self.errors <= MAX_LOGGED_ERRORS:
            self.say(logging.WARNING, "%s (%s): %s: %s", self.peer, self.role or "no hello", code, _one_line(message))
            if self.errors == MAX_LOGGED_ERRORS:
                self.say(logging.WARNING, "%s: further errors from this client are counted, not logged", self.peer)

    def fatal(self, code: str, message: str, ref: int = 0, extra: dict[str, Any] | None = None) -> _End:
        payload = {"code": code, "message": message, "fatal": True, **(extra or {})}
        try:
            self.send(M.ERROR, ref, P.encode_json(payload))
        except _End:
            pass
        return _End(f"{code}: {message}", code)

    # --- the connection's life --------------------------------------------------------------------
    def say(self, level: int, msg: str, *args: Any) -> None:
        """A log line about this client, at a bounded rate per client address."""
        self.server.clientlog.line(self.addr, level, msg, *args)

    def cut(self, reason: str) -> None:
        """End this connection from another thread (a rule the server checks now and then)."""
        self.stalled = reason
        self.interrupt()

    def evict(self) -> None:
        """Admission dropped this connection (still in its hello) to make room for another."""
        self.evicted = True
        self.interrupt()

    def interrupt(self) -> None:
        """Wake the thread blocked in recv (server shutdown, eviction, revocation)."""
        try:
            self.sock.shutdown(socket.SHUT_RD)
        except OSError:
            pass

    def revoke(self, why: str) -> None:
        """Another client took control from this stale one: tell it and end the connection."""
        self.revoked = why
        self.interrupt()

    def peer_gone(self) -> bool:
        """The client has closed its end (seen without reading: the session thread may be about to)."""
        if not _POLL_GONE:
            return False
        try:
            poller = select.poll()
            poller.register(self.sock.fileno(), _POLL_GONE)
            return bool(poller.poll(0))
        except (OSError, ValueError):
            return True

    def close_socket(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass

    def run(self) -> None:
        reason = "closed"
        try:
            if self.server.tls is not None:
                self._handshake()
            reason = self._loop()
        except _End as end:
            reason = end.reason
            self.refusal = end.code
        except OSError as exc:
            reason = f"connection error: {exc.strerror or exc}"
        except Exception as exc:  # never let one client take the server down
            reason = f"internal error: {type(exc).__name__}: {exc}"
        finally:
            self._finish(reason)

    def _finish(self, reason: str) -> None:
        server = self.server
        self.ending = True
        if self.revoked is not None:
            self.fatal("control_lost", self.revoked)
            reason = f"control_lost: {self.revoked}"
        was_controller = server.controller is self
        stopped = ""
        if was_controller:
            ok = server.release(self)
            server.armed = False
            stopped = "; car stopped" if ok else "; STOPPING THE CAR FAILED"
        if self.errors > MAX_LOGGED_ERRORS:
            reason += f"; {self.errors} error frames in all"
        if self.role is None:  # never a client: counted, at most one line per kind and interval
            if self.evicted:
                code = "evicted"
            elif self.refusal:
                code = self.refusal
            elif "HTTP" in reason:
                code = "http"
            else:
                code = "no_hello"
            server.refusals.refused(code, "%s (no hello) disconnected: %s", self.peer, _one_line(reason))
        else:
            line = "%s (%s) disconnected: %s%s"
            args = (self.peer, self.role, _one_line(reason), stopped)
            if reason.startswith(("internal", "connection error", "not reading", "control_lost")) or "STOPPING" in stopped:
                self.say(logging.WARNING, line, *args)
            else:
                self.say(logging.INFO, line, *args)
        if self.bye_ref is not None:
            try:
                self.send(M.BYE, self.bye_ref)
            except _End:
                pass
        self.close_socket()
        if not was_controller:
            server.release(self)

    def _handshake(self) -> None:
        """TLS: the handshake, within the hello's deadline (a client that stalls in it is cut off
        as one that never says hello)."""
        import ssl

        try:
            self.sock.handshake(self.reader.deadline, self.waiter)
        except TimeoutError:
            raise _End(f"no TLS handshake within {self.server.hello_timeout:g} s of connecting", "tls") from None
        except ssl.SSLError as exc:
            raise _End(f"TLS handshake failed: {exc.reason or exc} (a client without TLS? it needs tcps://)", "tls") from None
        except OSError as exc:
            raise _End(f"TLS handshake failed: {exc.strerror or exc}", "tls") from None

    def _wait_for_request(self) -> None:
        """The controller's next request usually comes within microseconds of its reply: look for it
        a little while (no sleep, no wake-up to pay) before blocking."""
        try:
            self.reader.spin(self.server.spin)
        except OSError:  # read_frame meets it
            pass

    def _loop(self) -> str:
        server = self.server
        reader = self.reader
        while True:
            if self.revoked is not None:
                return "control_lost"
            if self.stalled is not None:
                return self.stalled
            if server.spin and server.controller is self:
                self._wait_for_request()
            try:
                frame = reader.read_frame()
            except TimeoutError:
                if self.revoked is not None:
                    return "control_lost"
                if self.role is None:
                    if P.looks_like_http(reader.peek()):
                        return self._http()
                    what = "no complete HELLO" if reader.mid_frame else "no hello"
                    raise self.fatal("timeout", f"{what} within {server.hello_timeout:g} s of connecting") from None
                if reader.mid_frame:
                    raise self.fatal(
                        "timeout", f"incomplete frame: not complete {server.io_timeout:g} s after its first byte"
                    ) from None
                if server.stopping:
                    return "server stopping"
                continue  # an idle client may stay
            except P.IncompleteFrame:
                return "closed in the middle of a frame"
            except P.ProtocolError as exc:
                if exc.code == "bad_magic" and self.rx_seq == 0 and P.looks_like_http(reader.peek()):
                    return self._http()
                raise self.fatal(exc.code, exc.message) from None
            if frame is None:
                if self.revoked is not None:
                    return "control_lost"
                if self.stalled is not None:
                    return self.stalled
                if self.evicted:
                    raise self.fatal("too_many_clients", f"more than {server.max_pending} connections were reading "
                                     "their hello at once; this one, the oldest of the busiest address, was dropped")
                if server.stopping:
                    try:
                        self.send(M.BYE, 0, P.encode_json({"reason": "server stopping"}))
                    except _End:
                        pass
                    return "server stopping"
                return "closed by the client"
            self.last_frame = time.monotonic()
            expected = self.rx_seq + 1
            if frame.seq != expected:
                raise self.fatal("sequence", f"frame seq {frame.seq} out of order (expected {expected})", frame.seq)
            self.rx_seq = frame.seq
            if self.role is None:
                self._hello(frame)
                continue
            if frame.type == _BYE:
                self.bye_ref = frame.seq  # answered once the car is stopped and the line logged
                return "said bye"
            if self.role == "monitor":
                self._throttle()
            self.busy = True
            try:
                self._dispatch(frame)
            finally:
                self.busy = False

    def _throttle(self) -> None:
        """A monitor's requests are served at most MONITOR_REQUESTS_PER_S, in bursts of MONITOR_BURST:
        a request over the budget waits for it (the client sees a slower reply, never an error)."""
        now = time.monotonic()
        self.tokens = min(MONITOR_BURST, self.tokens + (now - self.tokens_at) * MONITOR_REQUESTS_PER_S)
        self.tokens_at = now
        if self.tokens < 1.0:
            self.server._stop_evt.wait((1.0 - self.tokens) / MONITOR_REQUESTS_PER_S)
            now = time.monotonic()
            self.tokens = min(MONITOR_BURST, self.tokens + (now - self.tokens_at) * MONITOR_REQUESTS_PER_S)
            self.tokens_at = now
        self.tokens = max(0.0, self.tokens - 1.0)

    def _http(self) -> str:
        try:
            P._send_nonblocking(self.sock, [P.HTTP_REPLY], self.waiter, 1.0)
        except OSError:
            pass
        return "spoke HTTP; answered 400 and closed"

    # --- hello ------------------------------------------------------------------------------------
    def _hello(self, frame: P.Frame) -> None:
        server = self.server
        if frame.type != M.HELLO:
            raise self.fatal("bad_hello", f"the first frame must be HELLO, got {frame.name}", frame.seq)
        try:
            msg = P.decode_json(frame.payload, "hello")
        except P.ProtocolError as exc:
            raise self.fatal("bad_hello", exc.message, frame.seq) from None
        proto = msg.get("protocol")
        if proto != P.VERSION:
            raise self.fatal(
                "bad_version", f"client speaks protocol {proto!r}; this server speaks version {P.VERSION}", frame.seq
            )
        role = msg.get("role", "control")
        if role not in ("control", "monitor"):
            raise self.fatal("bad_hello", f"role must be 'control' or 'monitor', got {role!r}", frame.seq)
        client = msg.get("client")
        if isinstance(client, str):  # free text going into a log line: printable, short
            self.client = "".join(ch if ch.isprintable() else "?" for ch in client[:64])
        if server.token is not None:
            wait, everyone = server.tokens.admit(self.addr)
            if wait > 0:
                whose = "from addresses without a right token lately" if everyone else f"from {self.addr}"
                raise self.fatal("bad_token", f"too many wrong tokens {whose}; try again in {wait:.1f} s",
                                 frame.seq, {"retry_after_s": round(wait, 3)})
            if not token_matches(msg.get("token"), server.token):
                wait = server.tokens.failed(self.addr)
                extra = {"retry_after_s": round(wait, 3)} if wait > 0 else None
                raise self.fatal("bad_token", "wrong or missing token", frame.seq, extra)
            server.tokens.succeeded(self.addr)
        with server.state_lock:
            if self.evicted or server.stopping:
                raise self.fatal("too_many_clients", "the server is busy with other connections; try again", frame.seq)
            if role == "monitor" and len(server.monitors) >= server.max_clients - 1:
                full = True
            else:
                full = False
                if role == "monitor":
                    server.monitors.add(self)
        server.admission.done(self)  # said hello: no longer one of the connections before theirs
        if full:
            raise self.fatal("too_many_clients", f"the server already has {server.max_clients - 1} monitors "
                             "(one more slot is kept for a controller); try again later", frame.seq)
        if role == "control":
            refusal = server.claim_control(self)
            if refusal is not None:
                raise self.fatal("busy", refusal, frame.seq)
            server.armed = False
            reset = getattr(self.car, "reset", None)
            if server.lockstep and callable(reset):  # a new run: from the start state, not the last client's
                with server.drive_lock:
                    reset()
                    server.cache_readout = None
            if server.priority:
                raise_thread_priority(PRIORITY_CONTROLLER)  # this thread serves the controller from now on
        elif server.priority and server.tuned:
            raise_thread_priority(PRIORITY_CLIENT)
        self.role = role
        self.reader.deadline = None
        self.reader.idle_timeout = server.io_timeout
        welcome = dict(server.welcome_base, role=role)
        self.say(logging.INFO, "%s connected as %s (%s)", self.peer, role, self.client)
        self.send(M.WELCOME, frame.seq, P.encode_json(welcome))

    # --- requests ---------------------------------------------------------------------------------
    def _dispatch(self, frame: P.Frame) -> None:
        server = self.server
        mtype = frame.type
        controller = server.controller is self
        if controller and server.lockstep:
            server.feed()
        handler = self.handlers.get(mtype)
        if handler is None:
            if mtype == M.HELLO:
                self.error("bad_payload", "HELLO was already received on this connection", frame.seq)
            else:
                self.error("unknown_type", f"unknown or unexpected message type {frame.name}", frame.seq)
            return
        if not controller and mtype in CONTROL_ONLY:
            if self.role == "control":
                self.error("read_only", f"{frame.name}: this connection no longer has control", frame.seq)
            else:
                self.error("read_only", f"{frame.name} needs the control role; this connection is a monitor", frame.seq)
            return
        try:
            handler(frame)
        except _End:
            raise
        except P.ProtocolError as exc:
            if mtype == M.COMMAND:
                server.safe_stop("bad command")
            self.error(exc.code, exc.message, frame.seq)
        except NotBuiltError as exc:
            self.error("unsupported", str(exc), frame.seq)
        except InputError as exc:
            if mtype == M.COMMAND:
                server.safe_stop("bad command")
            self.error("bad_value", str(exc), frame.seq)
        except (QcarlabError, Exception) as exc:  # a failing backend: report, keep serving
            if mtype == M.COMMAND:
                server.safe_stop("command failed")
            self.error("car_error", f"{type(exc).__name__}: {exc}", frame.seq)

    def _command(self, frame: P.Frame) -> None:
        server = self.server
        throttle, steering, leds, flags = P.unpack_command(frame.payload)
        if flags & ~FLAGS_KNOWN:
            raise InputError(f"command flags 0x{flags:08x} set reserved bits (only bit 0, read back, is defined)")
        with server.drive_lock:
            server.feed()
            server.arm()
            cmd = self.car.write(throttle, steering, leds)
            readout = self.car.read() if flags & FLAG_READ_BACK else None
        if readout is not None:
            if server.lockstep:
                server.cache_readout = readout
            self.send(M.READOUT, frame.seq, framed=P.READOUT_FRAME,
                      values=P.readout_payload_values(readout, server.status()))
        else:
            self.send(M.APPLIED, frame.seq, framed=P.APPLIED_FRAME, values=(cmd.throttle, cmd.steering, *cmd.leds))

    def _stop(self, frame: P.Frame) -> None:
        server = self.server
        _expect_empty(frame)
        with server.drive_lock:
            server.feed()
            server.arm()
            self.car.stop()
        self.send(M.OK, frame.seq)

    def _read(self, frame: P.Frame) -> None:
        server = self.server
        _expect_empty(frame)
        status = server.status()
        if server.lockstep and server.controller is not self:
            readout = server.cache_readout
            if readout is None:
                self.error("no_data", "lock-step: no readout yet (monitors see the controller's last readout)", frame.seq)
                return
            status |= P.STATUS_CACHED
        else:
            with server.drive_lock:
                readout = self.car.read()
            if server.lockstep:
                server.cache_readout = readout
        self.send(M.READOUT, frame.seq, framed=P.READOUT_FRAME, values=P.readout_payload_values(readout, status))

    def _truth(self, frame: P.Frame) -> None:
        _expect_empty(frame)
        with self.server.drive_lock:
            truth = self.car.truth()
        if truth is None:
            self.error("unsupported", "this car has no ground truth (only simulated cars do)", frame.seq)
            return
        self.send(M.TRUTH, frame.seq, P.pack_truth(truth))

    def _time(self, frame: P.Frame) -> None:
        _expect_empty(frame)
        with self.server.drive_lock:
            t = self.car.time
        self.send(M.TIME, frame.seq, P.pack_scalar(t))

    def _advance(self, frame: P.Frame) -> None:
        server = self.server
        dt = P.unpack_scalar(frame.payload, "advance")
        if not server.lockstep:
            self.error("not_lockstep", "ADVANCE needs a lock-step server (qcarlab serve --lockstep); time runs by itself here", frame.seq)
            return
        if not (math.isfinite(dt) and 0.0 <= dt <= P.MAX_ADVANCE):
            raise InputError(f"advance: dt must be a number of seconds in [0, {P.MAX_ADVANCE:g}], got {dt!r}")
        with server.drive_lock:
            self.car.advance(dt)
            t = self.car.time
        self.send(M.TIME, frame.seq, P.pack_scalar(t))

    def _sensor(self, frame: P.Frame) -> None:
        server = self.server
        _expect_empty(frame)
        kind = SENSORS[frame.type][1]
        if kind not in server.capabilities:
            self.error("unsupported", f"this car has no {kind} sensor", frame.seq)
            return
        controller = server.controller is self
        try:
            reply, parts = server.sensors.frame(frame.type, controller=controller, pace=None if controller else self.pace)
        except NoData:
            self.error("no_data", f"lock-step: no {kind} frame yet (monitors see the controller's last one)", frame.seq)
            return
        self.send(reply, frame.seq, *parts)

    def _ping(self, frame: P.Frame) -> None:
        if len(frame.payload) > P.MAX_PING:
            raise P.ProtocolError("bad_payload", f"ping payload is at most {P.MAX_PING} bytes, got {len(frame.payload)}")
        self.send(M.PONG, frame.seq, frame.payload)


def _expect_empty(frame: P.Frame) -> None:
    if len(frame.payload):
        raise P.ProtocolError("bad_payload", f"{frame.name} takes no payload, got {len(frame.payload)} bytes")
