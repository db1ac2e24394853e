"""Start-up: ``cdtm --help``, every command's ``--help`` and its usage errors load no numerics.

A user who asks for help or mistypes an option waits for the interpreter and the parser,
not for GTSAM, numba, SciPy or OpenCV (``cdtm smooth --help`` took 1.1-1.45 s when its
module imported the estimator for the enums of its choices; ~0.1 s now:
``benchmarks/bench_startup.py``). Each test runs one fresh interpreter for every command
(``sys.modules`` there is the measure, not time: the tests assert no times).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from cdtm_graph.cli import COMMANDS

ROOT = Path(__file__).resolve().parents[2]

#: What the parser must not load: the numerics (numpy itself too: nothing in a parser
#: needs it).
HEAVY = ("numpy", "gtsam", "numba", "scipy", "cv2", "trimesh", "pandas", "matplotlib")

#: Runs each argv (a JSON list of lists, argv[1]) through ``cdtm``'s ``main`` in this one
#: process, in order, stderr a terminal; prints per argv its exit code, the heavy modules
#: loaded so far and stderr (a step that loads one shows first, later steps keep it).
_PROBE = r"""
import contextlib, io, json, sys
from cdtm_graph.cli import ALL, build_parser, main
heavy = set(sys.argv[2].split(","))
rows = []
class Terminal(io.StringIO):  # stderr as a user's: the compilation announcement is on
    def isatty(self):
        return True
def loaded():
    return sorted(heavy & {name.partition(".")[0] for name in sys.modules})
for argv in json.loads(sys.argv[1]):
    out, err = io.StringIO(), Terminal()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        if argv == ["<every parser>"]:
            build_parser(only=ALL)
            code = 0
        else:
            try:
                code = main(argv)
            except SystemExit as exit_:
                code = exit_.code
    rows.append({"argv": argv, "code": code, "heavy": loaded(), "out": out.getvalue(),
                 "err": err.getvalue()})
print(json.dumps(rows))
"""


def _probe(argvs: list[list[str]]) -> list[dict]:
    done = subprocess.run(
        [sys.executable, "-c", _PROBE, json.dumps(argvs), ",".join(HEAVY)], cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True,
        timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = json.loads(done.stdout.strip().splitlines()[-1])
    assert [r["argv"] for r in rows] == argvs  # every step ran
    return rows


def _first_heavy(rows: list[dict]) -> dict | None:
    return next((r for r in rows if r["heavy"]), None)


def test_help_of_every_command_and_every_parser_load_no_numerics():
    """``cdtm --version``, ``cdtm --help``, a mistyped command, each command's ``--help``
    (and ``cdtm import``'s sources'), then every parser built at once: no numerics loaded.

    Catches a command module importing the estimator at its top for its choices'
    vocabulary (mutation tried: ``import gtsam`` back at the top of cli/smooth.py; also
    ``from cdtm_graph.sim.simulate import SimulationSettings`` back in cli/simulate.py),
    a light module reaching a heavy one, and a package ``__init__`` loading its modules
    eagerly again (``cdtm_graph.smoother``, ``factors``, ``cdtm_graph.flightlog``...).
    """
    argvs = [["--version"], ["--help"], ["nosuch"]]
    argvs += [[name, "--help"] for name in COMMANDS]
    argvs += [["import", source, "--help"] for source in ("euroc", "rosbag", "px4")]
    argvs += [["<every parser>"]]
    rows = _probe(argvs)
    assert _first_heavy(rows) is None, _first_heavy(rows)
    by_argv = {tuple(r["argv"]): r for r in rows}
    assert by_argv[("--version",)]["code"] == 0 and by_argv[("nosuch",)]["code"] == 2
    for name in COMMANDS:  # each help was printed whole (not an error before it)
        row = by_argv[(name, "--help")]
        assert row["code"] == 0 and row["out"].startswith(f"usage: cdtm {name}"), row


#: Option values a parser accepts and the command refuses before any work: exit 1, one
#: line (argv, the words the line must hold).
_BAD_VALUES = [
    (["smooth", "LOG", "--out", "R", "--gate", "2"], "--gate 2.0: expected a probability"),
    (["smooth", "LOG", "--out", "R", "--lag-s", "5"], "--lag-s needs --mode incremental"),
    (["smooth", "LOG", "--out", "R", "--mode", "incremental", "--lag-s", "-1"],
     "--lag-s -1.0: expected a finite lag"),
    (["smooth", " ", "--out", "R"], "LOG is empty"),
    (["navsim", "--frames", "1"], "--frames 1: expected at least 2 frames"),
]


def test_usage_errors_of_every_command_load_no_numerics():
    """A mistyped option of every command (exit 2, that command's usage), missing
    arguments (exit 2), and option values refused before any work (exit 1, one line):
    no numerics loaded by the time the error is out.

    Catches a usage error that imports the estimator first: the mutation above, or a
    command checking its options after importing its numerics (mutation tried: the imports
    of ``settings_from_args`` in cli/smooth.py moved above its checks; also the navsim
    ``--frames`` check after ``NavsimSettings`` is imported); and, stderr being a terminal,
    the compilation announcement importing numba before the command runs (mutation tried:
    ``from numba.core import event`` back at the start of ``announced``).
    """
    mistyped = [[name, "--no-such-option"] for name in COMMANDS]
    missing = [["smooth"], ["track"], ["import", "px4", "x.ulg"], ["analyze", "LOG"],
               ["simulate", "OUT", "--frames", "many"], ["study", "nosuch"]]
    bad = [argv for argv, _ in _BAD_VALUES]
    rows = _probe(mistyped + missing + bad)
    assert _first_heavy(rows) is None, _first_heavy(rows)
    for row in rows[:len(mistyped) + len(missing)]:
        command = " ".join(a for a in row["argv"][:2] if a in COMMANDS or a == "px4")
        assert row["code"] == 2, row
        assert row["err"].startswith(f"usage: cdtm {command}"), row
    for row, (argv, words) in zip(rows[len(mistyped) + len(missing):], _BAD_VALUES,
                                  strict=True):
        lines = row["err"].strip().splitlines()
        assert row["code"] == 1 and len(lines) == 1, row
        assert lines[0].startswith(f"cdtm {argv[0]}: error: ") and words in lines[0], row


_ANNOUNCED = r"""
import io, sys
from cdtm_graph.cli.compiling import announced
class Terminal(io.StringIO):
    def isatty(self):
        return True
stream = Terminal()
with announced("cdtm x", stream=stream) as counter:
    before = "numba" in sys.modules
    from numba import njit

    @njit(cache=False)
    def twice(x):
        return 2.0 * x

    twice(1.0)
print(before, counter.compiled, len(stream.getvalue().splitlines()))
"""


def test_the_announcement_waits_for_the_command_to_load_numba():
    """On a terminal, the compilation announcement loads no numba itself, and still sees a
    kernel compiled after the command loaded numba inside it (the other path, numba loaded
    before: tests/cli/test_cli.py).

    Catches ``announced`` importing numba as it starts (every command on a terminal paid
    numba's import, an option refused with exit 1 too), and a deferred listener that is
    never registered (mutation tried: the hook not inserted into ``sys.meta_path``: 0
    kernels counted).
    """
    done = subprocess.run([sys.executable, "-c", _ANNOUNCED], cwd=ROOT, capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["False", "1", "2"]


def test_a_run_never_imports_scipy_stats():
    """What a smoothing run imports (the smoothers, the run's pipeline and judgement, the
    CLI's smooth command): never ``scipy.stats``, whose import alone costs ~1.1 s of every
    ``cdtm smooth`` (issue 22; quantiles come from :mod:`cdtm_graph.constants`), nor
    ``scipy.optimize`` (0.25 s), ``scipy.linalg`` (0.16 s) or ``scipy.ndimage`` (0.05 s,
    only when a fix search runs). Mutations tried: ``scipy.stats.chi2.ppf`` back in
    ``robust/imu_walk.py`` (it was, 2026-11-27, imported with the graph builders);
    ``from scipy.optimize import brentq`` back in ``robust/map_error.py``, ``import
    scipy.linalg`` in ``robust/imu_walk.py`` (both were, 2026-11-28): each fails this
    test. (numba imports ``scipy.linalg.cython_blas`` itself when it loads a kernel that
    calls BLAS: after a run, not at import.)"""
    heavy = ("scipy.stats", "scipy.optimize", "scipy.linalg", "scipy.ndimage")
    probe = ("import sys, cdtm_graph.smoother.batch, cdtm_graph.smoother.incremental,"
             " cdtm_graph.run.pipeline, cdtm_graph.cli.smooth, cdtm_graph.verdict;"
             f" print(*[m for m in {heavy!r} if m in sys.modules])")
    done = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == []
