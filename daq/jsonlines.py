"""The one reader of JSON-lines files (a `rsra replay --out` telemetry file, a recording's
``angles.jsonl``): every non-blank line parsed on its own, bounded whatever the file holds.

A line is read at most :data:`MAX_LINE_CHARS` characters at a time: a longer one (a damaged
file, 2 GB without a newline) is never held whole — its rest is read and dropped — and is
reported as bad, as is a line that is not JSON or nests too deep for the parser. What a bad
line means is the caller's: ``on_bad(line_number, why)`` raises the caller's one-line error,
or returns to skip the line (an ``angles.jsonl`` cut off by a crash mid-write).
"""
from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from rsra.daq.payload_guard import MAX_BYTES

# The largest payload rsra publishes is bounded by the payload guard; a line adds its "key"
# and the JSON of the numbers around it: far below twice that bound.
MAX_LINE_CHARS = 2 * MAX_BYTES


def json_lines(path: str | Path, on_bad: Callable[[int, str], None],
               max_chars: int = MAX_LINE_CHARS) -> Iterator[tuple[int, Any]]:
    """(line number, parsed value) of every non-blank line of the UTF-8 file ``path`` (bytes
    that are not UTF-8 read as U+FFFD, so they make the line bad rather than the file
    unreadable); ``on_bad(n, why)`` for a line that is too long, not JSON or too deep.
    OSError (the file cannot be opened or read) goes to the caller."""
    with open(path, encoding="utf-8", errors="replace") as f:
        n = 0
        while line := f.readline(max_chars + 1):
            n += 1
            if len(line) > max_chars and not line.endswith("\n"):
                while (rest := f.readline(max_chars)) and not rest.endswith("\n"):
                    pass  # the rest of an over-long line, read and dropped
                on_bad(n, f"a line longer than {max_chars} characters")
                continue
            if not line.strip():
                continue
            try:
                value = json.loads(line)
            except ValueError as e:  # JSONDecodeError, or an integer of over 4 300 digits
                on_bad(n, f"not a JSON line ({getattr(e, 'msg', None) or e})")
                continue
            except RecursionError:
                on_bad(n, "JSON nested too deep")
                continue
            yield n, value
