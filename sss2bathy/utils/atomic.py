"""Atomic file writes: write to a temporary name in the same folder, then rename."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it over ``path``.

    On an exception the temporary file is removed and ``path`` is left untouched. The file
    gets the mode a plain ``open(path, "w")`` would give it (``0o666 & ~umask``), not
    ``mkstemp``'s private ``0o600``, so colleagues sharing a server can read the results.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=suffix or "".join(path.suffixes), dir=path.parent
    )
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():
            os.chmod(tmp_path, default_file_mode())
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def current_umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux
    ``/proc/self/status``); elsewhere set and restored at once."""
    try:
        with open("/proc/self/status") as f:
            for row in f:
                if row.startswith("Umask:"):
                    return int(row.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o077)
    os.umask(mask)
    return mask


def default_file_mode() -> int:
    """``0o666 & ~umask``: the mode ``open()`` gives a new file under the current umask."""
    return 0o666 & ~current_umask()


def default_dir_mode() -> int:
    """``0o777 & ~umask``: the mode ``mkdir()`` gives a new folder (``mkdtemp`` gives 0o700)."""
    return 0o777 & ~current_umask()


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def save_figure(fig: Any, path: str | Path, dpi: int = 110, **savefig: Any) -> Path:
    """Save a matplotlib figure as PNG atomically (:func:`atomic_path`) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format="png", **savefig)
    finally:
        plt.close(fig)
    return path


def stable_hash(obj: Any, length: int = 16) -> str:
    """Hex digest of a JSON-serialisable object (keys sorted), for cache keys."""
    blob = json.dumps(obj, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:length]


def file_sha256(path: str | Path, length: int = 16) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:length]


FOLDER_DIGEST = "files.sha256.json"


def write_folder_digest(folder: str | Path, name: str = FOLDER_DIGEST) -> dict[str, list]:
    """Write ``folder/name``: ``{relative path: [size, sha256]}`` of every file below
    ``folder`` (the digest itself and temporary ``.``-files excepted), atomically.

    Cache folders (surveys) carry it so :func:`folder_digest_problems` can tell a complete,
    intact folder from a truncated or altered one before anything loads it.
    """
    folder = Path(folder)
    digest = {
        str(p.relative_to(folder)): [p.stat().st_size, file_sha256(p, length=64)]
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != name and not p.name.startswith(".")
    }
    atomic_write_text(folder / name, json.dumps(digest, indent=1, sort_keys=True))
    return digest


def folder_digest_problems(folder: str | Path, name: str = FOLDER_DIGEST) -> list[str] | None:
    """What differs from the folder's digest: ``None`` without a (readable) digest, ``[]``
    when every listed file is there with its size and SHA-256, else one line per problem
    (missing file, size, content hash)."""
    folder = Path(folder)
    try:
        digest = json.loads((folder / name).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(digest, dict):
        return None
    problems = []
    for rel, entry in sorted(digest.items()):
        if not (isinstance(entry, list) and len(entry) == 2):
            problems.append(f"{rel}: malformed digest entry {entry!r}")
            continue
        size, sha = entry
        path = folder / rel
        if not path.is_file():
            problems.append(f"{rel}: missing")
        elif path.stat().st_size != size:
            problems.append(f"{rel}: {path.stat().st_size} bytes, expected {size}")
        elif file_sha256(path, length=64) != sha:
            problems.append(f"{rel}: content hash differs")
    return problems


# ----------------------------------------------------------------------------- failures
class WriteError(OSError):
    """A file that could not be written (full disk, read-only folder): an ``OSError`` with
    the failure's ``errno``, the file as ``filename`` and, as its text, one line naming the
    file, the reason and the free space (:func:`write_error`)."""

    def __init__(self, message: str, errno_: int | None, strerror: str, filename: str) -> None:
        super().__init__(errno_, strerror, filename)
        self.message = message

    def __str__(self) -> str:
        return self.message


def format_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def free_space(path: str | Path) -> tuple[Path, int | None]:
    """The nearest existing folder of ``path`` and the bytes free to a normal user there
    (None when the OS cannot tell)."""
    folder = Path(path)
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if folder.is_file():
        folder = folder.parent
    try:
        return folder, shutil.disk_usage(folder).free
    except OSError:
        return folder, None


def write_error(path: str | Path, err: OSError, what: str = "file") -> WriteError:
    """A :class:`WriteError` for ``path`` that failed with ``err``: the reason, the free
    space of its folder, and that nothing partial was left (:func:`atomic_path` removed it;
    an existing file under the name is the previous, complete one)."""
    path = Path(path)
    folder, free = free_space(path.parent)
    reason = err.strerror or type(err).__name__
    space = f"{format_bytes(free)} free in {folder}" if free is not None else "free space unknown"
    kept = "; the previous file is unchanged" if path.is_file() else ""
    return WriteError(
        f"{what} {path}: not written ({reason}); {space}; nothing partial was left{kept}",
        err.errno,
        reason,
        str(path),
    )


# ----------------------------------------------------------------------------- run lock
LOCK_NAME = "run.lock"


class FolderLockedError(ValueError):
    """Another live process holds the folder's :func:`folder_lock` (the folder chosen is
    busy: a user error, one line)."""


def _lock_holder(text: str) -> dict[str, Any]:
    try:
        holder = json.loads(text)
    except ValueError:
        return {}
    return holder if isinstance(holder, dict) else {}


def _describe(holder: dict[str, Any]) -> str:
    if not holder:
        return "an unknown process"
    where = f"pid {holder.get('pid', '?')} on {holder.get('host', '?')}"
    return where + (f", since {holder['started']}" if holder.get("started") else "")


@contextlib.contextmanager
def folder_lock(folder: str | Path, name: str = LOCK_NAME) -> Iterator[Path]:
    """Hold ``folder/name`` for the duration: an exclusive ``flock`` on a file that
    names its holder (``{"pid", "host", "started"}``).

    A folder whose lock a live process holds raises :class:`FolderLockedError` (one line:
    who holds it). The OS releases the lock when its process ends, however it ends, so a
    lock file left by a killed process is stale: it is taken over with a WARNING naming the
    old holder. The file is removed on exit. Without ``fcntl`` (Windows) or on a file system
    without locks nothing is locked (a WARNING says so).
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield Path(folder) / name
        return
    import datetime
    import logging
    import socket

    log = logging.getLogger(__name__)
    path = Path(folder) / name
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, default_file_mode())
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _lock_holder(os.read(fd, 4096).decode(errors="replace"))
            os.close(fd)
            raise FolderLockedError(
                f"{path.parent}: another run is writing this folder ({_describe(holder)}; "
                f"lock {path}); wait for it to end or pick another folder (hydra.run.dir=)"
            ) from None
        except OSError as err:
            os.close(fd)
            fd = None
            log.warning("%s: not locked (%s): the file system has no locks", path, err.strerror)
            break
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the holder removed it while we waited: lock the new file
    if fd is None:
        yield path
        return
    try:
        previous = _lock_holder(os.read(fd, 4096).decode(errors="replace"))
        if previous:
            log.warning(
                "%s: taking over the stale lock of %s (that process has ended)",
                path,
                _describe(previous),
            )
        me = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": datetime.datetime.now().isoformat(timespec="seconds"),
        }
        os.lseek(fd, 0, os.SEEK_SET)
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps(me).encode())
        os.fsync(fd)
        yield path
    finally:
        try:
            os.unlink(path)
        except OSError:
            pass
        os.close(fd)
