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

The wheel's runs load the numba kernels the checkout has compiled
(:func:`_reuse_compiled_kernels`): a user's first run compiles them, and what that costs is
``benchmarks/bench_first_run.py``'s to measure, not this file's. The wheel's contents are
checked fast, without installing it.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

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
        self.env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
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
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "*.nbi", "*.nbc")
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
    lost or too narrow, e.g. the sample logs' images or their hidden manifests)."""
    with zipfile.ZipFile(_build_wheel(tmp_path)) as wheel:
        packed = {name for name in wheel.namelist() if name.startswith("cdtm_graph/data/")}
    data = ROOT / "cdtm_graph" / "data"
    expected = {f"cdtm_graph/{p.relative_to(data.parent).as_posix()}" for p in data.rglob("*")
                if p.is_file() and "__pycache__" not in p.parts}
    assert {"cdtm_graph/data/geoid/egm96_15.tif",
            "cdtm_graph/data/sample_flight/imu.csv"} <= expected
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
    subprocess.run([sys.executable, "-m", "pip", "--python", str(box.python), "install", "-q",
                    "--no-deps", "--no-index", str(wheel)],
                   check=True, capture_output=True, text=True)
    _compile_the_demos_kernels_if_cold(work / "warm-up")
    _reuse_compiled_kernels(site)
    return box


def _compile_the_demos_kernels_if_cold(out: Path) -> None:
    """On a cold numba cache (a fresh clone: CI), run ``cdtm demo`` in this process first,
    so that :func:`_reuse_compiled_kernels` has the kernels to hand over.

    Why: this worker smooths other flights too and compiles the same kernels for them
    anyway, where the wheel's compiled copies serve nothing else: the wheel's demo took
    37.2 s on a cold cache, 5.4 s warm (2026-11-28); on a cold cache with this, 4.4 s (the
    fixture paying the compilation). With a warm cache (the factor's kernel cached beside
    its source) or ``NUMBA_CACHE_DIR`` (nothing to hand over) it does nothing.
    """
    cached = ROOT / "factors" / "__pycache__"
    if os.environ.get("NUMBA_CACHE_DIR") or any(cached.glob("kernel.cdtm_linearize-*.nbi")):
        return
    from cdtm_graph.cli import main

    assert main(["demo", "--out", str(out)]) == 0


def _reuse_compiled_kernels(site: Path) -> None:
    """Copy the checkout's compiled numba kernels beside the wheel's sources, each source's
    modification time set to the checkout's: numba keys a cached kernel on its source's
    time and size (and the code's hash, the numba version, the CPU), so the wheel's copy
    of a module the suite has compiled loads them instead of compiling again.

    Why: what this file tests is the package, not the compiler; a second compilation of
    every kernel was 60-90 s of the suite. Kernels the checkout has not compiled yet (a
    cold cache) are compiled by the wheel's own run, as a user's first run would.
    """
    for package in ("cdtm_graph", "factors"):
        for cache in (ROOT / package).rglob("__pycache__"):
            indices = sorted(cache.glob("*.nbi"))
            source_dir = cache.parent
            installed = site / source_dir.relative_to(ROOT) / "__pycache__"
            for module in {i.name.split(".", 1)[0] for i in indices}:
                source = source_dir / f"{module}.py"
                target = installed.parent / source.name
                if not (source.is_file() and target.is_file()
                        and source.stat().st_size == target.stat().st_size):
                    continue
                installed.mkdir(exist_ok=True)
                for path in cache.glob(f"{module}.*.nb[ic]"):
                    shutil.copy2(path, installed / path.name)
                stat = source.stat()
                os.utime(target, ns=(stat.st_atime_ns, stat.st_mtime_ns))


@pytest.mark.slow
def test_the_wheel_is_what_runs(installed):
    """Catches a test that would run the checkout instead of the wheel (PYTHONPATH, the
    editable finder of the checkout leaking in through the dependencies' site-packages)."""
    done = installed.run(installed.python, "-c", "import cdtm_graph; print(cdtm_graph.__file__)")
    assert done.returncode == 0, done.stderr
    where = Path(done.stdout.strip()).resolve()
    assert where.is_relative_to(installed.venv.resolve()), where
    assert not where.is_relative_to(ROOT), where


@pytest.mark.slow
def test_demo_runs_from_the_wheel(installed):
    """Catches the sample flight not shipped as package data, or read from a path relative
    to the repository (a2fce1e: ``.../data/sample_flight:1: not a directory``)."""
    done = installed.cdtm("demo")
    assert done.returncode == 0, done.stderr
    assert "verdict: trusted" in done.stdout
    assert (installed.cwd / "cdtm-demo-out" / "report.json").is_file()


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
