"""The package installs anywhere: a wheel (not an editable install) in a fresh venv outside
the checkout runs ``cdtm demo``, the README's worked example and its library example from
a directory that is not the checkout.

Offline and without a second copy of the dependencies: the wheel is built from a copy of
the package's sources with the environment's own setuptools (``--no-build-isolation``),
installed with ``--no-deps --no-index`` into a venv whose site-packages reads this
environment's site-packages through a ``.pth`` line (a path line: its own ``.pth`` files,
the checkout's editable finder among them, are not run). Every process runs in a
temporary working directory without ``PYTHONPATH``, and the first asserts that
``cdtm_graph`` is the wheel's copy.

The wheel's runs load the numba kernels it ships prebuilt (``_prebuilt/``, :mod:`factors.jit`),
as a user's first run does; ``benchmarks/bench_first_run.py`` measures what that saves. The
wheel's contents are checked fast, without installing it.
"""

from __future__ import annotations

import os
import pickle
import platform
import re
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import numba
import pytest

from factors.jit import COMPILE_ALL, PACKAGES, PREBUILT

ROOT = Path(__file__).resolve().parents[2]
#: What a wheel is built from: the project's metadata and its two packages.
SOURCES = ("pyproject.toml", "README.md", "cdtm_graph", "factors")
#: Longest a command of the installed package may take (the first compiles numba).
COMMAND_TIMEOUT_S = 600


class Installed:
    """A venv with the wheel installed and a working directory outside the checkout."""

    def __init__(self, root: Path):
        self.venv = root / "venv"
        self.cwd = root / "cwd"
        self.cwd.mkdir()
        self.site = Path()  # the venv's site-packages, once made
        self.env = {k: v for k, v in os.environ.items()
                    if k not in ("PYTHONPATH", "PYTHONHOME", "NUMBA_CACHE_DIR", COMPILE_ALL)}
        self.env["MPLBACKEND"] = "Agg"

    @property
    def python(self) -> Path:
        return self.venv / "bin" / "python"

    def run(self, *argv: str | Path) -> subprocess.CompletedProcess:
        return subprocess.run([str(a) for a in argv], cwd=self.cwd, env=self.env,
                              capture_output=True, text=True, timeout=COMMAND_TIMEOUT_S)

    def cdtm(self, *args: str) -> subprocess.CompletedProcess:
        return self.run(self.venv / "bin" / "cdtm", *args)


def _build_wheel(work: Path) -> Path:
    src = work / "src"
    src.mkdir()
    # (numba's own cache is in __pycache__; the prebuilt kernels in _prebuilt/ go in)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=ignore)
        else:
            shutil.copy2(path, src / name)
    dist = work / "dist"
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                           "--no-build-isolation", "--no-index", "-w", str(dist), str(src)],
                          capture_output=True, text=True, cwd=work)
    assert done.returncode == 0, ("the wheel did not build offline with this environment's "
                                  "setuptools (the test extra asks for >= 70.1: pip install "
                                  f"-e '.[test]'):\n{done.stderr[-2000:]}")
    (wheel,) = dist.glob("cdtm_graph-*.whl")
    return wheel


def test_the_wheel_holds_every_data_file(tmp_path):
    """Catches a file the commands read missing from the wheel (a package-data pattern
    lost or too narrow, e.g. the sample logs' images or their hidden manifests), and the
    prebuilt kernels left out (mutation tried: their package-data lines removed)."""
    with zipfile.ZipFile(_build_wheel(tmp_path)) as wheel:
        packed = set(wheel.namelist())
    folders = [ROOT / "cdtm_graph" / "data", ROOT / "cdtm_graph" / "_prebuilt",
               ROOT / "factors" / "_prebuilt"]
    expected = {p.relative_to(ROOT).as_posix() for folder in folders for p in folder.rglob("*")
                if p.is_file() and "__pycache__" not in p.parts}
    assert {"cdtm_graph/data/geoid/egm96_15.tif",
            "cdtm_graph/data/sample_flight/imu.csv"} <= expected
    assert any(name.startswith("factors/_prebuilt/kernel.cdtm_linearize-") for name in expected)
    assert expected <= packed, sorted(expected - packed)


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Installed:
    work = tmp_path_factory.mktemp("wheel")
    wheel = _build_wheel(work)
    box = Installed(work)
    venv.EnvBuilder(with_pip=False).create(box.venv)
    site = Path(box.run(box.python, "-c", "import sysconfig; "
                        "print(sysconfig.get_paths()['purelib'])").stdout.strip())
    # the dependencies: this environment's site-packages, appended after the venv's own
    (site / "_cdtm_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    box.site = site
    subprocess.run([sys.executable, "-m", "pip", "--python", str(box.python), "install", "-q",
                    "--no-deps", "--no-index", str(wheel)],
                   check=True, capture_output=True, text=True)
    return box


@pytest.mark.slow
def test_the_wheel_is_what_runs(installed):
    """Catches a test that would run the checkout instead of the wheel (PYTHONPATH, the
    editable finder of the checkout leaking in through the dependencies' site-packages)."""
    done = installed.run(installed.python, "-c", "import cdtm_graph; print(cdtm_graph.__file__)")
    assert done.returncode == 0, done.stderr
    where = Path(done.stdout.strip()).resolve()
    assert where.is_relative_to(installed.venv.resolve()), where
    assert not where.is_relative_to(ROOT), where


def _numba_of(index: Path) -> str:
    """The numba version a numba cache index was written by (its first pickle)."""
    with index.open("rb") as f:
        return pickle.load(f)


@pytest.mark.slow
def test_demo_runs_from_the_wheel(installed):
    """Catches the sample flight not shipped as package data, or read from a path relative
    to the repository (a2fce1e: ``.../data/sample_flight:1: not a directory``); and, on the
    platform the kernels are prebuilt for, a first run (numba's cache empty, as after any
    install) compiling a kernel of the packages: numba's cache beside the installed sources
    gets an index for each it compiles (issue 22, "First run"; mutations tried: the wheel
    built without ``_prebuilt/``: every kernel the demo calls named; the fallback off in
    ``factors/jit.py``: the same; ``cdtm_linearize``'s prebuilt index removed: named)."""
    done = installed.cdtm("demo")
    assert done.returncode == 0, done.stderr
    assert "verdict: trusted" in done.stdout
    assert (installed.cwd / "cdtm-demo-out" / "report.json").is_file()
    prebuilt = sorted((ROOT / "factors" / PREBUILT).glob("*.nbi"))
    tag = f".py{sys.version_info.major}{sys.version_info.minor}."
    if platform.machine() == "x86_64" and sys.platform == "linux" and prebuilt \
            and tag in prebuilt[0].name and _numba_of(prebuilt[0]) == numba.__version__:
        compiled = [p.name for package in PACKAGES
                    for p in (installed.site / package).rglob("__pycache__/*.nbi")]
        assert not compiled, compiled


@pytest.mark.slow
def test_geodetic_simulate_and_smooth_run_from_the_wheel(installed):
    """Catches the EGM96 grid not shipped (a2fce1e: ``EGM96 geoid grid not found``)."""
    done = installed.cdtm("simulate", "X", "--origin", "36.5", "127.25", "120",
                          "--frames", "8")
    assert done.returncode == 0, done.stderr
    done = installed.cdtm("smooth", "X", "--out", "R", "--quiet")
    assert done.returncode == 0, done.stderr
    assert (installed.cwd / "R" / "trajectory_geodetic.csv").is_file()


@pytest.mark.slow
def test_readme_library_examples_run_from_the_wheel(installed):
    """Catches a README example reading a path relative to the checkout (a2fce1e:
    ``load_log_and_dtm("data/sample_flight")``) or a bundled file missing from the wheel
    (the sample images)."""
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert blocks
    script = installed.cwd / "readme_example.py"
    script.write_text("\n".join(blocks) + "\nprint('README example done:', verdict.status.value)\n")
    done = installed.run(installed.python, script)
    assert done.returncode == 0, done.stderr
    assert "README example done: trusted" in done.stdout
