"""``qcarlab keyboard-drive``: drive the car from the keyboard in a terminal (sheet 3.4).

The logic (keys, ramps, lamps, the loop) lives in :mod:`qcarlab.experiments.keyboard_drive`; this
module is the terminal: the TTY check, the rich live panel (drawn by its own thread at 10 Hz so
a slow terminal never holds up the 50 Hz command stream) and the summary line.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import threading
from collections import deque
from typing import Annotated, Any

import typer
from rich.console import Console, Group
from rich.live import Live
from rich.panel import Panel
from rich.style import Style
from rich.table import Table
from rich.text import Text

from qcarlab.cli.app import app
from qcarlab.cli.common import recordable  # noqa: I001  (--record, --live)
from qcarlab.cli.common import CarTokenOpt, CarOpt, DebugOpt, ParamsOpt, SeedOpt, WorldOpt, open_from_options, stderr, stdout
from qcarlab.errors import CarError, InputError
from qcarlab.experiments.keyboard_drive import (
    DriveConfig,
    DriveSummary,
    Frame,
    MapGrid,
    cbreak_terminal,
    keyboard_drive,
    world_map,
)

DEFAULT_WORLD = "studio"  # the lab room: walls to see, space to drive
INFO_WIDTH = 52  # columns the readings take beside the map
_ARROWS = "→↗↑↖←↙↓↘"
_ASCII_ARROWS = ">/^\\<\\v/"
_CAR = (255, 40, 40)
_TRAIL = (235, 120, 40)


def _bar(value: float, limit: float, width: int = 19) -> str:
    """A centred bar: '░░░░░░░░░│███░░░░░░' for a signed value within +-limit."""
    half = width // 2
    n = 0 if limit <= 0 else min(half, int(round(abs(value) / limit * half)))
    left = "░" * (half - n) + "█" * n if value < 0 else "░" * half
    right = "█" * n + "░" * (half - n) if value > 0 else "░" * half
    return left + "│" + right


def _side(rad: float) -> str:
    return "left" if rad > 1e-6 else "right" if rad < -1e-6 else "straight"


class _MapView:
    """The world map with the car, its trail and the moving balls, as rich Text (half blocks)."""

    def __init__(self, world: Any, grid: MapGrid, color: bool, unicode: bool):
        self.world, self.grid, self.color, self.unicode = world, grid, color, unicode
        self.trail: deque[tuple[int, int]] = deque(maxlen=400)
        rgb = grid.rgb
        self._styles = [
            [
                Style(color=f"rgb({t[0]},{t[1]},{t[2]})", bgcolor=f"rgb({b[0]},{b[1]},{b[2]})")
                for t, b in zip(rgb[2 * r], rgb[2 * r + 1])
            ]
            for r in range(grid.rows)
        ]

    def render(self, frame: Frame) -> Text:
        g = self.grid
        tr = frame.truth
        car_cell = glyph = None
        extra: dict[tuple[int, int], tuple[int, int, int]] = {}  # pixel -> colour over the background
        if tr is not None:
            pix = g.pixel_of(tr.x, tr.y)
            if pix is not None:
                if not self.trail or self.trail[-1] != pix:
                    self.trail.append(pix)
                car_cell = (pix[1] // 2, pix[0])
                k = int(round(tr.yaw / (math.pi / 4))) % 8
                glyph = (_ARROWS if self.unicode else _ASCII_ARROWS)[k]
            for p in self.trail:
                extra[p] = _TRAIL
            for ball, c in zip(getattr(self.world, "balls", []), self.world.obstacles_at(tr.t)):
                p = g.pixel_of(c.x, c.y)
                if p is not None:
                    extra[p] = (int(ball.color[2]), int(ball.color[1]), int(ball.color[0]))
        text = Text(no_wrap=True, overflow="crop", end="")
        for r in range(g.rows):
            for c in range(g.cols):
                if (r, c) == car_cell:
                    bg = g.rgb[2 * r : 2 * r + 2, c].mean(axis=0).astype(int)
                    style = Style(color=f"rgb{_CAR}", bold=True, bgcolor=f"rgb({bg[0]},{bg[1]},{bg[2]})") if self.color else None
                    text.append(glyph or "@", style)
                    continue
                top, bot = extra.get((c, 2 * r)), extra.get((c, 2 * r + 1))
                if not self.color:
                    ch = "*" if (top or bot) else "#" if (g.solid[2 * r, c] or g.solid[2 * r + 1, c]) else "."
                    text.append(ch)
                elif top is None and bot is None:
                    text.append("▀", self._styles[r][c])
                else:
                    t = top or tuple(g.rgb[2 * r, c])
                    b = bot or tuple(g.rgb[2 * r + 1, c])
                    text.append("▀", Style(color=f"rgb({t[0]},{t[1]},{t[2]})", bgcolor=f"rgb({b[0]},{b[1]},{b[2]})"))
            if r < g.rows - 1:
                text.append("\n")
        return text


class _View:
    """Draws the latest frame at 10 Hz on its own thread; the drive loop only hands frames over."""

    def __init__(self, live: Live, title: str, config: DriveConfig, battery_low: float, map_view: _MapView | None, beside: bool):
        self.live, self.title, self.config = live, title, config
        self.battery_low = battery_low
        self.map_view, self.beside = map_view, beside
        self.frame: Frame | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="keyboard-drive view", daemon=True)

    def push(self, frame: Frame) -> None:
        self.frame = frame

    def __enter__(self) -> _View:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            frame = self.frame
            if frame is None:
                continue
            try:
                self.live.update(self.render(frame), refresh=True)
            except Exception:  # noqa: BLE001  (a closed terminal: keep driving to the stop)
                return

    def render(self, f: Frame) -> Panel:
        s, cfg = f.state, self.config
        info = Table.grid(padding=(0, 1))
        info.add_column(style="bold", no_wrap=True)
        info.add_column(no_wrap=True)
        info.add_row("speed", f"{f.speed:+.2f} m/s")
        info.add_row("throttle", f"{s.throttle:+.3f} {_bar(s.throttle, cfg.max_throttle)} target {s.target_throttle:+.3f}")
        info.add_row(
            "steering",
            f"{math.degrees(s.steering):+3.0f}°  {_bar(-s.steering, cfg.max_steering)} {_side(s.target_steering)}"
            f" {abs(math.degrees(s.target_steering)):.0f}°",
        )
        v = f.readout.battery_voltage
        info.add_row("battery", Text(f"{v:.2f} V" + ("  LOW: charge it" if v < self.battery_low else ""),
                                     style="bold red" if v < self.battery_low else ""))
        if isinstance(f.lidar, tuple):
            rng, bearing = f.lidar
            deg = math.degrees(bearing)
            where = "ahead" if abs(deg) < 5 else "behind" if abs(deg) > 175 else f"{abs(deg):.0f}° {_side(bearing)}"
            info.add_row("nearest", Text(f"{rng:.2f} m, {where}", style="bold red" if rng < 0.3 else ""))
        else:
            info.add_row("nearest", "n/a (no LIDAR on this car)" if f.lidar == "n/a" else "nothing in range")
        info.add_row("lamps", ", ".join(f.lamps) or "-")
        if f.truth is not None:
            tr = f.truth
            info.add_row("pose", f"x {tr.x:+.2f}  y {tr.y:+.2f} m  yaw {math.degrees(tr.yaw):+4.0f}°  (sim truth)")
        info.add_row("driven", f"{f.distance:.2f} m in {f.t:.1f} s, loop {f.rate:.0f} Hz")
        info.add_row("last key", s.last_key or "-")
        keys = Text(
            "W/↑ faster  S/↓ slower  A/← D/→ steer  C centre\n"
            "Space brake  H headlamps  Z/X indicators  E hazard\n"
            "Q or Ctrl-C: stop and quit",
            style="dim",
        )
        left = Group(info, Text(""), keys)
        body: Any = left
        if self.map_view is not None:
            mp = self.map_view.render(f)
            if self.beside:
                body = Table.grid(padding=(0, 2))
                body.add_column(width=INFO_WIDTH)
                body.add_column()
                body.add_row(left, mp)
            else:
                body = Group(left, Text(""), mp)
        return Panel(body, title=self.title, title_align="left", expand=False)


@contextlib.contextmanager
def _log_above(live: Live):
    """While the live panel is up, the library's warnings go through its console, printed on their
    own line above the panel: a plain stderr write would land after the panel's last character (on
    "starting the car...", glued to it) and be drawn over at the next refresh."""
    logger = logging.getLogger("qcarlab")

    class _AbovePanel(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            try:
                live.console.print(f"{record.levelname.lower()}: {record.getMessage()}", markup=False, highlight=False)
            except Exception:  # noqa: BLE001  (a closed terminal: the drive goes on to its stop)
                pass

    saved = list(logger.handlers)
    logger.handlers = [_AbovePanel()]
    try:
        yield
    finally:
        logger.handlers = saved


def _map_for(world: Any, console: Console, map_wanted: bool) -> tuple[_MapView | None, bool]:
    """The map view sized to the terminal (beside the readings when it fits), or None."""
    if world is None or not map_wanted:
        return None, False
    try:
        width, height = console.size
        beside = width - INFO_WIDTH - 6 >= 20
        cols = min(64, width - INFO_WIDTH - 6) if beside else min(64, width - 4)
        rows = min(20, height - 4) if beside else min(12, height - 18)
        if cols < 12 or rows < 4:
            return None, False
        grid = world_map(world, cols=cols, rows=rows)
    except Exception:  # noqa: BLE001  (the map is a nicety: never a reason not to drive)
        return None, False
    encoding = (console.encoding or "").lower()
    return _MapView(world, grid, console.color_system is not None, encoding.startswith("utf")), beside


@app.command("keyboard-drive")
@recordable
def keyboard_drive_cmd(
    max_throttle: Annotated[
        float, typer.Option(help="Most throttle the keys can give (duty fraction; the car's limit is 0.3). It caps "
                            "the duty, and so the speed: on the floor 0.1 holds about 1 m/s, 0.05 about 0.4 m/s.")
    ] = 0.15,
    throttle_step: Annotated[float, typer.Option(help="Throttle change per key press (duty fraction).")] = 0.03,
    ramp: Annotated[
        float, typer.Option(help="How fast the applied throttle follows the keys, duty fraction per second.")
    ] = 0.3,
    steering_step: Annotated[float, typer.Option(help="Steering change per key press, rad.")] = 0.1,
    steering_ramp: Annotated[float, typer.Option(help="How fast the wheels follow the keys, rad/s.")] = 1.5,
    rate: Annotated[float, typer.Option(help="Command rate in Hz, 5-500 (a served car stops after 0.25 s without "
                                        "one).")] = 50.0,
    show_map: Annotated[bool, typer.Option("--map/--no-map", help="Top-down map of the simulator's world.")] = True,
    car: CarOpt = "sim",
    token: CarTokenOpt = None,
    world: WorldOpt = None,
    seed: SeedOpt = 0,
    params: ParamsOpt = None,
    debug: DebugOpt = False,
) -> None:
    """Drive the car from the keyboard (sheet 3.4) with a live panel: speed, steering, battery, nearest obstacle, map.

    Keys move the throttle and steering targets one step per press; the car follows them smoothly
    (--ramp, --steering-ramp). A terminal reports no key releases, so the car holds its speed and
    steering until you change them: Space stops the motor at once, C centres the wheels.

    Keys:
      [b]W[/b] or [b]Up[/b]          faster (throttle target + one --throttle-step)
      [b]S[/b] or [b]Down[/b]        slower, then reverse
      [b]A[/b] or [b]Left[/b]        steer left (steering target + one --steering-step)
      [b]D[/b] or [b]Right[/b]       steer right
      [b]C[/b]                centre the steering
      [b]Space[/b]            brake: throttle 0 at once, brake lamp on
      [b]H[/b]                headlamps on/off
      [b]Z[/b] / [b]X[/b]            left / right indicator on/off
      [b]E[/b]                hazard lamps on/off
      [b]Q[/b] or [b]Ctrl-C[/b]      stop the car and quit

    The simulator runs in real time in the 'studio' world unless --world says otherwise; a served
    car (--car tcp://HOST:PORT) gets a command every tick. Needs an interactive terminal.

    Example:
      qcarlab keyboard-drive --world track --max-throttle 0.1
    """
    config = DriveConfig(
        max_throttle=max_throttle,
        throttle_step=min(throttle_step, max_throttle),
        throttle_ramp=ramp,
        max_steering=0.5,
        steering_step=steering_step,
        steering_ramp=steering_ramp,
    )
    if not (math.isfinite(rate) and 5.0 <= rate <= 500.0):
        raise InputError(f"--rate must be between 5 and 500 Hz, got {rate}")
    if not (sys.stdin.isatty() and sys.stdout.isatty()):
        raise InputError("keyboard-drive needs an interactive terminal (stdin and stdout must both be a TTY)")
    is_sim = car.strip() in ("sim", "sim:", "sim://")
    if not is_sim and world is not None:
        raise InputError("--world is for --car sim; a served car drives in the server's world (qcarlab serve --world)")
    if is_sim and world is None:
        world = DEFAULT_WORLD
    with open_from_options(
        car, world, seed, True, params, token=token, throttle_limit=max_throttle, timeout=1.0,
        client="qcarlab keyboard-drive",
    ) as qcar:
        config = DriveConfig(**{**config.__dict__, "max_steering": qcar.steering_limit})
        car_world = getattr(qcar, "world", None)
        map_view, beside = _map_for(car_world, stdout, show_map)
        if is_sim:
            title = "QCar keyboard drive · simulator, real time" + (f" · world {car_world.name}" if car_world is not None else "")
        else:
            title = f"QCar keyboard drive · {getattr(qcar, 'uri', car)} ({qcar.identity().name})"
        fd = sys.stdin.fileno()
        with cbreak_terminal(fd):
            with Live(Text("starting the car..."), console=stdout, auto_refresh=False, transient=True) as live, \
                    _log_above(live):
                with _View(live, title, config, qcar.params.battery_low_v, map_view, beside) as view:
                    try:
                        summary = keyboard_drive(qcar, config, key_fd=fd, on_frame=view.push, rate=rate)
                    except CarError as exc:
                        raise CarError(f"{exc}; the drive ended (a served car stops by itself when its driver drops)") from None
    _finish(summary)


def _finish(summary: DriveSummary) -> None:
    stdout.print(summary.line(), markup=False, highlight=False, soft_wrap=True)
    if summary.reason == "collision":
        stderr.print(f"qcarlab keyboard-drive: {summary.collision}; the drive ended and the car is stopped",
                     markup=False)
        raise typer.Exit(1)
    if summary.reason == "interrupted":
        raise typer.Exit(130)
    if summary.reason == "signal":
        raise typer.Exit(128 + (summary.signal or 15))
    if summary.reason == "terminal closed":
        raise typer.Exit(129)
