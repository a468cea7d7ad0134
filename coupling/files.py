"""Paths and HDF5 files at the tool's entrances: one place that checks them.

* :func:`regular_file` -- an input file: exists, is a regular file (a FIFO would block a
  reader forever, a device or socket is no data file), no symlink loop on the way.
* :func:`input_directory` / :func:`output_directory_path` -- a directory given by the
  user (``--runs-dir``, ``--massflow-dir``): no symlink loop, a directory.
* :func:`refuse_output_over_inputs` -- an output path that is one of the command's inputs
  (resolved, symlinks and hard links followed) is refused before anything is written.
* :func:`open_verified_h5` -- the loader of the velocity-table files (``--tables``): it
  checks the path as above and, when the file carries the ``sha256`` integrity digest
  (:func:`h5_digest`; every file this project writes does), recomputes it before anything
  is parsed. A digest mismatch is refused with one line naming the file. The results
  files (caches, shipped reference and campaign results) are read by
  :mod:`coupling.cache`, which checks the same digest, or that of the file's head alone
  (:func:`h5_head_digest`) for a reader of nothing else.
* :func:`writable_directory` -- an output directory, created and tried before any work.
* :func:`distinct_inputs` -- the input files of a command over several runs: no file given
  twice, whether by the same path, a symlink or hard link to it, or a copy with the same
  content digest (:func:`content_digest`).
* :func:`replace_file` -- the one way a file is written or rewritten in place (results,
  tables, reports, JSON records): under the file's lock (:func:`locked`, which a
  read-modify-write holds from its read to the rename), the free space and the file-size
  limit checked against the bytes to write, a temporary beside the file renamed onto it,
  and the temporary removed on every failure (a full disk, an exception, a signal); the
  file is untouched until the rename. HDF5 files are built in memory first
  (:class:`coupling.tables.atomic_h5`) and written through it.

Every check raises one of :mod:`coupling.errors`' types (the caller chooses which, so a
table reader raises TableError and the cache CacheError) with one line naming the path and
what would have been valid.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import os
import resource
import shutil
import stat
import tempfile
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from coupling import interrupts
from coupling.errors import ConfigError, OutputError, PbmDemError, os_reason

__all__ = [
    "DIGEST_ATTR",
    "DIGEST_ATTRS",
    "content_digest",
    "distinct_inputs",
    "FORMAT_ATTR",
    "HEAD_DIGEST_ATTR",
    "h5_digest",
    "h5_head_digest",
    "read_dataset",
    "input_directory",
    "locked",
    "open_verified_h5",
    "output_directory_path",
    "refuse_output_over_inputs",
    "regular_file",
    "replace_file",
    "resolved",
    "writable_directory",
]

#: Root attribute holding the SHA-256 of the file's canonical content (:func:`h5_digest`).
DIGEST_ATTR = "sha256"
#: Root attribute holding the SHA-256 of the file's head alone (:func:`h5_head_digest`): the
#: parts a reader that skips the bulk needs. Files written before it existed lack it; their
#: readers check the whole file instead.
HEAD_DIGEST_ATTR = "head_sha256"
#: The root attributes no digest covers.
DIGEST_ATTRS = (DIGEST_ATTR, HEAD_DIGEST_ATTR)
#: Root attribute naming a file this project wrote ("pbmdem-cache", "pbmdem-table"): a file
#: that says it is ours must carry its digest.
FORMAT_ATTR = "format"
OUR_FORMATS = ("pbmdem-cache", "pbmdem-table")


def _kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISDIR, "a directory"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def resolved(path: str | os.PathLike, what: str, error: type[Exception] = PbmDemError) -> Path:
    """``path`` with every symlink followed (need not exist); a symlink loop raises
    ``error`` naming the path, in one line."""
    try:
        return Path(path).resolve()
    except RuntimeError as exc:  # Python 3.11: "Symlink loop from '...'"
        raise error(
            f"{what} {path} is a symlink loop ({exc}); give a path that leads to a real file or directory"
        ) from None
    except OSError as exc:
        raise error(f"{what} {path}: {os_reason(exc)}") from None


def regular_file(path: str | os.PathLike, what: str, error: type[Exception] = PbmDemError) -> Path:
    """``path`` if it is an existing regular file (symlinks followed). Raises ``error``
    naming the path for a missing file, a directory, a FIFO or device, a symlink loop, or
    a file that cannot be examined."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise error(f"{what} {path} is a symlink loop; give a path that leads to a real file") from None
        if exc.errno == errno.ENOENT:
            raise error(f"{what} {path} does not exist") from None
        raise error(f"{what} {path}: {os_reason(exc)}") from None
    if not stat.S_ISREG(mode):
        raise error(f"{what} {path} is {_kind(mode)}, not a regular file; give a regular file") from None
    return path


def input_directory(path: str | os.PathLike, what: str, error: type[Exception] = PbmDemError) -> Path:
    """``path`` if it is an existing directory (symlinks followed); else ``error`` naming it
    (missing, a file, a symlink loop)."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise error(f"{what} {path} is a symlink loop; give a real directory") from None
        if exc.errno == errno.ENOENT:
            raise error(f"{what} {path} does not exist; give an existing directory") from None
        raise error(f"{what} {path}: {os_reason(exc)}") from None
    if not stat.S_ISDIR(mode):
        raise error(f"{what} {path} is {_kind(mode) if not stat.S_ISREG(mode) else 'a file'}, not a directory")
    return path


def output_directory_path(path: str | os.PathLike, what: str, error: type[Exception] = OutputError) -> Path:
    """``path`` for a directory that will be created if missing (``--runs-dir``,
    ``--out``): refused when it, or any parent on the way, is a symlink loop or exists as
    something other than a directory, or empty (the current directory, which a command's
    files would litter). Nothing is created here."""
    if not str(path).strip():
        raise error(f"{what} is empty: give a directory")
    path = Path(path)
    resolved(path, what, error)  # loops anywhere on the way
    probe = path
    while True:
        try:
            mode = os.stat(probe).st_mode
        except OSError as exc:
            if exc.errno in (errno.ENOENT, errno.ENOTDIR):  # look further up for what is in the way
                if probe.parent == probe:
                    break
                probe = probe.parent
                continue
            if exc.errno == errno.ELOOP:
                raise error(f"{what} {path}: {probe} is a symlink loop; give a real directory") from None
            raise error(f"{what} {path}: {os_reason(exc)}") from None
        if not stat.S_ISDIR(mode):
            raise error(
                f"{what} {path}: {probe} is {_kind(mode) if not stat.S_ISREG(mode) else 'a file'}, not a directory"
            )
        break
    return path


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def content_digest(path: str | os.PathLike) -> str:
    """What a file holds, as a SHA-256 (hex): the ``sha256`` digest an HDF5 file of this
    project stores (:func:`h5_digest`, over its content as h5py reads it: a copy, even one
    HDF5 laid out differently, has the same), else the SHA-256 of its bytes."""
    import h5py

    path = Path(path)
    if h5py.is_hdf5(path):
        try:
            with h5py.File(path, "r") as h5:
                digest = stored_digest(h5)
        except OSError:  # damaged: its bytes tell copies apart; its reader names the damage
            digest = None
        if digest is not None:
            return digest
    sha = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            sha.update(block)
    return sha.hexdigest()


def distinct_inputs(paths: Iterable[str | os.PathLike], what: str, error: type[Exception] = ConfigError) -> list[Path]:
    """``paths`` (each an existing regular file, :func:`regular_file`) when no two of them
    are one run: the same file by path, symlink or hard link, or a copy with the same
    :func:`content_digest`. A run given twice would be counted twice, and a statistic
    pooled over the runs would claim an interval narrower than the data give; raises
    ``error`` naming both files."""
    checked = [regular_file(path, what, error) for path in paths]
    seen_files: dict[tuple[int, int], Path] = {}
    seen_digests: dict[str, Path] = {}
    for path in checked:
        info = os.stat(path)
        same = seen_files.get((info.st_dev, info.st_ino))
        if same is not None:
            raise error(
                f"{what} {path} is the same file as {same} (by path, symlink or hard link): each run counts once; "
                "give every run once"
            )
        digest = content_digest(path)
        if digest in seen_digests:
            raise error(
                f"{what} {path} is a copy of {seen_digests[digest]} (the same content digest): each run counts "
                "once; give every run once"
            )
        seen_files[(info.st_dev, info.st_ino)] = seen_digests[digest] = path
    return checked


def writable_directory(path: str | os.PathLike, what: str) -> Path:
    """``path`` as a directory this process can write in, created if missing. Checked
    before any expensive work, so that a bad output path fails in a second, not after the
    solver; raises ConfigError naming the path and the problem."""
    path = output_directory_path(path, what, ConfigError)  # loops and files in the way: one line
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        raise ConfigError(f"{what} {path} is not a writable directory: {exc.strerror or exc}") from None
    return path


def refuse_output_over_inputs(
    out: str | os.PathLike,
    inputs: Iterable[str | os.PathLike | None],
    what: str = "output",
    error: type[Exception] = OutputError,
) -> Path:
    """``out`` unless it names one of ``inputs`` (after following symlinks, or the same
    file through a hard link), or a directory holding one of them when ``out`` is a
    directory to be cleared. Raises ``error`` naming both, before anything is written.
    ``None`` inputs are skipped."""
    out_path = resolved(out, what, error)
    for item in inputs:
        if item is None:
            continue
        source = resolved(item, "input", error)
        if source == out_path or (out_path.exists() and source.exists() and _same_file(source, out_path)):
            raise error(
                f"{what} {out} is one of this command's inputs ({item}); writing it would destroy the "
                "input: give another output path"
            )
    return out_path


# ----------------------------------------------------------------------------- writing
#: How long a writer waits for another process's lock on the same file before it is
#: refused [s]: far longer than a results file takes to write, about what a refit of the
#: shipped results holds its file for. ``PBMDEM_LOCK_WAIT_S`` overrides it.
LOCK_WAIT_S = 60.0
#: The locks this process holds: lock file -> [descriptor, depth].
_held: dict[Path, list[int]] = {}


def _lock_wait_s() -> float:
    text = os.environ.get("PBMDEM_LOCK_WAIT_S")
    try:
        return max(0.0, float(text)) if text else LOCK_WAIT_S
    except ValueError:
        return LOCK_WAIT_S


def _size(n: float) -> str:
    return f"{n:.0f} bytes" if n < 1e6 else f"{n / 1e6:.1f} MB"


@contextmanager
def locked(path: str | os.PathLike, what: str = "file", error: type[Exception] = OutputError) -> Iterator[Path]:
    """``path`` (symlinks followed) while this process holds its exclusive lock: an
    ``fcntl.flock`` on ``<name>.lock`` beside it, a file removed again on release. Another
    process asking for the same lock waits up to :data:`LOCK_WAIT_S`, then is refused
    (``error``, one line naming the file and the process holding it). Re-entrant within a
    process, so that a read-modify-write holds it from its read to the rename that
    :func:`replace_file` does under it. Only this project's writers take it."""
    target = resolved(path, what, error)
    lock = target.with_name(target.name + ".lock")
    held = _held.get(lock)
    if held is not None:
        held[1] += 1
        try:
            yield target
        finally:
            held[1] -= 1
        return
    fd = _acquire(lock, target, what, error)
    _held[lock] = [fd, 1]
    try:
        yield target
    finally:
        del _held[lock]
        # removed while still held: a process waiting on it then holds a removed file's lock,
        # sees that (_acquire) and takes the next one
        try:
            os.unlink(lock)
        except OSError:
            pass
        os.close(fd)


def _acquire(lock: Path, target: Path, what: str, error: type[Exception]) -> int:
    wait_s = _lock_wait_s()
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise error(f"{what} {target}: cannot create its lock file {lock}: {os_reason(exc)}") from None
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() >= deadline:
                        holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
                        raise error(
                            f"{what} {target} is being written by another process"
                            f"{f' (pid {holder})' if holder.isdigit() else ''}; waited {wait_s:g} s for it: run "
                            "this again when that has finished (PBMDEM_LOCK_WAIT_S sets the wait)"
                        ) from None
                    time.sleep(0.1)
            if _same_inode(fd, lock):
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
                return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)


def _same_inode(fd: int, path: Path) -> bool:
    try:
        on_disk = os.stat(path)
    except FileNotFoundError:
        return False
    mine = os.fstat(fd)
    return (mine.st_dev, mine.st_ino) == (on_disk.st_dev, on_disk.st_ino)


def _check_room(target: Path, size: int, what: str, error: type[Exception]) -> None:
    """Refuse, before anything is written, a file that the file system or the process's
    file-size limit cannot hold: a write that fails half-way has cost the work before it.
    The messages start as the file system's own refusals would (ENOSPC, EFBIG)."""
    try:
        free = shutil.disk_usage(target.parent).free
    except OSError:
        free = None
    if free is not None and size > free:
        raise error(
            f"{os.strerror(errno.ENOSPC)} for {what} {target}: {_size(size)} to write, {_size(free)} free; "
            "free space or write it elsewhere"
        )
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if limit != resource.RLIM_INFINITY and size > limit:
        raise error(
            f"{os.strerror(errno.EFBIG)} for {what} {target}: {_size(size)} to write, over this process's "
            f"file-size limit of {_size(limit)} (ulimit -f); raise the limit or write it elsewhere"
        )


def replace_file(
    path: str | os.PathLike, data: bytes | str, what: str = "file", error: type[Exception] = OutputError
) -> Path:
    """Write ``data`` (text is UTF-8) to ``path`` as a whole or not at all, and return the
    path written (symlinks followed: a link keeps pointing at the rewritten file). Under
    the file's lock (:func:`locked`): room checked (:func:`_check_room`), a temporary beside
    the file written, synced and renamed onto it. The temporary is removed on every failure
    (ENOSPC, EFBIG, any exception, an interrupt): until the rename the file is untouched. A
    signal that arrives meanwhile is raised once the temporary is renamed or removed
    (:func:`coupling.interrupts.deferred`). Raises ``error`` for a refusal, OSError for a
    write the file system refused."""
    data = data.encode() if isinstance(data, str) else bytes(data)
    target = resolved(path, what, error)
    target.parent.mkdir(parents=True, exist_ok=True)
    with locked(target, what, error), interrupts.deferred():
        _check_room(target, len(data), what, error)
        fd, tmp = tempfile.mkstemp(prefix=target.name + ".", suffix=".tmp", dir=target.parent)
        try:
            # mkstemp makes the file private (0600); results and reports are for sharing
            umask = os.umask(0)
            os.umask(umask)
            os.fchmod(fd, 0o666 & ~umask)
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
            os.fsync(fd)
            os.close(fd)
            fd = -1
            os.replace(tmp, target)
        except BaseException as exc:
            if fd >= 0:
                os.close(fd)
            try:
                os.unlink(tmp)
            except OSError:
                pass
            if isinstance(exc, OSError) and not exc.filename:  # os.write names no file
                raise OSError(exc.errno, exc.strerror, str(target)) from None
            raise
    return target


# ----------------------------------------------------------------------------- HDF5
def h5_digest(h5, values: dict[str, Any] | None = None) -> str:
    """SHA-256 (hex) of everything in an open HDF5 file except its digests
    (:data:`DIGEST_ATTRS`): every group, every dataset's dtype, shape and bytes, and every
    attribute's name and value, walked in sorted order, each item length-prefixed (no two
    different trees serialise to the same byte stream). ``values``, if given, receives every
    dataset's value keyed by its path ("/group/name"): a reader that checks the digest then
    takes its data from what the check read, rather than decompressing it all a second time."""
    return _Digest(h5, values).root().walk("", h5).hexdigest()


def h5_head_digest(
    h5, groups: Iterable[str], attributes_of: Iterable[str] = (), values: dict[str, Any] | None = None
) -> str:
    """SHA-256 (hex) of a file's head: the root's attributes except the digests, every group
    named in ``groups`` whole (as :func:`h5_digest` walks it, its name in the stream), and
    the attributes alone of each group named in ``attributes_of``. A reader that needs only
    these parts checks them without reading the rest of the file (:data:`HEAD_DIGEST_ATTR`);
    ``values`` receives what it read, as :func:`h5_digest`'s does."""
    digest = _Digest(h5, values).root()
    for name in groups:
        digest.feed(b"G", f"/{name}".encode())
        digest.walk(f"/{name}", h5[name])
    for name in attributes_of:
        digest.feed(b"H", f"/{name}".encode())
        digest.attrs(f"/{name}", h5[name])
    return digest.hexdigest()


class _Digest:
    """The canonical byte stream of :func:`h5_digest`, fed to SHA-256."""

    def __init__(self, h5, values: dict[str, Any] | None) -> None:
        self.h5, self.values, self.sha = h5, values, hashlib.sha256()

    def hexdigest(self) -> str:
        return self.sha.hexdigest()

    def feed(self, tag: bytes, payload: bytes) -> None:
        self.sha.update(tag + len(payload).to_bytes(8, "little"))
        self.sha.update(payload)

    def root(self) -> _Digest:
        self.attrs("", self.h5, skip=DIGEST_ATTRS)
        return self

    def attrs(self, where: str, obj, skip: tuple[str, ...] = ()) -> None:
        for name in sorted(obj.attrs.keys()):
            if name in skip:
                continue
            self.feed(b"A", f"{where}@{name}".encode())
            self.feed(b"V", _value_bytes(obj.attrs[name]))

    def walk(self, where: str, group) -> _Digest:
        """The group's members, recursively (its own attributes are the caller's)."""
        import h5py

        if where:
            self.attrs(where, group)
        for name in sorted(group.keys()):
            obj = group[name]
            child = f"{where}/{name}"
            if isinstance(obj, h5py.Group):
                self.feed(b"G", child.encode())
                self.walk(child, obj)
            elif isinstance(obj, h5py.Dataset):
                self.feed(b"D", child.encode())
                value = obj[()]
                if self.values is not None:
                    self.values[child] = value
                self.feed(b"V", _value_bytes(value))
                self.attrs(child, obj)
            else:
                raise ValueError(f"unexpected HDF5 object {child!r} of type {type(obj).__name__}")
        return self


def read_dataset(dataset, values: dict[str, Any] | None = None):
    """A dataset's value: taken from ``values`` (what a digest check read, keyed by path)
    when it is there, else read now."""
    return values[dataset.name] if values is not None and dataset.name in values else dataset[()]


def _value_bytes(value: Any) -> bytes:
    """Canonical bytes of an attribute or dataset value as h5py returns it."""
    if isinstance(value, str):
        return b"s" + value.encode("utf-8")
    if isinstance(value, bytes):
        return b"b" + value
    array = np.asarray(value)
    header = f"{array.dtype.str}{array.shape}".encode()
    if array.dtype.hasobject:
        parts = [_value_bytes(item) for item in array.ravel()]
        return b"o" + header + b"".join(len(p).to_bytes(8, "little") + p for p in parts)
    return b"n" + len(header).to_bytes(2, "little") + header + np.ascontiguousarray(array).tobytes()


def stored_digest(h5, name: str = DIGEST_ATTR) -> str | None:
    """The digest stored in root attribute ``name``, None when there is none."""
    value = h5.attrs.get(name)
    if value is None:
        return None
    if isinstance(value, bytes):
        value = value.decode("ascii", errors="replace")
    return str(value)


def verify_digest(h5, path: str | os.PathLike, error: type[Exception] = PbmDemError, required: bool = False) -> bool:
    """Check the digest of an open file: True when it carries one and it matches. A
    mismatch raises ``error`` naming the file; so does a missing digest when ``required``
    or when the file says it was written by this project (:data:`OUR_FORMATS`)."""
    digest = stored_digest(h5)
    if digest is None:
        fmt = h5.attrs.get(FORMAT_ATTR)
        fmt = fmt.decode(errors="replace") if isinstance(fmt, bytes) else fmt
        if required or fmt in OUR_FORMATS:
            raise error(
                f"{path} carries no '{DIGEST_ATTR}' integrity digest (written before digests existed, or "
                "the digest was removed); regenerate the file"
            )
        return False
    if digest != h5_digest(h5):
        raise error(
            f"{path} is corrupt or was edited: its content does not match its {DIGEST_ATTR} digest; regenerate the file"
        )
    return True


@contextmanager
def open_verified_h5(
    path: str | os.PathLike, what: str, error: type[Exception] = PbmDemError, digest_required: bool = False
) -> Iterator[Any]:
    """The one way this project opens an HDF5 file for reading: ``path`` checked
    (:func:`regular_file`), opened, and its digest verified (:func:`verify_digest`) before
    the block sees it. Any failure of h5py (a damaged or foreign file raises OSError,
    RuntimeError, KeyError, ...) becomes ``error`` naming the file."""
    path = regular_file(path, what, error)
    import h5py

    try:
        handle = h5py.File(path, "r")
    except OSError as exc:
        raise error(f"{what} {path} is not a readable HDF5 file: {' '.join(str(exc).split())}") from None
    with handle as h5:
        try:
            verify_digest(h5, path, error, required=digest_required)
        except PbmDemError:
            raise
        except Exception as exc:  # noqa: BLE001 - a damaged file surfaces as many types
            raise error(
                f"{path} is corrupt or unreadable: {type(exc).__name__}: {' '.join(str(exc).split())}"
            ) from None
        yield h5


def sign_h5(path: str | os.PathLike) -> None:
    """Write the digest of the file at ``path`` into it (root :data:`DIGEST_ATTR`): for a
    file edited on purpose (a migration tool, a test that builds a damaged-but-signed file).
    A head digest (:data:`HEAD_DIGEST_ATTR`) is removed, so that a reader of the head alone
    checks the whole file. The digest guards against accidents -- a partial copy, a stray
    edit -- not against someone who means to change the data."""
    import h5py

    with h5py.File(path, "a") as h5:
        if HEAD_DIGEST_ATTR in h5.attrs:
            del h5.attrs[HEAD_DIGEST_ATTR]
        h5.attrs[DIGEST_ATTR] = h5_digest(h5)
