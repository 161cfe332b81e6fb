"""Files the runtime saves and reads (the shell's side of persistence; estimator/ holds the
pure (de)serialisation).

One atomic text write for every file the project saves (posterior, zero offsets,
calibration fragments): a temporary file in the same directory, fsync, rename, then fsync of
the directory so the rename survives a power cut. A reader sees the old file or the new one,
never a torn one.

The temporary file is named ``.<name>.rsra-tmp.<pid>.<random>.tmp`` beside the target: a
writer killed mid-write (kill -9, power cut) leaves it behind, and :func:`own_temp_pid`
recognises exactly that pattern (and nothing a user would name) so the service can remove its
own leftovers on start (docs/reliability.md). A symbolic link is written through: the file it
points to is replaced and the link stays.

The posterior: :func:`save_posterior` / :func:`load_posterior` (``identification.state_file``,
``--angles``), the text made by :func:`posterior_to_json` and checked by
``posterior_from_json``."""
from __future__ import annotations

import json
import os
import re
import stat
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import IO, TYPE_CHECKING

from rsra.daq.jsonout import sanitise

if TYPE_CHECKING:  # (imported when used: the tare and calibrate commands need no scipy)
    from rsra.estimator.posterior import PosteriorState

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
    _write_atomic(path, text.encode("utf-8"))


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """The same atomic write for a binary file (the simulator's truth .npz)."""
    _write_atomic(path, data)


def _write_atomic(path: str | Path, data: bytes) -> None:
    # no parent folder is created (nothing the user did not name): a missing one fails here
    out = AtomicOutput(path, "wb")
    try:
        out.open().write(data)
        out.commit()
    finally:
        out.discard()


class AtomicOutput:
    """A file written under a temporary name beside ``path`` and renamed into place by
    :meth:`commit`; :meth:`discard` removes it and leaves the old file (if any) whole. Opened
    on the first :meth:`open` (an output refused before anything is written leaves nothing).
    A symbolic link is written through: the file it points to is replaced, the link stays. A
    target that is not a regular file (``/dev/stdout``, a named pipe) is written in place."""

    def __init__(self, path: str | os.PathLike[str], mode: str = "w"):
        self.path = Path(path)
        self.target = Path(os.path.realpath(self.path))
        self.mode = mode
        self.tmp: Path | None = None
        self.file: IO | None = None

    def open(self) -> IO:
        if self.file is None and self._special():  # a device or a pipe: written in place
            self.file = (open(self.target, self.mode, encoding="utf-8") if "b" not in self.mode
                         else open(self.target, self.mode))
        if self.file is None:
            fd, tmp = tempfile.mkstemp(prefix=temp_prefix(self.target), suffix=".tmp",
                                       dir=self.target.parent)
            self.tmp = Path(tmp)
            try:
                mode = os.stat(self.target).st_mode & 0o7777
            except OSError:
                umask = os.umask(0)
                os.umask(umask)
                mode = 0o666 & ~umask
            os.fchmod(fd, mode)
            self.file = (os.fdopen(fd, self.mode, encoding="utf-8") if "b" not in self.mode
                         else os.fdopen(fd, self.mode))
        return self.file

    def commit(self) -> None:
        if self.file is None:
            self.open()
        assert self.file is not None
        self.file.flush()
        if self.tmp is None:  # written in place (a device or a pipe)
            self.file.close()
            self.file = None
            return
        os.fsync(self.file.fileno())
        self.file.close()
        os.replace(self.tmp, self.target)
        self.file = self.tmp = None
        try:  # make the rename durable
            dfd = os.open(self.target.parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError:
            pass

    def _special(self) -> bool:
        try:
            return not stat.S_ISREG(os.stat(self.target).st_mode)
        except OSError:
            return False

    def discard(self) -> None:
        if self.file is not None:
            try:
                self.file.close()
            except OSError:
                pass
        if self.tmp is not None:
            self.tmp.unlink(missing_ok=True)
        self.file = self.tmp = None


def save_figure(fig, path: str | Path, **kwargs) -> None:
    """A matplotlib figure written atomically (:class:`AtomicOutput`), in the format of the
    target's suffix."""
    out = AtomicOutput(path, "wb")
    try:
        fig.savefig(out.open(), format=Path(path).suffix.lstrip(".") or "png", **kwargs)
        out.commit()
    finally:
        out.discard()


def save_posterior(path: str | Path, state: PosteriorState) -> None:
    """Write atomically (:func:`write_text_atomic`: temporary file, fsync, rename)."""

    write_text_atomic(path, posterior_to_json(state))


def posterior_to_json(state) -> str:
    """The saved posterior's text: strict JSON (the one converter, jsonout.sanitise)."""
    return json.dumps(sanitise(state.to_dict()), allow_nan=False, indent=1)


def load_posterior(path: str | Path, names: Sequence[str] | None = None) -> PosteriorState:
    """Read and check a saved posterior; a missing, corrupt or mismatched file raises
    :class:`estimator.posterior.PosteriorFileError`."""
    from rsra.estimator.posterior import PosteriorFileError, posterior_from_json

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise PosteriorFileError(path, "no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise PosteriorFileError(path, f"not readable JSON ({exc})") from None
    return posterior_from_json(text, path, names)
