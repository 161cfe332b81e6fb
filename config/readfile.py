"""Reading a file rsra is given: never blocking, never without a limit (docs/reliability.md
"Bad input").

Every configuration-sized file rsra reads — a rig TOML and the bases it ``extends``, a saved
posterior, a scenario, an EDS, a recording's ``config.json``, a Zenoh config — is opened with
``O_NONBLOCK`` (opening a FIFO then returns at once instead of waiting for a writer), checked
with ``fstat`` on the opened descriptor (a folder, a FIFO, a device or a socket is refused with
one line), and read up to :data:`TEXT_LIMIT` bytes: a larger file is refused naming the limit
(``/dev/zero`` or a 2 GB file never becomes a MemoryError). Frame logs are streamed elsewhere
with no total-size limit.

The one rule lives here; the callers turn :class:`UnreadableFile` into their own error
(ConfigError, PosteriorFileError, UsageError) with the key or option that named the file.
"""
from __future__ import annotations

import codecs
import os
import stat

TEXT_LIMIT = 16 * 1024 * 1024  # bytes: a rig TOML, posterior, scenario, EDS or JSON file
CHUNK = 1 << 16


def size_text(n: int) -> str:
    """``16 MiB`` for a limit in bytes."""
    return f"{n // (1024 * 1024)} MiB" if n % (1024 * 1024) == 0 else f"{n} bytes"


class UnreadableFile(ValueError):
    """A file that is not there, not a regular file, too large or not UTF-8 text: ``problem``
    is one phrase (``is a FIFO (a named pipe)``), ``fix`` what to do."""

    def __init__(self, path: str | os.PathLike[str], problem: str, fix: str):
        self.path, self.problem, self.fix = str(path), problem, fix
        super().__init__(f"{path}: {problem}; fix: {fix}")


def kind_of(mode: int) -> str | None:
    """None for a regular file, else what it is, as a phrase."""
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "is a folder"
    if stat.S_ISFIFO(mode):
        return "is a FIFO (a named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "is a device"
    if stat.S_ISSOCK(mode):
        return "is a socket"
    return "is not a regular file"


def open_regular(path: str | os.PathLike[str]) -> int:
    """A read-only descriptor of the regular file ``path`` (a symbolic link followed), opened
    without blocking and checked with fstat; the caller closes it. Raises UnreadableFile."""
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise UnreadableFile(path, "file not found", "give the path of an existing file") from None
    except OSError as e:
        raise UnreadableFile(path, f"cannot be opened ({e.strerror or e})",
                             "check the path and its permissions") from None
    try:
        st = os.fstat(fd)
        problem = kind_of(st.st_mode)
        if problem is not None:
            raise UnreadableFile(path, f"{problem}; rsra reads only regular files",
                                 "give the path of the file itself")
        os.set_blocking(fd, True)  # a regular file: reads never wait anyway
    except BaseException:
        os.close(fd)
        raise
    return fd


def read_bytes(path: str | os.PathLike[str], limit: int = TEXT_LIMIT) -> bytes:
    """The whole of a regular file of at most ``limit`` bytes (UnreadableFile otherwise)."""
    fd = open_regular(path)
    try:
        chunks, n = [], 0
        while n <= limit:
            block = os.read(fd, min(CHUNK, limit + 1 - n))
            if not block:
                break
            chunks.append(block)
            n += len(block)
    except OSError as e:
        raise UnreadableFile(path, f"cannot be read ({e.strerror or e})",
                             "check the file and its permissions") from None
    finally:
        os.close(fd)
    if n > limit:
        raise UnreadableFile(path, f"is larger than the {size_text(limit)} limit for this "
                             "kind of file", "give the right file (a configuration-sized one)")
    return b"".join(chunks)


def decode_text(data: bytes, path: str | os.PathLike[str]) -> str:
    """UTF-8 text, or UnreadableFile naming the line and byte of the first bad byte."""
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise _not_utf8(path, data[:e.start]) from None


def _not_utf8(path: str | os.PathLike[str], before: bytes, line0: int = 1) -> UnreadableFile:
    line = line0 + before.count(b"\n")
    col = len(before) - (before.rfind(b"\n") + 1) + 1
    return UnreadableFile(path, f"is not UTF-8 text (a bad byte on line {line}, byte {col})",
                          "give the undamaged file, or save it as UTF-8")


def read_text(path: str | os.PathLike[str], limit: int = TEXT_LIMIT) -> str:
    """:func:`read_bytes` decoded as UTF-8."""
    return decode_text(read_bytes(path, limit), path)


def check_utf8(path: str | os.PathLike[str]) -> None:
    """A text file of any size (a recording's ``angles.jsonl``) streamed through a UTF-8
    decoder: UnreadableFile at the first bad byte, naming its line."""
    fd = open_regular(path)
    dec = codecs.getincrementaldecoder("utf-8")()
    lines = 1
    try:
        with os.fdopen(fd, "rb", closefd=True) as f:
            while block := f.read(CHUNK):
                try:
                    dec.decode(block)
                except UnicodeDecodeError as e:
                    raise _not_utf8(path, block[:max(e.start, 0)], lines) from None
                lines += block.count(b"\n")
            try:
                dec.decode(b"", final=True)
            except UnicodeDecodeError:
                raise _not_utf8(path, b"", lines) from None
    except OSError as e:
        raise UnreadableFile(path, f"cannot be read ({e.strerror or e})",
                             "check the file and its permissions") from None


def regular_file_problem(path: str | os.PathLike[str],
                         limit: int | None = TEXT_LIMIT) -> str | None:
    """None for a regular file of at most ``limit`` bytes (a symbolic link followed), else the
    problem as a phrase — checked without opening it, for files another library opens by name
    (an EDS: canopen). ``limit`` None: any size (a telemetry file)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "file not found"
    except (OSError, ValueError) as e:
        return f"cannot be examined ({getattr(e, 'strerror', None) or e})"
    problem = kind_of(st.st_mode)
    if problem is not None:
        return f"{problem}; rsra reads only regular files"
    if limit is not None and st.st_size > limit:
        return f"is larger than the {size_text(limit)} limit for this kind of file"
    return None
