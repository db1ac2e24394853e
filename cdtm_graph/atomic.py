"""Output directories written completely or not at all, never at the cost of a user's file.

Every command that writes (``smooth``, ``demo``, ``simulate``, ``navsim``, ``study``,
``accuracy-map``) writes one directory through :func:`atomic_output_dir`. The rules:

* **Ours is what the manifest lists.** Each output directory holds ``.cdtm-run.json``
  (:data:`MANIFEST_NAME`), naming every file cdtm wrote there and which writer
  (``smooth``, ``study fov``, ...) wrote it. A file it does not list is never deleted or
  overwritten, with or without ``force``; a name clash with such a file is an error.
* **Where a directory may be written.** A new path (parents are created); an empty
  directory; an earlier cdtm output directory (it has a manifest): the writer's files of
  the earlier run are replaced and those it no longer writes removed (and named to the
  caller, ``on_removed``, so the user hears of them), everything else (notes the user
  added, other writers' files) is kept; a name another writer wrote is refused, as a
  user's file is. A non-empty directory without a manifest only with ``force``, and then
  only beside the files already there (its sub-directories that are cdtm output
  directories are cdtm's). Never an existing file, nor a path in, equal to or around a
  protected input (the input flight log, a terrain file).
* **Checked before the work.** On entry the rules are checked (:func:`check_output_dir`
  checks them alone, for a command writing several directories) and a staging directory is
  created where the files will be published (inside the target if it exists, else beside
  it): an unwritable place (read-only file system, a path through a file, no
  permission) fails at once, before minutes of smoothing.
* **Complete or not at all.** The caller writes into the staging directory. On success
  the files are published: a new target is the staging directory renamed (one atomic
  rename); into an existing directory each file is renamed over its old version, with
  the manifest updated first (listing old and new files) and last. SIGINT and SIGTERM
  are deferred while the renames run, so only SIGKILL or a power cut in those few
  milliseconds can leave a mix of old and new files, all listed in the manifest. On any
  exception, the staging directory is removed and the target is as it was.
* **Killed runs.** A staging directory holds a lock file (:data:`STAGING_LOCK_NAME`)
  locked with ``flock`` for as long as its process lives. A later run into the same
  place removes staging directories whose lock it can take (their process is gone:
  SIGKILL, power cut); a live run's staging directory is never touched.

``atomic_output_file`` is the single-file form for library callers (``save_dtm_npz``):
temporary file beside the target, renamed over it.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import os
import shutil
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path

from cdtm_graph.errors import OutputError

try:
    import fcntl
except ImportError:  # pragma: no cover  (Windows: no flock; stale staging is left alone)
    fcntl = None  # type: ignore[assignment]

logger = logging.getLogger(__name__)

#: The manifest of an output directory: which files cdtm wrote there, and by which writer.
MANIFEST_NAME = ".cdtm-run.json"
MANIFEST_FORMAT = "cdtm-output/1"
#: Staging directories are named ``<target>/.cdtm-staging.<random>`` (inside an existing
#: target) or ``<parent>/.<target name>.cdtm-staging.<random>`` (beside a new one).
STAGING_TAG = ".cdtm-staging."
#: The lock file inside a staging directory: JSON naming its process, flock-ed while it lives.
STAGING_LOCK_NAME = ".cdtm-staging.lock"
STAGING_FORMAT = "cdtm-staging/1"
#: A staging directory without a lock file (its process died between creating the
#: directory and the lock file) is removed only when empty and at least this old (s).
ORPHAN_MIN_AGE_S = 60.0

_MANIFEST_ABOUT = ("Files cdtm wrote into this directory, and which command wrote each. "
                   "cdtm replaces or removes only the files listed here; anything else in "
                   "the directory is never touched.")
_EXPECTED_DIR = ("a new path, an empty directory or an earlier cdtm output directory "
                 "(holding .cdtm-run.json)")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# --------------------------------------------------------------------------- manifest


def read_manifest(directory: str | os.PathLike) -> dict[str, str] | None:
    """The files cdtm wrote into ``directory`` (name -> writer), or None without a manifest.

    Raises:
        OutputError: the manifest exists but is not one cdtm wrote (unreadable JSON, other
            format, or names that are not plain file names).
    """
    path = Path(directory) / MANIFEST_NAME
    if not os.path.lexists(path):
        return None
    try:
        if path.is_symlink() or not path.is_file():
            raise ValueError("not a regular file")
        data = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(data, dict) or data.get("format") != MANIFEST_FORMAT:
            raise ValueError(f"format is not {MANIFEST_FORMAT!r}")
        files = data.get("files")
        if not isinstance(files, dict) or not all(
                isinstance(k, str) and isinstance(v, str) for k, v in files.items()):
            raise ValueError("'files' is not a mapping of names to writers")
        for name in files:
            _check_payload_name(name)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise OutputError(f"{path}: not a cdtm manifest ({exc}); expected the "
                          f"{MANIFEST_FORMAT} manifest cdtm writes, or no such file "
                          "(remove it if it is yours)") from None
    return dict(files)


def _check_payload_name(name: str) -> None:
    """A file name, or a relative path of names (``images/000000.png``)."""
    parts = name.split("/")
    if (not name or "\\" in name or "\0" in name or parts[0] == MANIFEST_NAME
            or parts[0].startswith(STAGING_TAG)
            or any(part in ("", ".", "..") for part in parts)):
        raise ValueError(f"{name!r} is not a plain output file name")


def _manifest_text(files: Mapping[str, str], complete: bool) -> str:
    stamp = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    data = {"format": MANIFEST_FORMAT, "about": _MANIFEST_ABOUT, "updated_utc": stamp,
            "complete": complete, "files": dict(sorted(files.items()))}
    return json.dumps(data, indent=2) + "\n"


def _write_manifest(directory: Path, files: Mapping[str, str], complete: bool,
                    scratch: Path) -> None:
    """Write ``directory``'s manifest atomically (built in ``scratch``, then renamed)."""
    tmp = scratch / (MANIFEST_NAME + ".new")
    _write_synced(tmp, _manifest_text(files, complete))
    os.replace(tmp, directory / MANIFEST_NAME)


def credit_file(directory: str | os.PathLike, name: str, writer: str) -> None:
    """List ``name`` in ``directory``'s manifest as ``writer``'s, after that command put it
    there itself (``cdtm track``'s tracks.csv, renamed into a log): another command's
    rerun then refuses to replace it, as it refuses a user's file. Nothing happens
    without a manifest (a log cdtm did not write)."""
    directory = Path(directory)
    _check_payload_name(name)
    with _directory_lock(directory):
        files = read_manifest(directory)
        if files is None or files.get(name) == writer:
            return
        tmp = directory / f"{STAGING_TAG}{MANIFEST_NAME}.{os.getpid()}"
        _write_synced(tmp, _manifest_text({**files, name: writer}, complete=True))
        os.replace(tmp, directory / MANIFEST_NAME)


def _write_synced(path: Path, text: str) -> None:
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())


def fsync_path(path: Path) -> None:
    """Flush a file's or a directory's content to disk (best effort where not supported)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# --------------------------------------------------------------------------- signals


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM until the block ends, then deliver them as they would have been.

    Only in the main thread (where Python runs signal handlers); elsewhere a no-op.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []

    def hold(signum: int, frame: object) -> None:
        pending.append(signum)

    wanted = [signal.SIGINT] + ([signal.SIGTERM] if hasattr(signal, "SIGTERM") else [])
    previous = {sig: signal.signal(sig, hold) for sig in wanted}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for signum in dict.fromkeys(pending):
            signal.raise_signal(signum)  # the restored handler decides (KeyboardInterrupt...)


# --------------------------------------------------------------------------- staging


class _Staging:
    """A staging directory and the flock-ed lock file that marks it as in use."""

    def __init__(self, path: Path, lock_fd: int | None):
        self.path = path
        self.lock_fd = lock_fd

    @classmethod
    def create(cls, parent: Path, prefix: str, writer: str, target: Path) -> _Staging:
        path = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
        fd: int | None = None
        try:
            path.chmod(0o777 & ~_umask())  # mkdtemp is owner-only; outputs are data to share
            # Locked and filled under another name, then renamed: a cleaner can only ever
            # open a lock file that is already locked (the rename keeps the inode's flock).
            draft = path / (STAGING_LOCK_NAME + ".new")
            fd = os.open(draft, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
            if fcntl is not None:
                # Without flock support (some network file systems) the lock cannot be
                # taken by a cleaner either: the directory then counts as in use.
                with contextlib.suppress(OSError):
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            marker = {"format": STAGING_FORMAT, "pid": os.getpid(), "writer": writer,
                      "target": str(target), "started_utc": datetime.datetime.now(
                          datetime.UTC).isoformat(timespec="seconds")}
            os.write(fd, (json.dumps(marker) + "\n").encode())
            os.rename(draft, path / STAGING_LOCK_NAME)
        except BaseException:
            if fd is not None:
                os.close(fd)
            shutil.rmtree(path, ignore_errors=True)
            raise
        return cls(path, fd)

    def payload(self) -> list[str]:
        """The files the caller wrote (plain regular files, in subdirectories too), as
        relative paths with ``/``, sorted."""
        names = []
        for root, dirs, files in os.walk(self.path):
            here = Path(root).relative_to(self.path)
            for d in dirs:
                if (Path(root) / d).is_symlink():
                    raise ValueError(f"output {str(here / d)!r} is a symbolic link; output "
                                     "directories hold plain files only")
            for f in files:
                if root == str(self.path) and f == STAGING_LOCK_NAME:
                    continue
                name = (here / f).as_posix()
                try:
                    _check_payload_name(name)
                except ValueError as exc:
                    raise ValueError(f"output {exc}") from None
                p = self.path / name
                if p.is_symlink() or not p.is_file():
                    raise ValueError(f"output {name!r} is not a regular file; output "
                                     "directories hold plain files only")
                names.append(name)
        return sorted(names)

    def unlock(self) -> None:
        """Drop the lock file (before the directory is renamed into place) and release it."""
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path / STAGING_LOCK_NAME)
        self.close()

    def close(self) -> None:
        if self.lock_fd is not None:
            os.close(self.lock_fd)
            self.lock_fd = None

    def remove(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)
        self.close()


def remove_stale_staging(directory: Path, prefix: str) -> list[Path]:
    """Remove the staging directories of dead runs in ``directory`` whose names start with
    ``prefix``; a directory whose lock is held (a live run) is left alone.

    Returns:
        The directories removed.
    """
    removed: list[Path] = []
    if fcntl is None:
        return removed
    try:
        names = os.listdir(directory)
    except OSError:
        return removed
    for name in names:
        if not name.startswith(prefix):
            continue
        path = directory / name
        if path.is_symlink() or not path.is_dir():
            continue
        try:
            fd = os.open(path / STAGING_LOCK_NAME, os.O_RDWR)
        except FileNotFoundError:
            # Killed between creating the directory and its lock file (or a live run in
            # that microsecond): only an old, empty directory is certainly an orphan.
            with contextlib.suppress(OSError):
                if time.time() - path.stat().st_mtime >= ORPHAN_MIN_AGE_S:
                    path.rmdir()  # fails unless empty
                    removed.append(path)
            continue
        except OSError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                continue  # held: a live run
            try:
                marker = json.loads(os.read(fd, 4096).decode() or "{}")
            except (UnicodeDecodeError, ValueError):
                marker = {}
            if not isinstance(marker, dict) or marker.get("format") != STAGING_FORMAT:
                continue  # not our marker: not ours to delete
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
            logger.info("removed %s, the staging directory of a killed run (pid %s)",
                        path, marker.get("pid"))
        finally:
            os.close(fd)
    return removed


@contextlib.contextmanager
def _directory_lock(directory: Path) -> Iterator[None]:
    """Serialize publishing into one directory between cdtm processes (best effort)."""
    fd = None
    try:
        fd = os.open(directory, os.O_RDONLY)
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX)
    except OSError:
        pass
    try:
        yield
    finally:
        if fd is not None:
            os.close(fd)


# --------------------------------------------------------------------------- checks


def _inside(path: str, directory: str) -> bool:
    return path == directory or path.startswith(directory.rstrip(os.sep) + os.sep)


def _check_protected(real_target: str, protected: Iterable[str | os.PathLike],
                     shown: str) -> None:
    for item in protected:
        real = os.path.realpath(item)
        if real_target == real:
            relation = "is"
        elif _inside(real_target, real):
            relation = "is inside"
        elif _inside(real, real_target):
            relation = "contains"
        else:
            continue
        raise OutputError(f"{shown}: {relation} the input ({item}); expected an output "
                          "path apart from the input: never the input, inside it or around it")


def _foreign_entries(directory: Path, ours: Mapping[str, str]) -> list[str]:
    """Entries of ``directory`` cdtm did not write (staging directories aside; a directory
    holding files cdtm wrote counts as cdtm's, and so does a cdtm output directory of its
    own: ``smooth-many``'s runs, left by a run that stopped before its evaluation)."""
    folders = {name.split("/", 1)[0] for name in ours if "/" in name}
    return sorted(n for n in os.listdir(directory)
                  if n != MANIFEST_NAME and n not in ours and n not in folders
                  and not n.startswith(STAGING_TAG)
                  and not _is_output_dir(directory / n))


def _is_output_dir(path: Path) -> bool:
    """A directory (not a link) holding a cdtm manifest."""
    return (not path.is_symlink() and path.is_dir()
            and _is_regular_file(path / MANIFEST_NAME))


def _is_regular_file(path: Path) -> bool:
    return not path.is_symlink() and path.is_file()


def _clashes(directory: Path, names: Iterable[str], ours: Mapping[str, str],
             writer: str | None = None) -> list[str]:
    """Names that would overwrite something cdtm did not write (or that is no longer a
    file), or another command's file (``writer`` given: a rerun replaces only its own
    command's), or whose folder is in the way (a file, or a link)."""
    out = []
    for n in names:
        parents = [directory.joinpath(*n.split("/")[:i]) for i in range(1, n.count("/") + 1)]
        if any(os.path.lexists(d) and (d.is_symlink() or not d.is_dir()) for d in parents):
            out.append(n)
        elif os.path.lexists(directory / n) and (
                n not in ours or not _is_regular_file(directory / n)
                or (writer is not None and ours[n] != writer)):
            out.append(n)
    return out


def _clash_error(shown: str, clashes: list[str], ours: Mapping[str, str] | None = None,
                 writer: str | None = None) -> OutputError:
    other = (ours or {}).get(clashes[0])
    if other is not None and writer is not None and other != writer:
        return OutputError(
            f"{shown}: {clashes[0]!r} was written by `cdtm {other}`; expected a directory "
            f"`cdtm {writer}` may write in (a rerun replaces only its own command's files: "
            "choose another output directory)")
    return OutputError(f"{shown}: {clashes[0]!r} exists and was not written by cdtm; expected "
                       "no such entry (cdtm never overwrites what it did not write: move it, "
                       "or choose another output directory)")


def _os_error(shown: str, where: Path, exc: OSError) -> OutputError:
    reason = exc.strerror or str(exc)
    return OutputError(f"{shown}: cannot write in {where}: {reason}; expected a writable "
                       "directory")


def _make_parents(parent: Path, shown: str) -> list[Path]:
    """Create the missing directories down to ``parent``; the ones created, deepest last."""
    missing: list[Path] = []
    probe = parent
    while not os.path.lexists(probe):
        missing.append(probe)
        probe = probe.parent
    if not probe.is_dir():
        raise OutputError(f"{shown}: {probe} is not a directory; expected a path through "
                          "directories")
    created: list[Path] = []
    for path in reversed(missing):
        try:
            path.mkdir()
        except FileExistsError:
            if not path.is_dir():
                raise OutputError(f"{shown}: {path} is not a directory; expected a path "
                                  "through directories") from None
            continue
        except OSError as exc:
            _remove_created(created)
            raise _os_error(shown, path.parent, exc) from None
        created.append(path)
    return created


def _remove_created(created: list[Path]) -> None:
    for path in reversed(created):
        with contextlib.suppress(OSError):
            path.rmdir()  # only if still empty


# --------------------------------------------------------------------------- publishing


def _check_foreign(path: Path, ours: Mapping[str, str] | None, force: bool, shown: str,
                   names: Iterable[str] = ()) -> None:
    """Refuse a non-empty directory without a manifest unless ``force``."""
    if ours is not None or force:
        return
    foreign = _foreign_entries(path, {})
    if foreign:
        more = f" and {len(foreign) - 1} more" if len(foreign) > 1 else ""
        hint = "--force writes beside such files, never over them"
        if set(foreign) <= set(names):
            hint = ("its files look like the output of a cdtm older than manifests: "
                    "remove them to write there")
        raise OutputError(f"{shown}: holds {foreign[0]!r}{more}, not written by cdtm; "
                          f"expected {_EXPECTED_DIR} ({hint})")


def _publish_into(target: Path, staging: _Staging, writer: str, names: list[str],
                  force: bool, shown: str) -> list[str]:
    """Rename each staged file over its old version, the manifest updated first and last.

    Returns:
        The files of an earlier run of the same writer that this one no longer writes,
        removed.
    """
    with _directory_lock(target):
        manifest = read_manifest(target)
        _check_foreign(target, manifest, force, shown, names)  # again: may have changed
        ours = manifest or {}
        clashes = _clashes(target, names, ours, writer)
        if clashes:
            raise _clash_error(shown, clashes, ours, writer)
        stale = [n for n, w in ours.items()
                 if w == writer and n not in names and _is_regular_file(target / n)]
        kept = {n: w for n, w in ours.items()
                if n not in names and (w != writer) and os.path.lexists(target / n)}
        # Crash-safe order: whatever happens from here, every file cdtm wrote is listed.
        pending = {**ours, **{n: writer for n in names}}
        _write_manifest(target, pending, complete=False, scratch=staging.path)
        for name in names:
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            os.replace(staging.path / name, target / name)
        for name in stale:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(target / name)
            folder = (target / name).parent
            while folder != target:  # folders cdtm made and emptied
                with contextlib.suppress(OSError):
                    folder.rmdir()  # only if empty
                folder = folder.parent
        _write_manifest(target, {**kept, **{n: writer for n in names}}, complete=True,
                        scratch=staging.path)
        fsync_path(target)
    return stale


@contextlib.contextmanager
def atomic_output_dir(target: str | os.PathLike, *, writer: str, force: bool = False,
                      protected: Iterable[str | os.PathLike] = (),
                      names: Iterable[str] = (), label: str = "output directory",
                      on_removed: Callable[[list[str]], None] | None = None
                      ) -> Iterator[Path]:
    """Check ``target`` and yield a staging directory whose files are published there on success.

    The rules are the module docstring's. Everything is checked on entry, before the
    caller's (possibly long) work: write the output files into the yielded directory
    (plain files, in subdirectories if need be); they appear in ``target`` only when the
    block ends without an exception.

    Args:
        target: the output directory.
        writer: who writes (``"smooth"``, ``"study fov"``, ...): the files an earlier run of
            the same writer listed and this one no longer writes are removed.
        force: also write into a non-empty directory cdtm did not write (beside its
            files; never over them).
        protected: input paths the target must not be, be inside, or contain.
        names: the files the caller will write, if known: a clash with a file cdtm did
            not write is then refused on entry rather than after the work.
        label: how messages name the target (``"--out"``).
        on_removed: called after publishing with the files of an earlier run of the same
            writer that this run no longer wrote and removed (only when there were any),
            so the user hears of them.

    Raises:
        OutputError: the target breaks a rule or is not writable (on entry), or a file
            appeared meanwhile under a name the caller wrote (when publishing).
        ValueError: the caller wrote something that is not a plain file.
    """
    given = os.fspath(target)
    shown = f"{label} {given}"
    path = Path(os.path.normpath(os.path.abspath(given)))
    names = list(names)
    created: list[Path] = []
    exists = check_output_dir(target, force=force, protected=protected, names=names,
                              label=label, writer=writer)
    if exists:
        remove_stale_staging(path, STAGING_TAG)
        remove_stale_staging(path.parent, f".{path.name}{STAGING_TAG}")
        try:
            staging = _Staging.create(path, STAGING_TAG, writer, path)
        except OSError as exc:
            raise _os_error(shown, path, exc) from None
        into = True
    else:
        created = _make_parents(path.parent, shown)
        remove_stale_staging(path.parent, f".{path.name}{STAGING_TAG}")
        try:
            staging = _Staging.create(path.parent, f".{path.name}{STAGING_TAG}", writer, path)
        except OSError as exc:
            _remove_created(created)
            raise _os_error(shown, path.parent, exc) from None
        into = False

    published = False
    removed: list[str] = []
    try:
        yield staging.path
        with signals_deferred():
            payload = staging.payload()
            for name in payload:
                fsync_path(staging.path / name)
            if not into:
                published = _rename_into_place(staging, path, writer, payload)
            if not published:
                removed = _publish_into(path, staging, writer, payload, force, shown)
                published = True
                staging.remove()
    except BaseException:
        with signals_deferred():
            if not published:
                staging.remove()
                _remove_created(created)
        raise
    if removed and on_removed is not None:
        on_removed(removed)


def check_output_dir(target: str | os.PathLike, *, force: bool = False,
                     protected: Iterable[str | os.PathLike] = (), names: Iterable[str] = (),
                     label: str = "output directory", writer: str | None = None) -> bool:
    """Check the rules of :func:`atomic_output_dir` for ``target`` without writing anything.

    For a command that writes several output directories (one per run, and a summary
    beside them) and checks them all before any work. ``writer``: who will write
    ``names`` (another command's files of those names are then refused).

    Returns:
        Whether ``target`` exists (as a directory).

    Raises:
        OutputError: ``target`` breaks a rule (the same messages as on entry to
            :func:`atomic_output_dir`).
    """
    given = os.fspath(target)
    shown = f"{label} {given}"
    path = Path(os.path.normpath(os.path.abspath(given)))
    _check_protected(os.path.realpath(path), protected, shown)
    if not os.path.lexists(path):
        return False
    if not path.exists():
        raise OutputError(f"{shown}: is a broken symbolic link; expected {_EXPECTED_DIR}")
    if not path.is_dir():
        raise OutputError(f"{shown}: exists and is not a directory; expected "
                          f"{_EXPECTED_DIR}")
    names = list(names)
    ours = read_manifest(path)
    _check_foreign(path, ours, force, shown, names)
    clashes = _clashes(path, names, ours or {}, writer)
    if clashes:
        raise _clash_error(shown, clashes, ours, writer)
    return True


def _rename_into_place(staging: _Staging, path: Path, writer: str, payload: list[str]) -> bool:
    """Publish a new target as the staging directory renamed: True, or False when a
    directory appeared at ``path`` meanwhile (then publish into it file by file)."""
    _write_synced(staging.path / MANIFEST_NAME,
                  _manifest_text(dict.fromkeys(payload, writer), complete=True))
    staging.unlock()
    try:
        os.rename(staging.path, path)  # one atomic step: all files or none
    except OSError:
        if not path.is_dir():
            raise
        os.unlink(staging.path / MANIFEST_NAME)
        return False
    fsync_path(path.parent)
    return True


def temporary_beside(target: Path) -> Path:
    """A new, empty, hidden temporary file in ``target``'s directory, to be renamed over
    it; readable as any output is (mkstemp makes it owner-only).

    Raises:
        OSError: the directory cannot take it.
    """
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    tmp = Path(name)
    tmp.chmod(0o666 & ~_umask())
    return tmp


@contextlib.contextmanager
def atomic_output_file(target: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path that is renamed over ``target`` on success (library use).

    For single files a library caller names explicitly (``save_dtm_npz``); the commands
    write directories through :func:`atomic_output_dir`, which never replaces a file it
    did not write.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_beside(target)
    try:
        yield tmp
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


