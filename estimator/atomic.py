"""One atomic text write for every file the project saves (posterior, zero offsets,
calibration fragments): a temporary file in the same directory, fsync, rename, then fsync of
the directory so the rename survives a power cut. A reader sees the old file or the new one,
never a torn one.

The temporary file is named ``.<name>.rsra-tmp.<pid>.<random>.tmp`` beside the target: a
writer killed mid-write (kill -9, power cut) leaves it behind, and :func:`own_temp_pid`
recognises exactly that pattern (and nothing a user would name) so the service can remove its
own leftovers on start (docs/reliability.md). A symbolic link is written through: the file it
points to is replaced and the link stays."""
from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

TEMP_TAG = "rsra-tmp"  # fixed part of every temporary name (with the writer's pid)


def temp_prefix(path: Path) -> str:
    """The start of this process's temporary names for ``path``."""
    return f".{path.name}.{TEMP_TAG}.{os.getpid()}."


def own_temp_pid(name: str, target_name: str) -> int | None:
    """The writer's pid if ``name`` is one of our temporary files for ``target_name``
    (``.<target_name>.rsra-tmp.<pid>.<random>.tmp``), else None."""
    m = re.fullmatch(rf"\.{re.escape(target_name)}\.{TEMP_TAG}\.([0-9]+)\.[a-z0-9_]+\.tmp",
                     name)
    return int(m.group(1)) if m else None


def write_text_atomic(path: str | Path, text: str) -> None:
    path = Path(os.path.realpath(path))  # through a symbolic link: the link stays the user's
    # no parent folder is created (nothing the user did not name): a missing one fails here
    fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path), suffix=".tmp", dir=path.parent)
    try:
        try:  # the mode of the file it replaces, else what open() would give (not mkstemp's 0600)
            mode = os.stat(path).st_mode & 0o7777
        except OSError:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
        os.fchmod(fd, mode)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    try:  # make the rename durable
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass
