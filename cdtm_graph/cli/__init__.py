"""The ``cdtm`` command line: one module per subcommand, one catch point for errors.

Each subcommand module defines ``register(subparsers)``, which adds its parser and sets
``func`` to a ``run(args) -> int``. User mistakes (:class:`CdtmError`, missing files)
become one line on stderr and exit code 1; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from cdtm_graph.errors import CdtmError

#: Subcommand modules, in the order ``cdtm --help`` lists them.
SUBCOMMANDS = ("demo", "smooth", "track", "simulate", "analyze", "study", "navsim", "accuracy_map")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cdtm",
        description="C-DTM navigation: smooth flight logs from camera, IMU and a DTM; "
                    "analyse and predict accuracy (Kupervasser et al.).")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"cdtm_graph.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"cdtm_graph.cli.{name}":
                raise
            continue  # subcommand not built yet
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except CdtmError as exc:
        print(f"cdtm {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except (FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        print(f"cdtm {args.command}: error: {exc.strerror}: {exc.filename}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # e.g. `cdtm ... | head`: the reader left; stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    except KeyboardInterrupt:
        print(f"cdtm {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
