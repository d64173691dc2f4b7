"""``python -m hilsim.campaign CAMPAIGN.toml ...``: the same as ``hilsim campaign``."""

from __future__ import annotations

import argparse
import sys

from hilsim.campaign.cli import add_parser, run


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m hilsim.campaign")
    sub = ap.add_subparsers(dest="command", required=True)
    add_parser(sub)
    args = ap.parse_args(["campaign", *(sys.argv[1:] if argv is None else argv)])
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
