"""The ``v2v`` command line.

Every user mistake ends as one line on stderr (``v2v: error: FIELD: what -- fix: how``)
and exit status 2, never a traceback. Internal errors (bugs) do show a traceback and
exit 1, so they can be reported.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from v2v import __version__
from v2v.errors import EXIT_USER_ERROR, Terminated, UserError, interrupts_unwrapped, signals_as_interrupts


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2 (argparse's own convention too)
        self.exit(EXIT_USER_ERROR, f"v2v: error: {message} -- fix: see `{self.prog} --help`\n")


def _add_run_options(p: argparse.ArgumentParser, default_out: str = "runs/<scenario name>") -> None:
    p.add_argument("--out", type=Path, default=None, help=f"run folder to write (default: {default_out})")
    p.add_argument("--seed", type=int, default=None, help="override the scenario's seed (drives SUMO and every sensor)")
    p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a scenario field, e.g. --set clusters.0.vehicles=20 (repeatable; values are TOML)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar and no table (the run's note, if any, still "
                   "goes to stderr)")
    p.add_argument("--no-replay", action="store_true", help="do not write replay.rrd (rerun recording)")
    p.add_argument("--save-measurements", action="store_true", help="also write measurements.parquet (every raw measurement)")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="v2v", description="Multi-vehicle V2V relative-positioning simulator (SUMO + DGPS/UWB/bearing EKF).")
    p.add_argument("--version", action="version", version=f"v2v {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True, parser_class=_Parser, metavar="COMMAND")

    r = sub.add_parser("run", help="run a scenario file", description="Run a scenario and write its run folder.")
    r.add_argument("scenario", type=Path, help="scenario .toml (layered over the built-in default)")
    _add_run_options(r)

    d = sub.add_parser("demo", help="run the built-in default scenario and print a short table")
    _add_run_options(d, default_out="runs/demo")

    n = sub.add_parser("nets", help="shipped road networks: build, list, import OpenStreetMap")
    nsub = n.add_subparsers(dest="nets_cmd", required=True, parser_class=_Parser,
                            metavar="{build,list,import-osm}")
    nb = nsub.add_parser("build", help="(re)build the shipped nets with netconvert")
    nb.add_argument("names", nargs="*", metavar="NAME", help="nets to build (default: all)")
    nsub.add_parser("list", help="list the shipped nets")
    ni = nsub.add_parser("import-osm", help="turn an OpenStreetMap .osm extract into a net + buildings with heights")
    ni.add_argument("osm", type=Path, metavar="OSM", help="the .osm file")
    ni.add_argument("--name", required=True, help="name of the new net")
    ni.add_argument("--out", type=Path, default=None, help="folder in which <name>/ is written (default: sumo_nets); <name>/ must be new or empty")

    rp = sub.add_parser("replay", help="open a run's replay.rrd in the rerun viewer (or serve the web viewer)")
    rp.add_argument("run_dir", type=Path, help="a run folder (or a .rrd file)")
    rp.add_argument("--web", action="store_true", help="serve the web viewer on 127.0.0.1 instead of a native window")
    rp.add_argument("--port", type=int, default=None, help="web viewer port (with --web; default 9090)")
    rp.add_argument("--grpc-port", type=int, default=None,
                    help="port of rerun's gRPC server, which the web page reads the recording from (with --web; default 9876)")

    s = sub.add_parser("scenario", help="scenario files")
    ssub = s.add_subparsers(dest="scenario_cmd", required=True, parser_class=_Parser, metavar="{check}")
    sc = ssub.add_parser("check", help="validate a scenario and print it resolved")
    sc.add_argument("file", type=Path, help="scenario .toml (layered over the built-in default)")
    sc.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a scenario field, as `v2v run --set` (repeatable; values are TOML)")

    from v2v.sweep import add_sweep_parser

    add_sweep_parser(sub)

    k = sub.add_parser("sky", help="satellites in view at a place and time (or a scenario's start)")
    k.add_argument("--lat", type=float, help="latitude, degrees")
    k.add_argument("--lon", type=float, help="longitude, degrees")
    k.add_argument("--height", type=float, default=None, help="ellipsoidal height, m (default 0; -500 to 100000)")
    k.add_argument("--time", help="UTC time, ISO 8601 (e.g. 2021-04-28T19:00:00Z)")
    k.add_argument("--scenario", type=Path, help="take place and time from a scenario's network and start_utc")
    k.add_argument("--rinex", type=Path, help="RINEX navigation file (default: the scenario's sensors.gnss.ephemeris, else the built-in nominal constellation)")
    k.add_argument("--mask-deg", type=float, default=None,
                   help="elevation mask, degrees (default: the scenario's sensors.gnss.elevation_mask_deg, else 10)")
    return p


def _load(args) -> object:
    from v2v.config.scenario import load_scenario

    overrides = list(args.overrides)
    if args.seed is not None:
        overrides.append(f"seed={args.seed}")
    return load_scenario(getattr(args, "scenario", None), overrides)


def _warn(scenario) -> None:
    """The scenario's warnings (a sensor too slow for the run: Scenario.sparse_sensor_warnings),
    one line each on stderr, also with --quiet: they say what the results will rest on."""
    for line in scenario.sparse_sensor_warnings():
        print(f"v2v: warning: {line}", file=sys.stderr, flush=True)


def _cmd_run(args, demo: bool = False) -> int:
    from v2v.run import run_scenario

    scenario = _load(args)
    _warn(scenario)
    out = args.out or Path("runs") / scenario.name  # type: ignore[attr-defined]
    base = Path(args.scenario).resolve().parent if getattr(args, "scenario", None) else None
    result = run_scenario(
        scenario, out, quiet=args.quiet, replay=not args.no_replay,  # type: ignore[arg-type]
        save_measurements=args.save_measurements, base_dir=base,
    )
    if not args.quiet:
        _print_summary(result.summary, out)
    elif "note" in result.summary:  # (what the results rest on: also with --quiet, as the warnings)
        print("v2v: note: " + result.summary["note"], file=sys.stderr, flush=True)
    return 0


def _print_summary(summary: dict, out: Path) -> None:
    print(f"run folder: {out}")
    print(
        f"scenario {summary['scenario']!r}  seed {summary['seed']}  simulated {summary['simulated_s']:.1f} s  "
        f"wall {summary['wall_s']:.1f} s  ({summary['real_time_factor']}x real time)"
    )
    print(f"vehicles: {', '.join(summary['vehicles'])}  (leads: {', '.join(summary['leads'])})")
    ev = {k: v for k, v in summary["event_counts"].items() if v}
    if ev:
        print("events: " + ", ".join(f"{k} {v}" for k, v in ev.items()))
    table = summary.get("table")
    if table:
        print(table)
    if "note" in summary:
        print("note: " + summary["note"])


def _cmd_nets(args) -> int:
    from v2v import nets

    if args.nets_cmd == "list":
        for info in nets.list_nets():
            print(f"{info.name:16s} {'built' if info.built else 'not built':10s} {info.description}")
        return 0
    if args.nets_cmd == "build":
        names = args.names or [i.name for i in nets.list_nets()]
        for name in names:  # (before any build; the library's error names the scenario's network.name)
            if name not in nets.SHIPPED_NETS:
                raise UserError(f"{name!r} is not a shipped net", field="NAME",
                                fix=f"use one of {', '.join(nets.SHIPPED_NETS)} (v2v nets list); "
                                    "an imported net is built by v2v nets import-osm")
        for name in names:
            built = nets.build_net(name, force=True)
            print(f"built {name}: {built.net_path}")
        return 0
    if args.nets_cmd == "import-osm":
        built = nets.import_osm(args.osm, args.name, out_root=args.out)
        print(f"imported {args.name}: {built.net_path}")
        for rname, edges in (built.routes or {}).items():
            print(f"  route {rname}: {len(edges)} edges")
        return 0
    raise AssertionError(args.nets_cmd)


def replay_command(run_dir: Path, web: bool = False, port: int = 9090, grpc_port: int = 9876) -> list[str]:
    """The rerun command that opens a run's recording (native viewer, or web viewer; either
    serves on loopback only: rerun's own default is every interface). The web viewer is two
    servers: the page on ``port`` and rerun's gRPC server on ``grpc_port``, from which the page
    (in the user's browser) reads the recording."""
    import shutil

    if web:
        for opt, p in (("--port", port), ("--grpc-port", grpc_port)):
            if not 1 <= p <= 65535:
                raise UserError(f"port {p} is not a TCP port", field=opt, fix="give a port in 1..65535")
        if port == grpc_port:
            raise UserError(f"the web page and rerun's gRPC server cannot share port {port}", field="--grpc-port",
                            fix="give two different ports (defaults: --port 9090, --grpc-port 9876)")
    rrd = run_dir if run_dir.suffix == ".rrd" else run_dir / "replay.rrd"
    if not rrd.is_file():
        raise UserError(f"no replay at {rrd}", field="RUN_DIR", fix="give a run folder written without --no-replay")
    with rrd.open("rb") as f:
        head = f.read(4)
    if head != b"RRF2":  # (rerun's file header; rerun itself serves an empty viewer for a bad file)
        raise UserError(f"{rrd} is not a rerun recording ({len(head)} byte header {head!r}, not b'RRF2')",
                        field="RUN_DIR", fix="run the scenario again to write its replay.rrd")
    exe = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun") or "rerun"
    if web:
        return [exe, "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(port), "--port", str(grpc_port),
                str(rrd)]
    return [exe, "--bind", "127.0.0.1", str(rrd)]


def recording_whole(rrd: Path) -> bool:
    """Whether ``rrd`` ends as a whole recording of the pinned rerun (0.41) ends: a 32-byte
    trailer (footer offset and length, u64 little-endian, a u32 checksum, ``RRF2FOOT``, a u32
    version) after a footer that ends where the trailer starts. A copy cut short has none (the
    viewer would show its first part, or nothing); reading it costs two small reads, where
    ``rerun rrd verify`` decodes the whole file (~0.4 s per MB)."""
    import struct

    size = rrd.stat().st_size
    if size < 8 + 32:
        return False
    with rrd.open("rb") as f:
        f.seek(size - 32)
        tail = f.read(32)
    offset, length = struct.unpack("<QQ", tail[:16])
    return tail[20:28] == b"RRF2FOOT" and offset + length == size - 32


def web_viewer_url(port: int, grpc_port: int) -> str:
    """The address that opens the web viewer on the recording (rerun prints the same one)."""
    from urllib.parse import quote

    return f"http://127.0.0.1:{port}?url=" + quote(f"rerun+http://localhost:{grpc_port}/proxy", safe="")


def _port_in_use(port: int) -> bool:
    """Whether a server already listens on 127.0.0.1:``port`` (another replay, another program)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # (what rerun's server sets: TIME_WAIT is no conflict)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return True
    return False


def _cmd_replay(args) -> int:
    import os
    import subprocess

    for opt, val in (("--port", args.port), ("--grpc-port", args.grpc_port)):
        if val is not None and not args.web:
            raise UserError(f"{opt} is the web viewer's", field=opt, fix=f"add --web, or leave {opt} out")
    port = 9090 if args.port is None else args.port
    grpc_port = 9876 if args.grpc_port is None else args.grpc_port
    cmd = replay_command(args.run_dir, args.web, port, grpc_port)
    ssh = f"ssh -L {port}:127.0.0.1:{port} -L {grpc_port}:127.0.0.1:{grpc_port}"
    if not recording_whole(Path(cmd[-1])):
        raise UserError(f"{cmd[-1]} is not a whole rerun recording (it does not end with rerun's footer: cut short "
                        "when it was copied?)", field="RUN_DIR",
                        fix="copy it again, or run the scenario again to write its replay.rrd")  # (before the display)
    if not args.web and sys.platform.startswith("linux") and not any(
            os.environ.get(k) for k in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")):
        raise UserError("no display for the native viewer (DISPLAY and WAYLAND_DISPLAY are not set)", field="replay",
                        fix=f"use --web and open {web_viewer_url(port, grpc_port)} (on a remote machine through {ssh})")
    if args.web:
        for opt, p in (("--port", port), ("--grpc-port", grpc_port)):
            if _port_in_use(p):
                raise UserError(f"port {p} on 127.0.0.1 is in use (another replay?)", field=opt,
                                fix=f"stop what listens there or give {opt} another port")
        print(f"serving the web viewer: open {web_viewer_url(port, grpc_port)} (the page on port {port}, the recording "
              f"on {grpc_port}; from another machine: {ssh}; Ctrl-C to stop)", file=sys.stderr)
    return subprocess.call(cmd)


def _cmd_scenario(args) -> int:
    from v2v.config.scenario import load_scenario
    from v2v.run import check_scenario

    sc = load_scenario(args.file, args.overrides)
    check_scenario(sc, Path(args.file).resolve().parent)
    _warn(sc)
    print(sc.to_toml())
    print(f"# {args.file}: OK", file=sys.stderr)
    return 0


def _cmd_sky(args) -> int:
    from datetime import datetime

    import numpy as np

    from v2v.sensors.gnss.sky import sky_view
    from v2v.sensors.gnss.time import utc_to_gps_s

    if args.scenario is not None:
        from v2v.config.scenario import load_scenario
        from v2v.run import resolve_network

        given = [f"--{n}" for n in ("lat", "lon", "height", "time") if getattr(args, n) is not None]
        if given:
            raise UserError(f"{', '.join(given)} and --scenario both give the place or time", field=given[0],
                            fix="give --lat, --lon, --time (and --height), or --scenario alone")

        from v2v.run import absolute_paths

        # (its relative paths, net_file and ephemeris, are relative to its folder, as for v2v run)
        sc = absolute_paths(load_scenario(args.scenario), Path(args.scenario).resolve().parent)
        net = resolve_network(sc)
        lat, lon = net.georef.xy_to_geodetic(0.0, 0.0)
        lat_deg, lon_deg = float(np.degrees(lat)), float(np.degrees(lon))
        h = sc.network.origin_h_m
        when = sc.start_utc
        mask_deg = sc.sensors.gnss.elevation_mask_deg if args.mask_deg is None else args.mask_deg
        scenario_eph = None if args.rinex is not None else sc.sensors.gnss.ephemeris
    else:
        mask_deg = 10.0 if args.mask_deg is None else args.mask_deg
        scenario_eph = None
        if args.lat is None or args.lon is None or args.time is None:
            raise UserError("give --lat, --lon and --time, or --scenario", field="sky", fix="e.g. v2v sky --lat 51.08 --lon -114.13 --time 2021-04-28T19:00:00Z")
        if not (-90 <= args.lat <= 90 and -180 <= args.lon <= 180):
            raise UserError("latitude/longitude out of range", field="--lat/--lon", fix="degrees, lat in [-90, 90], lon in [-180, 180]")
        lat_deg, lon_deg, h = args.lat, args.lon, 0.0 if args.height is None else args.height
        try:
            when = datetime.fromisoformat(args.time.replace("Z", "+00:00"))
        except ValueError:
            raise UserError(f"cannot read time {args.time!r}", field="--time", fix="ISO 8601, e.g. 2021-04-28T19:00:00Z") from None
    if not 0.0 <= mask_deg < 90.0:  # (also NaN)
        raise UserError(f"elevation mask {mask_deg} deg is not in [0, 90)", field="--mask-deg",
                        fix="give degrees above the horizon, e.g. --mask-deg 10")
    if not -500.0 <= h <= 100e3:  # (also NaN)
        raise UserError(f"height {h} m is not near the Earth's surface", field="--height",
                        fix="give metres above the ellipsoid, from -500 to 100000")
    try:
        t_gps = utc_to_gps_s(when)
        if scenario_eph is not None:  # the scenario's sky (its RINEX file or the nominal constellation)
            from v2v.sensors.gnss.source import ephemeris_source

            eph = ephemeris_source(scenario_eph, float(t_gps), 0.0)
        else:
            eph = _ephemeris(args.rinex, t_gps)
        df = sky_view(np.radians(lat_deg), np.radians(lon_deg), h, t_gps, eph, np.radians(mask_deg))
    except UserError as exc:  # the time's errors name the option it came from (not a scenario's start_utc)
        if args.scenario is None and exc.field in ("utc", "start_utc"):
            raise UserError(f"{args.time}: {exc.message}", field="--time",
                            fix="give a time the ephemeris covers (a RINEX nav file: its day), after 1980-01-06"
                            ) from None
        raise
    src = "nominal 27-slot constellation" if (scenario_eph == "nominal" or (scenario_eph is None and args.rinex is None)) \
        else f"RINEX {scenario_eph or args.rinex}"
    print(f"# {lat_deg:.5f} deg, {lon_deg:.5f} deg, {h:.0f} m at {when.isoformat()} (GPS {t_gps:.0f} s); "
          f"mask {mask_deg} deg; {src}")
    print(df.to_string(index=False) if len(df) else "(no satellites in view)")
    return 0


def _ephemeris(rinex: Path | None, t_gps: float):
    if rinex is not None:
        from v2v.sensors.gnss.rinex import read_rinex_nav

        return read_rinex_nav(rinex)
    from v2v.sensors.gnss.constellation import NominalConstellation

    return NominalConstellation(t_gps)


def main(argv: list[str] | None = None) -> int:
    import signal

    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # (argparse's own message sends the user to the top-level help, not the command's)
        cmd = " ".join(["v2v", args.cmd, *(getattr(args, f"{args.cmd}_cmd", None) or "").split()])
        print(f"v2v: error: unrecognized arguments: {' '.join(extra)} -- fix: see `{cmd} --help`", file=sys.stderr)
        return EXIT_USER_ERROR
    from v2v.io.atomic import PUBLISHED

    published_before = len(PUBLISHED)
    try:
        # (a signal inside a numba kernel comes out as its SystemError; one raised inside a
        # ctypes callback is swallowed, and the run loop raises it again)
        with signals_as_interrupts(), interrupts_unwrapped():
            return _dispatch(args)
    except UserError as exc:
        print(f"v2v: error: {exc.one_line()}", file=sys.stderr)
        return EXIT_USER_ERROR
    except BrokenPipeError:  # stdout piped into e.g. head, which stopped reading: not an error
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # (no second error at exit's flush)
        return 128 + signal.SIGPIPE
    except KeyboardInterrupt as exc:
        what = "terminated (SIGTERM)" if isinstance(exc, Terminated) else "interrupted"
        if args.cmd == "replay":  # Ctrl-C is how the web viewer is stopped
            print(f"v2v: replay viewer {what}", file=sys.stderr)
            return 0 if not isinstance(exc, Terminated) else 128 + signal.SIGTERM
        if args.cmd == "sweep" and getattr(args, "sweep_cmd", None) == "run":  # (v2v.sweep.run_study's cleanup)
            print(f"v2v: {what}; the sweep folder keeps every run that completed (runs.parquet lists them): run the "
                  "same command again for the rest", file=sys.stderr)
            return 128 + signal.SIGTERM if isinstance(exc, Terminated) else 130
        done = _completed_run_folder(args, published_before)
        if done is not None:  # the signal came after the run's folder was whole: the run is done
            print(f"v2v: {what} after the run finished; its folder {done} is complete", file=sys.stderr)
            return 0
        print(f"v2v: {what}; no partial run folder was kept", file=sys.stderr)
        return 128 + signal.SIGTERM if isinstance(exc, Terminated) else 130


def _completed_run_folder(args: argparse.Namespace, since: int) -> Path | None:
    """The run folder ``v2v run`` / ``demo`` completed in this call, if it did (an interrupt
    that lands while the summary is printed, or as the process ends, loses nothing)."""
    from v2v.io.atomic import PUBLISHED

    out = getattr(args, "out", None)
    if args.cmd not in ("run", "demo") or out is None:
        return None
    return out if Path(out).resolve() in PUBLISHED[since:] else None


def console_main() -> int:
    """The ``v2v`` command's entry point: :func:`main`, after which Ctrl-C and SIGTERM are
    ignored, so that a signal arriving while the finished process shuts down (libsumo's and
    rerun's teardown) cannot turn a complete run into a failed exit status."""
    import signal

    rc = main()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    return rc


def _dispatch(args: argparse.Namespace) -> int:
    if args.cmd == "run":
        return _cmd_run(args)
    if args.cmd == "demo":
        args.scenario = None
        if args.out is None:
            args.out = Path("runs") / "demo"
        return _cmd_run(args, demo=True)
    if args.cmd == "nets":
        return _cmd_nets(args)
    if args.cmd == "scenario":
        return _cmd_scenario(args)
    if args.cmd == "replay":
        return _cmd_replay(args)
    if args.cmd == "sweep":
        from v2v.sweep import cmd_sweep

        return cmd_sweep(args)
    if args.cmd == "sky":
        return _cmd_sky(args)
    raise AssertionError(args.cmd)


if __name__ == "__main__":
    sys.exit(main())
