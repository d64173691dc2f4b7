"""Command line: ``hilsim render | ...`` (``python -m hilsim`` too)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Sequence

from hilsim import __version__
from hilsim.config import ConfigError


def _add_render(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render",
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


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="hilsim", description="Hardware-in-the-loop bridge for AUVs.")
    ap.add_argument("--version", action="version", version=f"hilsim {__version__}")
    ap.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    _add_render(sub)
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
            from hilsim.render import render_command

            return render_command(args)
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
