"""``cdtm demo``: smooth the bundled sample log into ./cdtm-demo-out and print the errors."""

from __future__ import annotations

import argparse
from pathlib import Path

from cdtm_graph.atomic import read_manifest
from cdtm_graph.cli.outdir import add_out_option
from cdtm_graph.cli.smooth import smooth_log_to_dir, summary
from cdtm_graph.outputs import RUN_WRITER

SAMPLE_LOG = Path(__file__).resolve().parents[2] / "data" / "sample_flight"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="smooth the bundled sample log into ./cdtm-demo-out")
    add_out_option(p, "output directory", default="cdtm-demo-out")
    p.set_defaults(func=run, mode="batch", plane="reintersect", robust="none", lag_s=None,
                   gate=None, plots=True, quiet=False)


def run(args: argparse.Namespace) -> int:
    out_dir = Path(args.out)
    out = smooth_log_to_dir(str(SAMPLE_LOG), out_dir, args)
    print(f"sample log: {SAMPLE_LOG}")
    print(summary(out, out_dir))
    written = sorted(n for n, w in (read_manifest(out_dir) or {}).items() if w == RUN_WRITER)
    print(f"wrote {', '.join(written)}")
    return 0
