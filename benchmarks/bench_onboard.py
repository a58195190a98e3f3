"""The car-side server (qcarlab/onboard/car_server.py, --dry-run) under load, as issue 16 measures a server:

Run: python benchmarks/bench_onboard.py [--python /path/to/python3.8] [--trips 20] [--commands 3000]

- watchdog: the time from the last command to the car stopped (status bit 0 seen by a monitor
  polling READ), with 8 monitors pulling RGBD frames flat out; target: watchdog + 20 ms.
- controller: command + readout round trips at 100 Hz with 8 monitors pulling RGBD at 10 Hz;
  p50/p99 and ticks missed (round trip over 10 ms); target p99 < 2 ms.
- takeover: a silent controller, a new one asking for control every 10 ms: the time from the
  last command to the new controller's WELCOME (max(watchdog, controller timeout) by design).

The server runs in its own process (the cars' Python 3.8 when found); every monitor is its own
process. Prints one line per figure with the machine and its load.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import re
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from onboard_support import Served, car_python  # noqa: E402

from qcarlab.wire import protocol as P  # noqa: E402
from qcarlab.wire.protocol import MsgType as M  # noqa: E402
from qcarlab.net.testing import RawClient  # noqa: E402

OFF = (0.0,) * 12
WATCHDOG = 0.25


def _monitor(address, period, stop, counter):
    raw = RawClient(address, timeout=30.0)
    raw.hello("monitor")
    n = 0
    next_t = time.monotonic()
    while not stop.is_set():
        raw.request(M.GET_RGBD)
        n += 1
        if period:
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
    with counter.get_lock():
        counter.value += n
    raw.close()


def monitors(address, count, period):
    stop, counter = mp.Event(), mp.Value("l", 0)
    procs = [mp.Process(target=_monitor, args=(address, period, stop, counter), daemon=True) for _ in range(count)]
    for p in procs:
        p.start()
    time.sleep(1.0)  # connected and pulling
    return stop, counter, procs


def finish(stop, counter, procs):
    stop.set()
    for p in procs:
        p.join(10)
    return counter.value


def status(raw):
    return P.unpack_readout(raw.request(M.READ).payload)[1]


def bench_watchdog(address, trips):
    stop, counter, procs = monitors(address, 8, 0.0)
    late = []
    ctl = RawClient(address)
    ctl.hello("control")
    mon = RawClient(address, timeout=10.0)
    mon.hello("monitor")
    for _ in range(trips):
        for _ in range(20):
            time.sleep(0.01)
            last = time.monotonic()  # before the command is sent: an upper bound on the server's lateness
            ctl.request(M.COMMAND, P.pack_command(0.1, 0.0, OFF))
        while not status(mon) & P.STATUS_WATCHDOG:
            pass
        late.append(time.monotonic() - last - WATCHDOG)
    frames = finish(stop, counter, procs)
    ctl.close()
    mon.close()
    return late, frames


def bench_controller(address, commands):
    stop, counter, procs = monitors(address, 8, 0.1)
    ctl = RawClient(address)
    ctl.hello("control")
    rtts, missed = [], 0
    next_t = time.monotonic()
    for i in range(commands):
        t0 = time.perf_counter()
        ctl.request(M.COMMAND, P.pack_command(0.1, 0.0, OFF, P.FLAG_READ_BACK))
        rtt = time.perf_counter() - t0
        rtts.append(rtt)
        missed += rtt > 0.01
        next_t += 0.01
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    frames = finish(stop, counter, procs)
    ctl.close()
    return rtts, missed, frames


def bench_takeover(address, times):
    out = []
    for _ in range(times):
        old = RawClient(address)
        old.hello("control")
        old.request(M.COMMAND, P.pack_command(0.1, 0.0, OFF))
        last = time.monotonic()
        while True:
            new = RawClient(address)
            frame = new.hello("control")
            if frame.type == M.WELCOME:
                out.append(time.monotonic() - last)
                new.request(M.BYE)
                new.close()
                break
            new.close()
            time.sleep(0.01)
        old.close()
        time.sleep(0.2)
    return out


def pct(values, q):
    values = sorted(values)
    return values[min(len(values) - 1, int(round(q * (len(values) - 1))))]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--python", default=None, help="the server's Python (default: the cars' 3.8 if found)")
    ap.add_argument("--trips", type=int, default=20)
    ap.add_argument("--commands", type=int, default=3000)
    ap.add_argument("--takeovers", type=int, default=5)
    args = ap.parse_args()
    python = args.python or car_python("3.8") or sys.executable
    version = os.popen(f"{python} -c 'import platform; print(platform.python_version())'").read().strip()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; "
          f"server on Python {version}; laptop side Python {platform.python_version()}")
    # the watchdog against monitors that are not paced (--monitor-rate 1000): frames flat out
    with Served(python, "--dry-run", "--port", "0", "--watchdog", str(WATCHDOG), "--monitor-rate", "1000") as srv:
        late, frames = bench_watchdog(srv.address, args.trips)
        print(f"watchdog ({args.trips} trips, 8 monitors pulling RGBD as fast as they are let, {frames} frames): seen stopped "
              f"watchdog + median {statistics.median(late) * 1e3:.1f} ms, p95 {pct(late, 0.95) * 1e3:.1f} ms, "
              f"max {max(late) * 1e3:.1f} ms (target + 20 ms)")
        server_side = [float(x) / 1e3 - WATCHDOG for x in re.findall(r"stopped ([0-9.]+) ms after the last", srv.stderr)]
        if server_side:
            print(f"watchdog as the server logged it ({len(server_side)} trips): watchdog + median "
                  f"{statistics.median(server_side) * 1e3:.1f} ms, max {max(server_side) * 1e3:.1f} ms")
    with Served(python, "--dry-run", "--port", "0", "--watchdog", str(WATCHDOG)) as srv:
        rtts, missed, frames = bench_controller(srv.address, args.commands)
        print(f"controller ({args.commands} commands+readouts at 100 Hz, 8 monitors at 10 Hz RGBD, {frames} frames): "
              f"p50 {statistics.median(rtts) * 1e3:.3f} ms, p99 {pct(rtts, 0.99) * 1e3:.3f} ms, "
              f"max {max(rtts) * 1e3:.2f} ms, {missed} of {args.commands} ticks over 10 ms (target p99 < 2 ms)")
        take = bench_takeover(srv.address, args.takeovers)
        print(f"takeover ({args.takeovers} times): a new controller gets control {statistics.median(take):.3f} s "
              f"(median; max {max(take):.3f} s) after the old one's last command (by design: max(watchdog 0.25 s, controller timeout 1.0 s))")
    print(f"load after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
