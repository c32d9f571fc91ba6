"""Atomic file output: write to a temporary file beside the target, then rename over it.

Below every stage (no jaxflare imports): :mod:`jaxflare.io` re-exports it, and the colour tables'
disk cache, below :mod:`jaxflare.io` in the layer contract, writes its entries with it."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator


def _target_mode(path: str) -> int:
    """Permissions for the result: the existing file's, else ordinary ones (0666 less the umask);
    ``mkstemp`` alone would leave 0600."""
    try:
        return os.stat(path).st_mode & 0o7777
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


@contextlib.contextmanager
def atomic_output_path(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path in the target's directory; on success it replaces ``path``.

    On an exception the temporary file is removed and ``path`` is left untouched, so a reader
    never sees a half-written file. The temporary name keeps the target's extension, so writers
    that pick a format from the extension (matplotlib, OpenEXR) still work. The data is flushed to
    disk before the rename.
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    suffix = os.path.splitext(path)[1]
    handle, temporary = tempfile.mkstemp(prefix=".tmp-", suffix=suffix, dir=directory)
    os.close(handle)
    try:
        yield temporary
        with open(temporary, "rb") as written:
            os.fsync(written.fileno())
        os.chmod(temporary, _target_mode(path))
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(temporary)
        raise


@contextlib.contextmanager
def atomic_output_group(paths: list[str | os.PathLike], *, stale: tuple[str | os.PathLike, ...] = ()) -> Iterator[list[str]]:
    """Temporary paths for files that belong together (an EXR and its PNG preview, a fit's JSON
    and its renders), committed so that a reader never sees files of two runs side by side.

    ``paths[0]`` is the primary file, the others its companions; ``stale`` are companions of an
    earlier run that this run does not write. Yields one temporary path per target (in the
    target's folder, with its extension). On success: the stale files and the old companions are
    removed, then the primary is renamed over its target, then each companion. A reader sees the
    old files, the old primary alone, the new primary alone, or the new files, never a mix. On an
    exception (a failure, Ctrl-C, a termination signal turned into an exception) every temporary
    file is removed and the targets are untouched.
    """
    targets = [os.fspath(p) for p in paths]
    if not targets:
        raise ValueError("atomic_output_group needs at least one path")
    with contextlib.ExitStack() as stack:
        temporaries = [stack.enter_context(_deferred_output_path(path)) for path in targets]
        yield [temporary for temporary, _ in temporaries]
        for temporary, _ in temporaries:
            with open(temporary, "rb") as written:
                os.fsync(written.fileno())
        for old in [os.fspath(p) for p in stale] + targets[1:]:
            with contextlib.suppress(FileNotFoundError):
                os.remove(old)
        for (temporary, mode), target in zip(temporaries, targets):
            os.chmod(temporary, mode)
            os.replace(temporary, target)


@contextlib.contextmanager
def _deferred_output_path(path: str) -> Iterator[tuple[str, int]]:
    """A temporary file beside ``path`` (and the permissions the result should get), removed on
    any exception and left in place otherwise, for :func:`atomic_output_group` to rename."""
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.splitext(path)[1], dir=directory)
    os.close(handle)
    try:
        yield temporary, _target_mode(path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            if os.path.exists(temporary):
                os.remove(temporary)


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_output_path(path) as temporary:
        with open(temporary, "wb") as handle:
            handle.write(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))
