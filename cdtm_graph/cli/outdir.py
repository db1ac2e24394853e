"""The output-directory options every writing command shares (``--out``, ``--force``).

The rules themselves are :mod:`cdtm_graph.atomic`'s; this module words them for ``--help``
and opens the output directory with the command's arguments.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

from cdtm_graph.atomic import atomic_output_dir

#: How ``--help`` states what may be an output directory.
OUT_RULES = ("a new path, an empty directory, or an earlier cdtm output directory (its "
             "hidden .cdtm-run.json lists the files cdtm wrote there: this command's are "
             "replaced or removed, anything else is kept); never an existing file, nor the "
             "input, inside it or around it. Checked before any work")
FORCE_HELP = ("also write into a non-empty directory cdtm did not write: the outputs go "
              "beside what is there; no existing file is ever deleted or overwritten (a name "
              "clash is an error) and the input is still refused")


def add_out_option(parser: argparse.ArgumentParser, what: str,
                   default: str | None = None) -> None:
    """``--out DIR`` (required when ``default`` is None) and ``--force``."""
    dflt = f" (default: {default})" if default is not None else ""
    parser.add_argument("--out", type=Path, required=default is None, metavar="DIR",
                        default=None if default is None else Path(default),
                        help=f"{what}{dflt}: {OUT_RULES}")
    add_force_option(parser)


def add_force_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--force", action="store_true", help=FORCE_HELP)


@contextlib.contextmanager
def output_dir(args: argparse.Namespace, target: str | os.PathLike, writer: str, *,
               protected: Iterable[str | os.PathLike] = (), names: Iterable[str] = (),
               label: str = "--out") -> Iterator[Path]:
    """:func:`~cdtm_graph.atomic.atomic_output_dir` with the command's ``--force``; the
    earlier outputs a rerun removed (``--plots`` left out, say) are named in one line on
    stderr."""
    with atomic_output_dir(target, writer=writer, force=bool(getattr(args, "force", False)),
                           protected=[p for p in protected if p is not None], names=names,
                           label=label,
                           on_removed=lambda removed: say_removed(args, target, removed)
                           ) as staging:
        yield staging


def say_removed(args: argparse.Namespace, target: str | os.PathLike,
                removed: list[str]) -> None:
    """One line on stderr naming the earlier outputs a rerun removed from ``target``."""
    command = f"cdtm {args.command}" if getattr(args, "command", None) else "cdtm"
    print(f"{command}: removed {len(removed)} earlier output(s) of this command in {target} "
          f"that this run does not write: {', '.join(removed)}", file=sys.stderr)
