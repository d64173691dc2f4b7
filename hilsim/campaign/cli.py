"""``hilsim campaign CAMPAIGN.toml [--out DIR] [--workers N] [--ray [ADDRESS]] [--resume]``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from hilsim.config import ConfigError


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "campaign", help="run a campaign: a matrix of missions (bridge + your stack) or labelled renders",
        description="Run every case of a campaign file (scenarios/CAMPAIGNS.md) locally or on Ray, and write "
                    "results.parquet (or index.parquet for renders) and report.html to --out. Exit status: "
                    "0 when every run passed, 1 when some failed, 2 for a bad campaign file.")
    p.add_argument("campaign", type=Path, help="the campaign file (TOML)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default out/campaigns/<name>)")
    p.add_argument("--workers", type=int, default=None,
                   help="local runs at once (default: the cores / the CPUs a run needs, at least 1)")
    p.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                   help="run each case as a Ray task: a local Ray without ADDRESS, else join that cluster "
                        "(e.g. ray://HEAD:10001); needs pip install 'hilsim[cluster]'")
    p.add_argument("--ray-cpus", type=int, default=None, help="CPUs of the local Ray (default: all)")
    p.add_argument("--shared-out", action="store_true",
                   help="with --ray: --out is a folder every worker sees; runs write there (else their "
                        "folders are sent back to this machine)")
    p.add_argument("--resume", action="store_true",
                   help="run only what --out's results lack: missing runs, and runs that ended in an error "
                        "(pass, fail and timeout are results and are kept)")
    return p


def run(args: argparse.Namespace) -> int:
    from hilsim.campaign.runner import run_campaign

    if args.workers is not None and args.workers < 1:
        print("hilsim campaign: error: --workers must be at least 1", file=sys.stderr)
        return 2
    try:
        o = run_campaign(args.campaign, out=args.out, workers=args.workers, ray=args.ray, resume=args.resume,
                         ray_cpus=args.ray_cpus, shared=args.shared_out)
    except ConfigError as exc:
        print(f"hilsim campaign: error: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:  # Ray missing or unreachable
        print(f"hilsim campaign: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hilsim campaign: interrupted (finished runs are in the results; --resume goes on)", file=sys.stderr)
        return 130
    counts: dict[str, int] = {}
    for r in o.rows:
        counts[str(r.get("status"))] = counts.get(str(r.get("status")), 0) + 1
    print(f"campaign {o.campaign.name}: {len(o.rows)} {'runs' if o.campaign.kind == 'mission' else 'frames'} "
          f"({', '.join(f'{k} {v}' for k, v in sorted(counts.items()))}); {o.ran} tasks run now; "
          f"{o.table}; {o.report}")
    for r in o.rows:
        if o.campaign.kind == "mission" and r.get("status") != "pass":
            print(f"  {r['case']} {r.get('status')}: {r.get('failure')}")
    return 0 if o.ok else 1
