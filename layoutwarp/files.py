"""Writing records: files that no reader ever sees half-written, and how a run ran."""

from __future__ import annotations

import functools
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from .checks import ArgumentError

__all__ = ["atomic_write", "check_file_destination", "file_in_the_way"]


@functools.cache
def _file_mode() -> int:
    """The mode ``open()`` gives a new file here (``0o666`` less the umask; ``mkstemp`` gives 0o600).

    Read from ``/proc/self/status`` where it is there; elsewhere the umask is set and
    restored once, on first use (never at import).
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return 0o666 & ~int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def check_file_destination(path: str | Path, argument: str = "path") -> Path:
    """``path`` as a file that can be written: not a folder, and no file where one of its folders
    would be (those folders are created by the writer).

    Raises:
        ArgumentError: naming ``argument``, the path and the file in the way, in one line.
    """
    path = Path(path)
    if path.is_dir():
        raise ArgumentError(argument, f"must be a file; {str(path)!r} is a folder")
    blocker = file_in_the_way(path.parent)
    if blocker is not None:
        raise ArgumentError(argument, f"cannot write {str(path)!r}: {str(blocker)!r} is a file, not a folder")
    return path


def file_in_the_way(folder: str | Path) -> Path | None:
    """The file that stands where ``folder`` (to be created if need be) or one of the folders
    above it would be: its nearest existing path, when that is not a folder; else ``None``."""
    for p in (Path(folder), *Path(folder).parents):
        if p.exists():
            return None if p.is_dir() else p
    return None


def atomic_write(path: str | Path, content: bytes | str | Callable[[str], object]) -> Path:
    """Write ``path`` so that no reader ever sees it half-written, even if the process dies.

    The content goes to a temporary file in the same folder (named ``.<name>.<random><suffix>``,
    so writers that pick a format from the suffix still work), which is then renamed over
    ``path``; on any error the temporary file is removed and ``path`` is left as it was.

    Args:
        path: the file to write (its folder is created).
        content: bytes or text, or a function that writes the file at the path it is given.

    Returns:
        ``path`` as a `Path`.

    Raises:
        ArgumentError: ``path`` cannot be a file ([`check_file_destination`][]).
    """
    path = check_file_destination(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            if isinstance(content, (bytes, str)):
                f.write(content.encode() if isinstance(content, str) else content)
        if callable(content):
            content(tmp)
        os.chmod(tmp, _file_mode())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
