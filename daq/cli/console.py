"""One way to make a rich Console: on a terminal it fits the terminal; sent to a pipe or a file
it wraps nothing (rich would otherwise wrap every line at 80 columns)."""
from __future__ import annotations

from rich.console import Console

# Width given to rich when the output is not a terminal: tables and text keep their natural
# width below it (nothing printed here comes near it).
NOT_A_TERMINAL_WIDTH = 1000


def make_console(stderr: bool = False, **kwargs) -> Console:
    """A Console on stdout (stderr=True: stderr) that does not wrap when not on a terminal."""
    console = Console(stderr=stderr, soft_wrap=True, **kwargs)
    if not console.is_terminal:
        console.width = NOT_A_TERMINAL_WIDTH
    return console
