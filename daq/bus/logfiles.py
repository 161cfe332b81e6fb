"""Reading one recording file into frames (python-can's readers), the errors that name the
file and line where a recording cannot be read (daq.bus.replay, daq.bus.columnar)."""
from __future__ import annotations

import logging
import math
from collections.abc import Generator, Iterator
from pathlib import Path
from typing import Any

import can

log = logging.getLogger("rsra.daq.bus.replay")


class ReplayError(ValueError):
    """A recording that cannot be replayed (missing, empty folder, unknown format)."""


class _CompleteLines:
    """The lines of a text log that end with a newline: a crash (``kill -9``, power loss)
    can leave the last line cut anywhere, and a cut candump line may even parse — as a
    shorter, wrong frame. Only the final line can be cut (the writer appends whole lines)."""

    def __init__(self, path: Path):
        self.file = open(path, encoding="utf-8", errors="replace")
        self.lineno = 0  # the line last handed to the parser (1-based)
        self.line = ""

    def __iter__(self) -> Iterator[str]:
        while line := self.file.readline(MAX_LINE_CHARS + 1):  # bounded: never a whole 2 GB
            if len(line) > MAX_LINE_CHARS and not line.endswith("\n"):
                line = self._rest_skipped(line[:MAX_LINE_CHARS])
            if line.endswith("\n"):
                self.lineno += 1
                self.line = line
                yield line
            else:
                cut_line_dropped(Path(self.file.name), line)

    def _rest_skipped(self, kept: str) -> str:
        """A line longer than any frame: its first MAX_LINE_CHARS characters stand for it (a
        frame-shaped one is then counted malformed, anything else refused naming the line),
        the rest read and dropped up to its newline — memory stays bounded."""
        while more := self.file.readline(MAX_LINE_CHARS):
            if more.endswith("\n"):
                return kept + "\n"
        return kept  # the file ended inside it: a cut line

    def close(self) -> None:
        self.file.close()


#: no candump line is longer (the longest valid one, a CAN FD frame of 64 bytes on a long
#: channel name, is about 250): a longer one is read only to this length (the rest dropped
#: unread into memory) — a frame-shaped one is then a malformed frame, anything else refused
MAX_LINE_CHARS = 4096


def cut_line_dropped(path: Path, line: str) -> None:
    """A last line without its newline (a cut write): dropped, said once."""
    log.warning("%s: last line cut (a crash while recording?): dropped: %r", path, line[:80])


def read_file(f: Path) -> Generator[can.Message, None, None]:
    """The frames of one recording file (see :func:`read_frames`)."""
    if f.suffix.lower() == ".log":
        yield from candump_frames(f, _CompleteLines(f))
        return
    n = 0
    try:
        with can.LogReader(f) as reader:
            for msg in reader:
                if not math.isfinite(msg.timestamp):
                    raise ValueError(f"frame {n + 1}: time stamp {msg.timestamp} is not a "
                                     "finite number")
                n += 1
                yield msg
    except ReplayError:
        raise
    except Exception as e:  # BLFParseError, zlib.error, struct.error, …
        where = f"after {n} frames" if n else "at its start"
        raise ReplayError(
            f"{f}: not a readable {f.suffix.lstrip('.').lower()} recording {where} "
            f"({_why(e)}); fix: give an undamaged recording (rename it if its suffix "
            "names the wrong format)") from None


def candump_frames(f: Path, lines: Any) -> Generator[can.Message, None, None]:
    """The frames of candump text ``lines`` of file ``f`` (python-can's parser); ``lines``
    iterates text lines and tells the number (``lineno``) and text (``line``) of the last
    one, for the error naming the line python-can refuses."""
    try:
        with can.CanutilsLogReader(lines) as reader:
            for msg in reader:
                if not math.isfinite(msg.timestamp):
                    raise ValueError(f"time stamp {msg.timestamp} is not a finite number")
                yield msg
    except ReplayError:
        raise
    except Exception as e:  # python-can raises assorted errors on a bad line
        raise ReplayError(
            f"{f}:{lines.lineno}: not a candump frame ({_why(e)}): "
            f"{lines.line.strip()[:60]!r}; fix: repair or delete that line (a candump "
            "line reads '(1700000000.000000) can0 181#0102')") from None


def _why(e: BaseException) -> str:
    name = type(e).__name__
    if name == "error":  # zlib.error, struct.error: say whose
        name = f"{type(e).__module__}.error"
    text = " ".join(str(e).split())
    return f"{name}: {text}" if text else name
