"""Atomic, checksummed files (``.npz`` arrays, checkpoint bytes) and output locks. Writes go to a
per-process-and-thread temporary file, fsync'ed and renamed over the destination (:func:`os.replace`);
reads recompute the checksum (:class:`~torchfmap.errors.CorruptFileError` on a mismatch)."""

from __future__ import annotations

import contextlib
import hashlib
import os
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import IO

import numpy as np

from ..errors import CorruptFileError, ParameterError, file_read_error, file_write_error

#: Key of the checksum array in files written by :meth:`torchfmap.bases.Basis.save`.
CHECKSUM_KEY = "checksum"


def checksum(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 hex digest of named arrays: every key (sorted) with its dtype, shape and bytes."""
    h = hashlib.sha256()
    for key in sorted(arrays):
        a = np.ascontiguousarray(arrays[key])
        h.update(key.encode())
        h.update(str(a.dtype).encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


#: Bytes the temporary file of :func:`atomic_write` adds to a name (``.{name}.{pid}.{thread}.{hex}.tmp``).
TEMP_NAME_EXTRA = 48


def check_file_name(path: str | os.PathLike) -> None:
    """Raise :class:`ParameterError` for a file name longer than its file system allows, less
    :data:`TEMP_NAME_EXTRA` bytes for the temporary file."""
    path = Path(path)
    try:
        name_max = os.pathconf(path.parent if str(path.parent) else ".", "PC_NAME_MAX")
    except (AttributeError, OSError, ValueError):  # no pathconf (Windows), or no folder yet
        name_max = 255
    size = len(os.fsencode(path.name))
    if size + TEMP_NAME_EXTRA > name_max:
        raise ParameterError(
            f"the file name {path.name[:40]}... is {size} bytes long; its folder's file system allows "
            f"{name_max}, and it is written through a temporary file whose name is up to "
            f"{TEMP_NAME_EXTRA} bytes longer. Fix: a name of at most {name_max - TEMP_NAME_EXTRA} bytes."
        )


def _temp_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.{uuid.uuid4().hex[:12]}.tmp")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists (another user's) or cannot tell: keep its file
    return True


@contextlib.contextmanager
def output_lock(path: str | os.PathLike, what: str = "file"):
    """Hold ``<path>.lock`` (holding this pid) while writing ``path`` over a long run; a lock of a
    dead process is taken over. Raises :class:`ParameterError` if another live process holds it."""
    lock = Path(f"{path}.lock")
    for _ in range(3):  # a stale lock is removed and the creation tried again
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                holder = int(lock.read_text().strip() or 0)
            except (OSError, ValueError):
                holder = 0  # being written this instant: judged on the next pass
            if holder and holder != os.getpid() and _pid_alive(holder):
                raise ParameterError(
                    f"{path} is being written by another process (pid {holder}; lock {lock}). Fix: "
                    f"give this run another {what} path, or wait for that one to end (a lock left by a "
                    "killed process is taken over)."
                ) from None
            if holder:
                lock.unlink(missing_ok=True)
            else:
                time.sleep(0.05)
            continue
        with os.fdopen(fd, "w") as fh:
            fh.write(str(os.getpid()))
        break
    else:
        raise ParameterError(f"could not take the lock {lock}. Fix: remove it if no run is writing {path}.")
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)


def remove_stale_temps(path: str | os.PathLike) -> int:
    """Delete temporary files of ``path`` left by dead writers; returns how many."""
    path = Path(path)
    removed = 0
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        fields = tmp.name[len(path.name) + 2 : -len(".tmp")].split(".")
        if len(fields) >= 1 and fields[0].isdigit() and not _pid_alive(int(fields[0])):
            try:
                tmp.unlink()
                removed += 1
            except OSError:
                pass
    return removed


def atomic_write(
    path: str | os.PathLike,
    write: Callable[[IO[bytes]], None],
    verify: Callable[[Path], object] | None = None,
) -> Path:
    """Write ``path`` atomically: ``write(fh)`` fills a temporary file, fsync'ed, checked by
    ``verify(temp_path)`` and renamed over ``path``; the temporary file never outlives the call.

    Raises:
        FileWriteError (also the original OSError subclass): the write or the rename failed.
        CorruptFileError: ``verify`` refused the written file (nothing was replaced).
        ParameterError: a file name too long for its file system (:func:`check_file_name`).
    """
    path = Path(path)
    check_file_name(path)
    remove_stale_temps(path)
    tmp = _temp_path(path)
    try:
        with open(tmp, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        if verify is not None:
            verify(tmp)
        os.replace(tmp, path)
    except OSError as err:
        message = (
            f"could not write {path} ({err.strerror or err}); any previous file there is unchanged. "
            "Fix: free disk space, check write permission, or choose another folder."
        )
        raise file_write_error(err, message) from err
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def save_arrays(
    path: str | os.PathLike, arrays: dict[str, np.ndarray], checksum_key: str = CHECKSUM_KEY
) -> Path:
    """Write ``arrays`` and their :func:`checksum` (under ``checksum_key``) to ``.npz`` atomically."""
    if checksum_key in arrays:
        raise ParameterError(f"{checksum_key!r} is reserved for the checksum. Fix: rename that array.")
    digest = np.array(checksum(arrays))
    return atomic_write(
        path,
        lambda fh: np.savez(fh, **{checksum_key: digest}, **arrays),
        verify=lambda tmp: load_arrays(tmp, checksum_key),
    )


def load_arrays(
    path: str | os.PathLike, checksum_key: str = CHECKSUM_KEY, what: str = "file"
) -> dict[str, np.ndarray]:
    """The arrays of a file written by :func:`save_arrays`, checksum verified (and removed); raises
    :class:`FileReadError` (cannot be read) or :class:`CorruptFileError` (unreadable, checksum mismatch)."""
    path = Path(path)
    try:  # opened here, not by np.load: a corrupt file never leaks its handle
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except OSError as err:  # missing, a folder, no permission: not corrupt
        raise file_read_error(err, path, what) from None
    except Exception as err:  # truncated zip, bad header, a pickled array...
        raise CorruptFileError(f"{path} is not a readable {what} ({err}). Fix: rebuild it.") from err
    stored = str(arrays.pop(checksum_key, ""))
    if stored != checksum(arrays):
        raise CorruptFileError(
            f"{path} fails its checksum (altered or truncated, or written without one). Fix: rebuild it."
        )
    return arrays


#: First line of checksummed byte files (:func:`save_checked_bytes`): format tag and version.
CHECKED_MAGIC = b"TORCHFMAP-CHECKED-1\n"


def save_checked_bytes(path: str | os.PathLike, payload: bytes) -> Path:
    """Write ``payload`` atomically behind a header with its SHA-256 (checkpoints)."""
    digest = hashlib.sha256(payload).hexdigest().encode()
    return atomic_write(
        path, lambda fh: fh.write(CHECKED_MAGIC + digest + b"\n" + payload), verify=load_checked_bytes
    )


def load_checked_bytes(path: str | os.PathLike, what: str = "file") -> bytes:
    """The payload of a file written by :func:`save_checked_bytes`, its checksum verified; raises
    :class:`CorruptFileError` (no header, altered) or :class:`FileReadError` (cannot be read)."""
    try:
        data = Path(path).read_bytes()
    except OSError as err:
        raise file_read_error(err, path, what) from None
    head = len(CHECKED_MAGIC)
    if not data.startswith(CHECKED_MAGIC) or len(data) < head + 65 or data[head + 64 : head + 65] != b"\n":
        raise CorruptFileError(
            f"{str(path)!r} is not a torchfmap {what} (no checksummed header). Fix: save it again."
        )
    payload = data[head + 65 :]
    if hashlib.sha256(payload).hexdigest().encode() != data[head : head + 64]:
        raise CorruptFileError(
            f"{str(path)!r} fails its checksum (truncated or altered). Fix: save it again."
        )
    return payload
