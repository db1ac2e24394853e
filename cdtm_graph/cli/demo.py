"""``cdtm demo``: smooth the bundled sample log into ./cdtm-demo-out and print the errors."""

from __future__ import annotations

import argparse
from pathlib import Path

from cdtm_graph.cli.smooth import smooth_log_to_dir, summary

SAMPLE_LOG = Path(__file__).resolve().parents[2] / "data" / "sample_flight"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="smooth the bundled sample log into ./cdtm-demo-out")
    p.add_argument("--out", default="cdtm-demo-out", help="output directory")
    p.set_defaults(func=run, mode="batch", plane="reintersect", robust="none", lag_s=None,
                   gate=None, plots=True, quiet=False)


def run(args: argparse.Namespace) -> int:
    out_dir = Path(args.out)
    out = smooth_log_to_dir(str(SAMPLE_LOG), out_dir, args)
    print(f"sample log: {SAMPLE_LOG}")
    print(summary(out, out_dir))
    print(f"wrote {', '.join(sorted(p.name for p in out_dir.iterdir()))}")
    return 0
