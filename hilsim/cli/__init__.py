"""Command line: ``hilsim run | record | render | experiment | campaign`` (``python -m hilsim`` too).

The package gathers every command: this module builds the parser and dispatches;
each command's code is a module beside it (:mod:`hilsim.cli.run` for ``run`` and
``record``, :mod:`hilsim.cli.render`, :mod:`hilsim.cli.experiment`), imported only
when its command runs. A command that lives with its feature registers itself in
:data:`PLUGINS` (module with ``add_parser(subparsers)`` and ``run(args) -> int``).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from pathlib import Path
from typing import Sequence

from hilsim import __version__
from hilsim.config import ConfigError


#: commands that live with their feature: name -> module with add_parser(subparsers) and run(args)
PLUGINS: dict[str, str] = {"campaign": "hilsim.campaign.cli"}

_COMMON = argparse.ArgumentParser(add_help=False)
_COMMON.add_argument("--log-level", default=argparse.SUPPRESS, choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                     help="logging level (default INFO)")


def _add_render(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render", parents=[_COMMON],
        help="render the sonar and camera frames of a scenario at named positions or poses",
        description="Render the sonar frame (raw + fan PNG) and the camera image at one or more "
                    "vehicle poses and write them with a JSON of what was done.",
    )
    p.add_argument("scenario", nargs="?", default=None,
                   help="scenario folder, .toml file or bundled name (default: water_tank)")
    p.add_argument("--at", default=None,
                   help="named positions of the scenario separated by commas (A,B,C), or a pose "
                        "'x,y,z,yaw' in metres NED and degrees (default: every named position, "
                        "else the vehicle's initial pose)")
    p.add_argument("--out", default="out", type=Path, help="output folder (default: out)")
    p.add_argument("--sonar", default=None, help="sonar sensor name (default: the first sonar)")
    p.add_argument("--camera", default=None, help="camera sensor name (default: the first camera)")
    p.add_argument("--elevation-rays", type=int, default=None,
                   help="rays per beam in elevation (default: the profile's; the paper used 1000)")
    p.add_argument("--paper-sampling", action="store_true",
                   help="the paper's literal method: no echo spreading (shows its empty-bin artifacts)")
    p.add_argument("--gain", choices=("paper", "fixed"), default=None, help="gain mode (default: profile's)")
    p.add_argument("--seed", type=int, default=None, help="seed for noise (default: the scenario's)")


def _add_run(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run", parents=[_COMMON], help="run the live bridge: the simulation and every device the scenario wires up",
        description="Build the world, the vehicle, the sensors and the scenario's devices and serve "
                    "them until Ctrl-C/SIGTERM or --duration. Prints the endpoints when listening.")
    p.add_argument("scenario", nargs="?", default=None,
                   help="scenario folder, .toml file or bundled name (default: water_tank)")
    p.add_argument("--fast", action="store_true", help="virtual clock: as fast as possible (tests, batch runs)")
    p.add_argument("--time-scale", type=float, default=1.0,
                   help="run the real-time clock this many times faster than the wall clock (e.g. 4 for a "
                        "control stack under test that paces itself by the frames' timestamps)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many simulated seconds")
    p.add_argument("--endpoints", type=Path, default=None, help="write the endpoints as JSON to this file")
    p.add_argument("--truth", type=Path, default=None, metavar="FILE",
                   help="the ground truth CSV (default: truth.csv beside --endpoints, else in the run folder)")
    p.add_argument("--truth-rate", type=float, default=20.0, metavar="HZ",
                   help="ground truth rows per simulated second (default 20; 0: every physics tick)")
    p.add_argument("--summary", type=Path, default=None, metavar="FILE",
                   help="the run's summary JSON, written at shutdown (default: summary.json beside "
                        "--endpoints, else in the run folder)")
    p.add_argument("--bind", default="127.0.0.1", help="address servers listen on (default 127.0.0.1)")
    p.add_argument("--broadcast", default="127.0.0.1",
                   help="destination of UDP status/beacon messages (default 127.0.0.1: stays on this machine)")
    p.add_argument("--record", type=Path, default=None, help="also write the DIDSON-like stream to FILE.ddf")
    p.add_argument("--seed", type=int, default=None, help="seed for noise (default: the scenario's)")
    p.add_argument("--physics-rate", type=float, default=200.0, help="physics rate [Hz] (default 200)")
    p.add_argument("--status-interval", type=float, default=5.0,
                   help="seconds of simulated time between status lines (0: none)")
    p.add_argument("--epoch", type=float, default=None,
                   help="UNIX time stamped for simulated time 0 (default: now); fixes timestamps for "
                        "byte-identical runs")
    p.add_argument("--pty-dir", type=Path, default=None,
                   help="folder for the emulated serial ports' symlinks (default: a fresh temporary folder)")
    p.add_argument("--render-timeout", type=float, default=10.0,
                   help="seconds a frame may take before the render worker is deemed hung and restarted")
    p.add_argument("--console", type=int, default=0, metavar="PORT",
                   help="port of the live browser console on the bind address (default 0: a free port)")
    p.add_argument("--no-console", dest="console", action="store_const", const=None, help="no console")
    p.add_argument("--record-mcap", type=Path, default=None, metavar="FILE.mcap",
                   help="record the run for Foxglove/Lichtblick: sonar, camera, ground truth, readings, commands")
    p.add_argument("--foxglove", type=int, nargs="?", const=8765, default=None, metavar="PORT",
                   help="serve the same channels live over the Foxglove WebSocket protocol (default port 8765)")


def _add_record(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("record", parents=[_COMMON],
                       help="record the DIDSON-like sonar stream of a scenario to a .ddf file",
                       description="Run the scenario on the virtual clock and write N frames of its "
                                   "DIDSON-like stream to a DDF file (the bytes a TCP client receives).")
    p.add_argument("scenario", nargs="?", default=None)
    p.add_argument("--out", type=Path, required=True, help="the .ddf file to write")
    p.add_argument("--frames", type=int, default=20, help="number of frames (default 20)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--epoch", type=float, default=None, help="UNIX time stamped for simulated time 0")


def _add_experiment(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("experiment", parents=[_COMMON],
                       help="reproduce an experiment of the seed paper (water-tank)",
                       description="water-tank: drive the vehicle forward 1.5 m above the floor, record the "
                                   "sonar and camera at positions A, B and C, and write the paper's Fig. 4 and "
                                   "the 96 x 1000 sampling vs artifact-free comparison figure.")
    p.add_argument("name", choices=("water-tank",), help="which experiment")
    p.add_argument("scenario", nargs="?", default=None, help="scenario (default: water_tank)")
    p.add_argument("--out", type=Path, default=Path("out/experiment"), help="output folder")
    p.add_argument("--speed", type=float, default=0.2, help="forward speed to hold [m/s] (default 0.2)")
    p.add_argument("--seed", type=int, default=None)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="hilsim", description="Hardware-in-the-loop bridge for AUVs.")
    ap.add_argument("--version", action="version", version=f"hilsim {__version__}")
    ap.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    _add_render(sub)
    _add_run(sub)
    _add_record(sub)
    _add_experiment(sub)
    for name, module in PLUGINS.items():
        try:
            importlib.import_module(module).add_parser(sub)
        except ImportError as exc:  # an optional feature that is not installed
            logging.getLogger(__name__).debug("command %s unavailable: %s", name, exc)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    logging.basicConfig(level=getattr(logging, args.log_level), format="%(levelname)s %(name)s: %(message)s")
    if args.command is None:
        ap.print_help()
        return 2
    try:
        if args.command == "render":
            from hilsim.cli.render import render_command

            return render_command(args)
        if args.command == "experiment":
            from hilsim.cli.experiment import experiment_command

            return experiment_command(args)
        if args.command in ("run", "record"):
            from hilsim.cli.run import record_command, run_command

            return run_command(args) if args.command == "run" else record_command(args)
        if args.command in PLUGINS:
            return int(importlib.import_module(PLUGINS[args.command]).run(args))
    except (ConfigError, FileNotFoundError, ValueError, KeyError) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"hilsim {args.command}: error: {msg}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"hilsim {args.command}: interrupted", file=sys.stderr)
        return 130
    ap.error(f"unknown command {args.command!r}")
    return 2


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
