"""Output directories (cdtm_graph.atomic): complete or absent, never at the cost of a user's file.

Each rule is tested with the fault it guards against: the input as output, a user's
folder, a file, a name clash, a failure mid-write, a signal mid-publish, a killed run's
staging directory and a live run's.
"""

from __future__ import annotations

import errno
import json
import os
import signal
from pathlib import Path

import pytest

from cdtm_graph import atomic
from cdtm_graph.atomic import (
    MANIFEST_NAME,
    STAGING_LOCK_NAME,
    STAGING_TAG,
    atomic_output_dir,
    read_manifest,
    remove_stale_staging,
)
from cdtm_graph.errors import OutputError


def _write(directory: Path, **files: str) -> None:
    for name, text in files.items():
        (directory / name).write_text(text)


def _snapshot(directory: Path) -> dict[str, bytes]:
    return {str(p.relative_to(directory)): p.read_bytes()
            for p in sorted(directory.rglob("*")) if p.is_file()}


def _staging_dirs(*directories: Path) -> list[Path]:
    return [p for d in directories if d.is_dir() for p in d.iterdir()
            if STAGING_TAG in p.name]


def test_new_directory_appears_complete_with_its_manifest(tmp_path: Path):
    out = tmp_path / "a" / "b" / "run"
    with atomic_output_dir(out, writer="smooth") as staging:
        _write(staging, **{"x.txt": "1", "y.txt": "2"})
        assert not out.exists()  # nothing visible before the end
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST_NAME, "x.txt", "y.txt"]
    assert read_manifest(out) == {"x.txt": "smooth", "y.txt": "smooth"}
    assert json.loads((out / MANIFEST_NAME).read_text())["complete"] is True
    assert _staging_dirs(tmp_path / "a" / "b") == []


def test_failure_leaves_nothing_not_even_the_parents_it_made(tmp_path: Path):
    with pytest.raises(RuntimeError), atomic_output_dir(tmp_path / "p" / "q" / "run",
                                                        writer="smooth") as staging:
        _write(staging, **{"x.txt": "half"})
        raise RuntimeError("disk full")
    assert list(tmp_path.iterdir()) == []


def test_rerun_replaces_its_files_removes_its_stale_ones_and_keeps_the_rest(tmp_path: Path):
    out = tmp_path / "run"
    with atomic_output_dir(out, writer="smooth") as staging:
        _write(staging, **{"report.json": "old", "plot.png": "old plot"})
    _write(out, **{"notes.md": "my notes"})
    with atomic_output_dir(out, writer="study fov") as staging:  # another writer's file
        _write(staging, **{"study_fov.csv": "fov"})
    with atomic_output_dir(out, writer="smooth") as staging:
        _write(staging, **{"report.json": "new"})
    assert _snapshot(out) == {MANIFEST_NAME: (out / MANIFEST_NAME).read_bytes(),
                              "notes.md": b"my notes", "report.json": b"new",
                              "study_fov.csv": b"fov"}
    assert read_manifest(out) == {"report.json": "smooth", "study_fov.csv": "study fov"}
    assert _staging_dirs(out, tmp_path) == []


def test_failed_rerun_keeps_the_old_run_and_the_users_files(tmp_path: Path):
    out = tmp_path / "run"
    with atomic_output_dir(out, writer="smooth") as staging:
        _write(staging, **{"report.json": "old"})
    _write(out, **{"notes.md": "mine"})
    before = _snapshot(out)
    with pytest.raises(KeyboardInterrupt), atomic_output_dir(out, writer="smooth") as staging:
        _write(staging, **{"report.json": "new"})
        raise KeyboardInterrupt
    assert _snapshot(out) == before
    assert _staging_dirs(out, tmp_path) == []


@pytest.mark.parametrize("relation", ["is", "inside", "around"])
def test_the_input_is_never_an_output(tmp_path: Path, relation: str):
    log = tmp_path / "flight"
    log.mkdir()
    _write(log, **{"imu.csv": "data"})
    target = {"is": log, "inside": log / "run", "around": tmp_path}[relation]
    before = _snapshot(tmp_path)
    with pytest.raises(OutputError, match="the input"), \
            atomic_output_dir(target, writer="smooth", protected=[log], force=True):
        pytest.fail("the body must not run")
    assert _snapshot(tmp_path) == before


def test_the_input_through_a_symlink_is_still_the_input(tmp_path: Path):
    log = tmp_path / "flight"
    log.mkdir()
    (tmp_path / "link").symlink_to(log)
    with pytest.raises(OutputError, match="is the input"):
        with atomic_output_dir(tmp_path / "link", writer="smooth", protected=[log]):
            pass


def test_an_existing_file_is_refused_and_kept(tmp_path: Path):
    target = tmp_path / "results"
    target.write_text("my file")
    with pytest.raises(OutputError, match="exists and is not a directory"):
        with atomic_output_dir(target, writer="smooth", force=True):
            pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]
    assert target.read_text() == "my file"


def test_a_foreign_folder_is_refused_unless_forced_and_then_written_beside(tmp_path: Path):
    out = tmp_path / "mine"
    out.mkdir()
    _write(out, **{"notes.txt": "keep", "data.csv": "keep too"})
    with pytest.raises(OutputError, match=r"holds 'data.csv' and 1 more, not written by cdtm"):
        with atomic_output_dir(out, writer="smooth"):
            pass
    with atomic_output_dir(out, writer="smooth", force=True) as staging:
        _write(staging, **{"report.json": "r"})
    assert (out / "notes.txt").read_text() == "keep"
    assert (out / "data.csv").read_text() == "keep too"
    assert read_manifest(out) == {"report.json": "smooth"}
    # From now on it is a cdtm directory: no --force needed, the user's files stay.
    with atomic_output_dir(out, writer="smooth") as staging:
        _write(staging, **{"report.json": "r2"})
    assert (out / "notes.txt").read_text() == "keep"


def test_a_name_clash_with_a_users_file_is_refused_before_and_after_the_work(tmp_path: Path):
    out = tmp_path / "mine"
    out.mkdir()
    _write(out, **{"report.json": "the user's"})
    with pytest.raises(OutputError, match="'report.json' exists and was not written by cdtm"):
        with atomic_output_dir(out, writer="smooth", force=True, names=["report.json"]):
            pytest.fail("refused on entry when the names are known")
    # Names not announced: refused when publishing, and nothing moved.
    with pytest.raises(OutputError, match="'report.json'"):
        with atomic_output_dir(out, writer="smooth", force=True) as staging:
            _write(staging, **{"report.json": "ours", "states.csv": "ours"})
    assert _snapshot(out) == {"report.json": b"the user's"}


def test_a_file_of_ours_the_user_replaced_by_a_folder_is_left_alone(tmp_path: Path):
    out = tmp_path / "run"
    with atomic_output_dir(out, writer="smooth") as staging:
        _write(staging, **{"a.png": "plot", "r.json": "r"})
    (out / "a.png").unlink()
    (out / "a.png").mkdir()
    _write(out / "a.png", **{"inside.txt": "user"})
    with atomic_output_dir(out, writer="smooth") as staging:
        _write(staging, **{"r.json": "r2"})  # a.png is stale, but no longer our file
    assert (out / "a.png" / "inside.txt").read_text() == "user"
    assert read_manifest(out) == {"r.json": "smooth"}


def test_path_through_a_file_and_unwritable_places_fail_on_entry(tmp_path: Path, monkeypatch):
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputError, match="is not a directory"):
        with atomic_output_dir(tmp_path / "f" / "sub" / "run", writer="smooth"):
            pass

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(atomic.tempfile, "mkdtemp", read_only)
    with pytest.raises(OutputError, match="Read-only file system"):
        with atomic_output_dir(tmp_path / "ro" / "run", writer="smooth"):
            pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]  # made parents removed


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_a_directory_without_write_permission_fails_on_entry(tmp_path: Path):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    with pytest.raises(OutputError, match="Permission denied"):
        with atomic_output_dir(locked / "run", writer="smooth"):
            pass


def test_a_foreign_manifest_is_refused(tmp_path: Path):
    out = tmp_path / "d"
    out.mkdir()
    (out / MANIFEST_NAME).write_text("not json")
    with pytest.raises(OutputError, match="not a cdtm manifest"):
        with atomic_output_dir(out, writer="smooth", force=True):
            pass
    assert (out / MANIFEST_NAME).read_text() == "not json"


@pytest.mark.parametrize("name", ["../escape.txt", "sub/../../escape.txt", "/abs/x", "a//b",
                                  MANIFEST_NAME])
def test_a_manifest_cannot_make_cdtm_delete_outside_its_files(tmp_path: Path, name: str):
    out = tmp_path / "d"
    out.mkdir()
    (tmp_path / "escape.txt").write_text("victim")
    (out / MANIFEST_NAME).write_text(json.dumps(
        {"format": "cdtm-output/1", "files": {name: "smooth"}}))
    with pytest.raises(OutputError, match="not a cdtm manifest"):
        with atomic_output_dir(out, writer="smooth"):
            pass
    assert (tmp_path / "escape.txt").read_text() == "victim"


def test_signals_wait_until_the_files_are_published(tmp_path: Path, monkeypatch):
    """SIGINT arriving between two renames is held until every file is in place, then
    delivered to the handler that was there: here Python's own, as in a command (a worker
    of pytest-xdist ignores SIGINT, and a held signal then stays ignored, rightly)."""
    out = tmp_path / "run"
    with atomic_output_dir(out, writer="smooth") as staging:
        _write(staging, **{"a.txt": "old a", "b.txt": "old b"})
    real_replace = os.replace
    calls = []

    def replace_then_signal(src, dst):
        real_replace(src, dst)
        calls.append(Path(dst).name)
        if Path(dst).name == "a.txt":
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(atomic.os, "replace", replace_then_signal)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            with atomic_output_dir(out, writer="smooth") as staging:
                _write(staging, **{"a.txt": "new a", "b.txt": "new b"})
    finally:
        signal.signal(signal.SIGINT, previous)
    assert "b.txt" in calls  # the publication went on after the signal
    assert (out / "a.txt").read_text() == "new a" and (out / "b.txt").read_text() == "new b"
    assert json.loads((out / MANIFEST_NAME).read_text())["complete"] is True
    assert _staging_dirs(out, tmp_path) == []


def _fake_staging(parent: Path, prefix: str) -> tuple[Path, int]:
    """A staging directory as a run makes it, its lock held through the returned fd."""
    staging = atomic._Staging.create(parent, prefix, "smooth", parent / "run")
    (staging.path / "half.npz").write_bytes(b"partial")
    assert staging.lock_fd is not None
    return staging.path, staging.lock_fd


def test_a_killed_runs_staging_is_removed_and_a_live_runs_is_not(tmp_path: Path):
    out = tmp_path / "run"
    out.mkdir()
    dead, dead_fd = _fake_staging(out, STAGING_TAG)
    os.close(dead_fd)  # the process died: its flock is gone
    live, live_fd = _fake_staging(out, STAGING_TAG)
    beside_dead, fd = _fake_staging(tmp_path, f".run{STAGING_TAG}")
    os.close(fd)
    try:
        with atomic_output_dir(out, writer="smooth") as staging:
            _write(staging, **{"r.json": "r"})
        assert not dead.exists() and not beside_dead.exists()
        assert (live / "half.npz").read_bytes() == b"partial"
        assert (live / STAGING_LOCK_NAME).exists()
    finally:
        os.close(live_fd)
    assert remove_stale_staging(out, STAGING_TAG) == [live]


def test_only_directories_with_our_marker_are_removed(tmp_path: Path):
    look_alike = tmp_path / f"{STAGING_TAG}mine"
    look_alike.mkdir()
    (look_alike / STAGING_LOCK_NAME).write_text('{"format": "something else"}')
    (look_alike / "data").write_text("user data")
    empty_recent = tmp_path / f"{STAGING_TAG}empty"
    empty_recent.mkdir()
    assert remove_stale_staging(tmp_path, STAGING_TAG) == []
    assert (look_alike / "data").read_text() == "user data" and empty_recent.is_dir()
    old = atomic.time.time() - 2 * atomic.ORPHAN_MIN_AGE_S
    os.utime(empty_recent, (old, old))
    assert remove_stale_staging(tmp_path, STAGING_TAG) == [empty_recent]


def test_a_folder_made_at_the_target_during_the_work_is_respected(tmp_path: Path):
    out = tmp_path / "run"
    with pytest.raises(OutputError, match="holds 'theirs.txt'"):
        with atomic_output_dir(out, writer="smooth") as staging:
            _write(staging, **{"r.json": "r"})
            out.mkdir()  # someone else, meanwhile
            _write(out, **{"theirs.txt": "theirs"})
    assert _snapshot(out) == {"theirs.txt": b"theirs"}
    assert _staging_dirs(tmp_path) == []
    with atomic_output_dir(out, writer="smooth", force=True) as staging:
        _write(staging, **{"r.json": "r"})
        _write(out, **{"more.txt": "theirs too"})
    assert read_manifest(out) == {"r.json": "smooth"}
    assert (out / "more.txt").read_text() == "theirs too"


def test_an_output_of_an_older_cdtm_is_recognised_in_the_message(tmp_path: Path):
    """Run directories written before manifests existed: refused (nothing proves they are
    ours), with the way out in the message."""
    out = tmp_path / "old"
    out.mkdir()
    _write(out, **{"report.json": "r", "states.csv": "s"})
    with pytest.raises(OutputError, match="older than manifests: remove them"):
        with atomic_output_dir(out, writer="smooth", names=["report.json", "states.csv",
                                                            "trajectory.tum"]):
            pass
    assert _snapshot(out) == {"report.json": b"r", "states.csv": b"s"}


def test_files_in_subdirectories_are_published_and_their_folder_is_ours(tmp_path: Path):
    """A log's images/ (files in a folder) appear with the run; a rerun that writes fewer
    images removes the old ones it wrote, keeps the user's file in the folder, and a
    folder in the way of a file is a clash."""
    out = tmp_path / "log"
    with atomic_output_dir(out, writer="simulate") as staging:
        (staging / "images").mkdir()
        for i in range(3):
            (staging / "images" / f"{i}.png").write_text(str(i))
        (staging / "flight.yaml").write_text("x")
    assert sorted(p.name for p in (out / "images").iterdir()) == ["0.png", "1.png", "2.png"]
    assert read_manifest(out)["images/2.png"] == "simulate"
    (out / "images" / "notes.txt").write_text("mine")
    with atomic_output_dir(out, writer="simulate") as staging:  # a rerun: not foreign
        (staging / "images").mkdir()
        (staging / "images" / "0.png").write_text("new")
    assert sorted(p.name for p in (out / "images").iterdir()) == ["0.png", "notes.txt"]
    assert (out / "images" / "0.png").read_text() == "new"
    other = tmp_path / "other"
    other.mkdir()
    (other / MANIFEST_NAME).write_text(json.dumps({"format": "cdtm-output/1", "files": {}}))
    (other / "images").write_text("a file where the folder goes")
    with pytest.raises(OutputError, match="images"):
        with atomic_output_dir(other, writer="simulate") as staging:
            (staging / "images").mkdir()
            (staging / "images" / "0.png").write_text("0")
    assert (other / "images").read_text() == "a file where the folder goes"


def test_a_rerun_tells_which_earlier_files_it_removed(tmp_path: Path):
    """on_removed hears the same writer's files a rerun no longer wrote, and only those.

    Catches: stale files removed without a word (issue 23: `--plots` left out), or a
    user's file or another writer's named as removed."""
    out = tmp_path / "run"
    with atomic_output_dir(out, writer="smooth") as staging:
        _write(staging, **{"a.txt": "1", "plot.png": "2"})
    with atomic_output_dir(out, writer="evaluate") as staging:
        _write(staging, **{"table.csv": "3"})
    (out / "notes.md").write_text("mine")
    heard: list[list[str]] = []
    with atomic_output_dir(out, writer="smooth", on_removed=heard.append) as staging:
        _write(staging, **{"a.txt": "1"})
    assert heard == [["plot.png"]]
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST_NAME, "a.txt", "notes.md",
                                                      "table.csv"]
    with atomic_output_dir(out, writer="smooth", on_removed=heard.append) as staging:
        _write(staging, **{"a.txt": "1"})
    assert heard == [["plot.png"]]  # nothing removed: not called


def test_check_output_dir_applies_the_rules_and_writes_nothing(tmp_path: Path):
    """check_output_dir refuses what atomic_output_dir refuses, and creates nothing.

    Catches: a multi-directory command (smooth-many) working for minutes before a
    refused --out, or a check that leaves directories behind."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.md").write_text("mine")
    with pytest.raises(OutputError, match="not written by cdtm"):
        atomic.check_output_dir(mine)
    assert atomic.check_output_dir(mine, force=True) is True
    with pytest.raises(OutputError, match="'notes.md' exists"):
        atomic.check_output_dir(mine, force=True, names=["notes.md"])
    assert atomic.check_output_dir(tmp_path / "new" / "run") is False
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]
    assert [p.name for p in mine.iterdir()] == ["notes.md"]


def test_another_commands_file_of_the_same_name_is_refused_and_kept(tmp_path: Path):
    """A rerun replaces only its own command's files: ``simulate`` into a log that
    ``import euroc`` wrote (and the user edited) is refused, on entry when the names are
    known and when publishing otherwise, and nothing is replaced. Mutation tried: the
    writer left out of the clash test (the import's flight.yaml, edits and all, was
    replaced without a word: a hostile-input hunt's find, 2026-11-28)."""
    out = tmp_path / "log"
    with atomic_output_dir(out, writer="import euroc") as staging:
        _write(staging, **{"flight.yaml": "imported", "imu.csv": "imported"})
    _write(out, **{"flight.yaml": "imported, then edited by hand"})
    before = _snapshot(out)
    with pytest.raises(OutputError, match="'flight.yaml' was written by `cdtm import euroc`"):
        atomic.check_output_dir(out, names=["flight.yaml"], writer="simulate")
    with pytest.raises(OutputError, match="'flight.yaml' was written by `cdtm import euroc`"):
        with atomic_output_dir(out, writer="simulate", names=["flight.yaml"]):
            pytest.fail("refused on entry when the names are known")
    with pytest.raises(OutputError, match="was written by `cdtm import euroc`"):
        with atomic_output_dir(out, writer="simulate") as staging:
            _write(staging, **{"flight.yaml": "simulated", "frames.csv": "simulated"})
    assert _snapshot(out) == before
    with atomic_output_dir(out, writer="import euroc") as staging:  # its own rerun: replaced
        _write(staging, **{"flight.yaml": "imported again"})
    assert (out / "flight.yaml").read_text() == "imported again"


def test_a_cdtm_output_directory_inside_is_not_a_users_file(tmp_path: Path):
    """A directory whose sub-directories are cdtm output directories (``smooth-many``'s
    runs, left by a run stopped before its evaluation) may be written again; a
    sub-directory without a manifest is still the user's. Mutation tried: the manifest
    test dropped (the rerun is refused: "holds 'base', not written by cdtm")."""
    out = tmp_path / "many"
    with atomic_output_dir(out / "base", writer="smooth") as staging:
        _write(staging, **{"report.json": "run"})
    assert atomic.check_output_dir(out, names=["evaluation.csv"]) is True
    (out / "mine").mkdir()
    with pytest.raises(OutputError, match="holds 'mine', not written by cdtm"):
        atomic.check_output_dir(out, names=["evaluation.csv"])
