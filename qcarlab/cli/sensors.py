"""``qcarlab lidar-scan`` (sheet 3.5) and ``qcarlab camera`` (sheets 3.6, 3.7)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import cv2
import typer
from rich.live import Live

from qcarlab import plots
from qcarlab.car import parse_car_uri
from qcarlab.cli.app import app
from qcarlab.cli.common import recordable  # noqa: I001  (--record, --live)
from qcarlab.cli.common import (
    Table,
    CarTokenOpt,
    StartOpt, WorldOpt, sim_world,
    check_out,
    CarOpt, DebugOpt, JsonOpt, OutOpt, ParamsOpt, RealtimeOpt, SeedOpt, emit, interactive, open_from_options,
    stderr, stdout, summary_table,
)
from qcarlab.constants import load_params
from qcarlab.errors import InputError
from qcarlab.experiments.camera import grab
from qcarlab.experiments.lidar_scan import MAX_TARGET_M, capture, sector_minima, target_world
from qcarlab.experiments.result import Result

SECTORS = ("ahead", "ahead-left", "left", "behind-left", "behind", "behind-right", "right", "ahead-right")


def _list_worlds() -> None:
    from qcarlab.experiments.worlds import list_worlds

    table = Table(title="shipped worlds", title_justify="left")
    table.add_column("name")
    table.add_column("description")
    for name, description in list_worlds():
        table.add_row(name, description)
    stdout.print(table)


def _lidar_summary(result: Result) -> None:
    m = result.metrics
    table = summary_table(f"lidar-scan: {m['scans']} scan(s) of {m['beams']} beams at {m['rate_hz']:g} Hz")
    table.add_row("points with a return", f"{m['points_with_return']} of {m['beams']}")
    if m["nearest_obstacle_m"] is None:
        table.add_row("nearest obstacle", "none within range")
    else:
        table.add_row("nearest obstacle", f"{m['nearest_obstacle_m']:.3f} m at "
                      f"{math.degrees(m['nearest_bearing_rad']):+.1f} deg (+ = left)")
        table.add_row("range min / max", f"{m['range_min_m']:.3f} / {m['range_max_m']:.3f} m")
    if "target" in m:
        tg = m["target"]
        measured = "no return" if tg["measured_m"] is None else f"{tg['measured_m']:.4f} m (error {tg['error_m'] * 1000:+.1f} mm)"
        table.add_row("target ahead: true / measured", f"{tg['true_m']:.3f} m / {measured}")
    stdout.print(table)


def _sector_table(k: int, scan) -> Table:
    table = Table(title=f"nearest obstacle per sector (scan {k + 1}, t = {scan.t:.1f} s)", title_justify="left",
                  min_width=50)
    table.add_column("sector")
    table.add_column("nearest", justify="right")
    for name, r in zip(SECTORS, sector_minima(scan, len(SECTORS))):
        table.add_row(name, "-" if r is None else f"{r:.2f} m")
    return table


@app.command("lidar-scan")
@recordable
def lidar_scan_cmd(
    scans: Annotated[int, typer.Option(min=1, help="How many LIDAR turns to capture (10 per second).")] = 1,
    beams: Annotated[int | None, typer.Option(min=8, max=8000, help="Beams per turn (default: the device's 800 at 10 Hz; simulator only).",
                                              show_default=False)] = None,
    drive: Annotated[bool, typer.Option("--drive", help="Drive a slow circle while scanning.")] = False,
    target: Annotated[float | None, typer.Option(help="Put a box this many metres ahead of the LIDAR and compare "
                                                 "measured with true distance (simulator only).", show_default=False)] = None,
    watch: Annotated[bool, typer.Option("--watch", help="Live view of the nearest obstacle per sector (terminal; "
                                        "runs in real time until --scans or Ctrl-C).")] = False,
    worlds: Annotated[bool, typer.Option("--worlds", help="List the shipped worlds and exit.")] = False,
    start: StartOpt = None,
    car: CarOpt = "sim",
    token: CarTokenOpt = None,
    world: WorldOpt = None,
    seed: SeedOpt = 0,
    out: OutOpt = None,
    json_out: JsonOpt = False,
    realtime: RealtimeOpt = False,
    params: ParamsOpt = None,
    debug: DebugOpt = False,
) -> None:
    """Capture LIDAR scans (sheet 3.5): nearest obstacle, range, polar plot and point cloud.

    Examples:
      qcarlab lidar-scan --world obstacles --out scans/
      qcarlab lidar-scan --target 1.5
      qcarlab lidar-scan --world berlin.yaml --scans 20 --drive --out berlin/
    """
    if worlds:
        _list_worlds()
        return
    if target is not None and not (math.isfinite(target) and 0.0 < target <= MAX_TARGET_M):
        raise InputError(f"--target must be a distance in (0, {MAX_TARGET_M:g}] m, got {target}")
    if watch and not interactive(json_out):
        raise InputError("--watch needs an interactive terminal (and no --json)")
    if target is not None and parse_car_uri(car)[0] != "sim":
        raise InputError("--target applies to the simulator only")
    world_obj, pose = sim_world(car, world, start, "studio", params)
    if target is not None:
        world_obj, pose, note = target_world(world_obj, pose, target, load_params(params),
                                             chosen=world is not None or start is not None)
        if note is not None:
            stderr.print(f"lidar-scan: {note}", markup=False)
    with open_from_options(car, world_obj, seed, realtime or watch, params, start=pose, token=token,
                           sensors=("lidar",)) as qcar:
        if beams is not None:
            if not hasattr(qcar, "lidar_beams"):
                raise InputError("--beams applies to the simulator only")
            qcar.lidar_beams = beams
        if watch:
            with Live(console=stdout, refresh_per_second=10, transient=False) as view:
                result = capture(qcar, scans, drive, target, on_scan=lambda k, s: view.update(_sector_table(k, s)))
        else:
            result = capture(qcar, scans, drive, target)
        result.metrics.update({"car": car, "world": getattr(world_obj, "name", None), "seed": seed})
        if world_obj is not None:
            from qcarlab.experiments.worlds import topdown_map

            top, extent = topdown_map(world_obj, px_per_m=50.0)  # the extent includes the render's margin
        else:
            top, extent = None, None
    scan, cloud, poses = result.data["scan"], result.data["cloud"], result.data["poses"]
    result.figures["polar.png"] = lambda f: plots.plot_polar_scan(scan.angles, scan.ranges, f)
    if len(cloud):
        result.figures["cloud.png"] = lambda f: plots.plot_cloud(cloud, poses, f, top, extent)
    emit(result, json_out, out, _lidar_summary)


def _camera_summary(result: Result) -> None:
    m = result.metrics
    table = summary_table("camera")
    if "rgbd" in m:
        r = m["rgbd"]
        d = r["depth"]
        table.add_row("RGBD colour / depth", f"{r['color_size'][0]}x{r['color_size'][1]} / "
                      f"{r['depth_size'][0]}x{r['depth_size'][1]} at {r['rate_hz']:g} fps")
        if d["min_m"] is not None:
            table.add_row("depth min / median / max", f"{d['min_m']:.2f} / {d['median_m']:.2f} / {d['max_m']:.2f} m")
        table.add_row("depth valid pixels", f"{d['valid_fraction'] * 100:.1f} %")
        table.add_row("depth at the image centre", f"{r['center_depth_m']:.3f} m" if r["center_depth_m"] else "no data")
    if "csi" in m:
        c = m["csi"]
        sizes = ", ".join(f"{name} {w}x{h}" for name, (w, h) in c["views"].items())
        table.add_row("CSI views", f"{sizes} at {c['rate_hz']:g} fps")
    stdout.print(table)


@app.command("camera")
@recordable
def camera_cmd(
    rgbd: Annotated[bool, typer.Option("--rgbd", help="The Intel D435 RGBD pair: color.png and depth.png (sheet 3.7).")] = False,
    csi: Annotated[bool, typer.Option("--csi", help="The four CSI views and the 360 panorama (sheet 3.6).")] = False,
    start: StartOpt = None,
    car: CarOpt = "sim",
    token: CarTokenOpt = None,
    world: WorldOpt = None,
    seed: SeedOpt = 0,
    out: Annotated[Path | None, typer.Option("--out", help="Folder for the images and results.json (without it "
                                             "nothing is written).", callback=check_out, show_default=False)] = None,
    json_out: JsonOpt = False,
    realtime: RealtimeOpt = False,
    params: ParamsOpt = None,
    debug: DebugOpt = False,
) -> None:
    """Grab camera frames (sheets 3.6, 3.7): RGBD colour + depth with a metre scale, or the CSI 360 views.

    Examples:
      qcarlab camera --rgbd --world track --out cam/
      qcarlab camera --csi --world hallway --out cam/
    """
    if not (rgbd or csi):
        rgbd = True
    world_obj, pose = sim_world(car, world, start, "track", params)
    with open_from_options(car, world_obj, seed, realtime, params, start=pose, token=token) as qcar:
        result = grab(qcar, rgbd=rgbd, csi=csi)
        result.metrics.update({"car": car, "world": getattr(world_obj, "name", None), "seed": seed})
    if rgbd:
        frame = result.data["rgbd"]
        result.figures["color.png"] = lambda f: cv2.imwrite(str(f), frame.color)
        result.figures["depth.png"] = lambda f: plots.plot_depth(frame.depth, f)
    if csi:
        from qcarlab.experiments.worlds import label_views, stitch_panorama

        frames = result.data["csi"]
        views = label_views(dict(zip(("right", "rear", "left", "front"), frames.as_list())))  # each names its camera
        for name, img in views.items():
            result.figures[f"csi_{name}.png"] = lambda f, img=img: cv2.imwrite(str(f), img)
        result.figures["panorama.png"] = lambda f: cv2.imwrite(str(f), stitch_panorama(list(views.values())))
    emit(result, json_out, out, _camera_summary)
    if out is None and not json_out:
        stdout.print("(no images written: pass --out DIR to save them)", markup=False)
