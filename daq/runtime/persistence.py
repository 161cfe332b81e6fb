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
    with OutputFile(path, "wb") as f:
        f.write(data)


class OutputRefused(ValueError):
    """An output :class:`OutputFile` will not write: one line naming the path and the fix."""


# FIFOs found to have a reader by a check, kept open for the write: opening and closing a
# writer's end would give its reader an end of file
_held_fifos: dict[tuple[int, int], int] = {}


def output_problem(path: str | os.PathLike[str]) -> str | None:
    """Why ``path`` cannot be an output, by what it is (the one rule, docs/cli.md §16), or
    None: absent or a regular file (written under a temporary name and renamed), a character
    device (``/dev/null``: written in place), a FIFO with a reader (written in place: its
    write end opened without waiting and kept for the write). A folder, a block device, a
    socket, a FIFO nobody reads are refused: never replaced by a regular file, never waited
    on."""
    try:
        st = os.stat(path)  # through a symbolic link: what it names
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:
        return f"cannot be examined ({getattr(e, 'strerror', None) or e}); fix: write elsewhere"
    mode = st.st_mode
    if stat.S_ISREG(mode) or stat.S_ISCHR(mode):
        return None
    if stat.S_ISDIR(mode):
        return "is a folder; fix: give a file name"
    if stat.S_ISFIFO(mode):
        key = (st.st_dev, st.st_ino)
        if key not in _held_fifos:
            try:
                _held_fifos[key] = _open_fifo(path)
            except OSError:
                return ("is a FIFO (a named pipe) nobody reads, and rsra does not wait for a "
                        "reader; fix: start its reader first, or give a file name")
        return None
    return ("is a block device or a socket: rsra writes only a regular file, a character "
            "device or a pipe; fix: give a file name")


def _open_fifo(path: str | os.PathLike[str]) -> int:
    """A FIFO's write end: the one kept by a check, else opened without waiting (ENXIO at
    once without a reader); then set back to blocking writes, as any pipe."""
    try:
        st = os.stat(path)
        fd = _held_fifos.pop((st.st_dev, st.st_ino), None)
    except OSError:
        fd = None
    if fd is None:
        fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    os.set_blocking(fd, True)
    return fd


class OutputFile:
    """The one writer of every file rsra writes (docs/cli.md §16): a command's outputs, the
    posterior, zero offsets, fragments, figures, exports.

    Contract: ``OutputFile(path, mode)``; :meth:`check` (optional, before any work) raises
    :class:`OutputRefused` for a path that cannot be an output (:func:`output_problem`);
    :meth:`open` returns the file object to write (text modes are UTF-8); :meth:`commit`
    makes it the file at ``path``; :meth:`discard` (always safe, also after commit) drops
    an uncommitted one and leaves the old file whole. Also a context manager: commit on a
    clean exit, discard on an exception.

    * absent or a regular file: written under a temporary name beside the target
      (``.<name>.rsra-tmp.<pid>.<random>.tmp``), fsynced, renamed into place, the folder
      fsynced; a symbolic link is written through (the file it names is replaced, the link
      stays). Nothing is created before :meth:`open`.
    * a character device (``/dev/null``, a terminal): written in place, never replaced.
    * a FIFO, named or the pipe behind ``/dev/stdout``: written in place, opened without
      waiting — refused at once when nobody reads it, never blocking forever.
    * a folder, a block device, a socket: refused.

    That an output is not one of the command's inputs is checked by the command line
    (daq.cli.outputs), which knows the inputs."""

    def __init__(self, path: str | os.PathLike[str], mode: str = "w"):
        #: the path as given (for messages)
        self.path = Path(path)
        #: the file a symbolic link names (what is replaced)
        self.target = Path(os.path.realpath(self.path))
        #: "w"/"wb" (replaced), "a"/"ab" (appended in place: log files)
        self.mode = mode
        #: the temporary file while writing a regular one
        self.tmp: Path | None = None
        #: the open file object, once opened
        self.file: IO | None = None

    def check(self) -> None:
        problem = output_problem(self.path)  # (the kernel follows /dev/stdout to its pipe)
        if problem is not None:
            raise OutputRefused(f"{self.path}: {problem}")

    def open(self) -> IO:
        if self.file is not None:
            return self.file
        self.check()
        try:  # what the path names, as the kernel follows it (realpath cannot: /dev/stdout)
            st: os.stat_result | None = os.stat(self.path)
        except OSError:
            st = None
        if st is not None and stat.S_ISFIFO(st.st_mode):
            try:
                fd = _open_fifo(self.path)
            except OSError:
                raise OutputRefused(f"{self.path}: is a FIFO (a named pipe) nobody reads, and "
                                    "rsra does not wait for a reader; fix: start its reader "
                                    "first, or give a file name") from None
        elif (st is not None and stat.S_ISCHR(st.st_mode)) or "a" in self.mode:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | getattr(os, "O_CLOEXEC", 0)
                         | (os.O_APPEND if "a" in self.mode else 0), 0o666)
        else:
            fd, tmp = tempfile.mkstemp(prefix=temp_prefix(self.target), suffix=".tmp",
                                       dir=self.target.parent)
            self.tmp = Path(tmp)
            if st is not None:
                perm = st.st_mode & 0o7777
            else:
                umask = os.umask(0)
                os.umask(umask)
                perm = 0o666 & ~umask
            os.fchmod(fd, perm)
        fmode = self.mode.replace("a", "w")
        self.file = (os.fdopen(fd, fmode, encoding="utf-8") if "b" not in fmode
                     else os.fdopen(fd, fmode))
        return self.file

    def commit(self) -> None:
        if self.file is None:
            self.open()
        assert self.file is not None
        if not self.file.closed:
            self.file.flush()
            if self.tmp is not None:
                os.fsync(self.file.fileno())
            self.file.close()
        self.file = None
        if self.tmp is None:  # written in place (a device, a pipe, an appended log)
            return
        os.replace(self.tmp, self.target)
        self.tmp = None
        try:  # make the rename durable
            dfd = os.open(self.target.parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError:
            pass

    def discard(self) -> None:
        if self.file is not None:
            try:
                self.file.close()
            except OSError:
                pass
        if self.tmp is not None:
            self.tmp.unlink(missing_ok=True)
        self.file = self.tmp = None

    def __enter__(self) -> IO:
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        self.discard()


#: the writer's former name (other branches may still import it)
AtomicOutput = OutputFile


def save_figure(fig, path: str | Path, **kwargs) -> None:
    """A matplotlib figure written atomically (:class:`OutputFile`), in the format of the
    target's suffix."""
    with OutputFile(path, "wb") as f:
        fig.savefig(f, format=Path(path).suffix.lstrip(".") or "png", **kwargs)


def save_posterior(path: str | Path, state: PosteriorState) -> None:
    """Write atomically (:func:`write_text_atomic`: temporary file, fsync, rename)."""

    write_text_atomic(path, posterior_to_json(state))


def posterior_to_json(state) -> str:
    """The saved posterior's text: strict JSON (the one converter, jsonout.sanitise)."""
    return json.dumps(sanitise(state.to_dict()), allow_nan=False, indent=1)


POSTERIOR_SIGMA_MAX = 1e6  # a parameter's σ in a saved posterior, in its SI unit (rad for angles)


def load_posterior(path: str | Path, names: Sequence[str] | None = None) -> PosteriorState:
    """Read and check a saved posterior; a missing, corrupt or mismatched file raises
    :class:`estimator.posterior.PosteriorFileError`. Read without blocking and within the
    size limit (config.readfile: a FIFO or a device is refused, not waited on); a covariance
    whose σ exceeds :data:`POSTERIOR_SIGMA_MAX` (``1e308·I``) is refused, not computed with."""
    import numpy as np

    from rsra.config.readfile import UnreadableFile, read_text
    from rsra.estimator.posterior import PosteriorFileError, posterior_from_json

    path = Path(path)
    try:
        text = read_text(path)
    except UnreadableFile as e:
        problem = "no such file" if e.problem == "file not found" else e.problem
        raise PosteriorFileError(path, problem) from None
    state = posterior_from_json(text, path, names)
    variance = np.diag(state.P)
    if variance.size and not float(np.max(variance)) <= POSTERIOR_SIGMA_MAX ** 2:
        worst = state.names[int(np.argmax(variance))]
        raise PosteriorFileError(path, f"the covariance of {worst} (σ = "
                                 f"{float(np.sqrt(np.max(variance))):.3g}) exceeds "
                                 f"{POSTERIOR_SIGMA_MAX:g}: not a posterior",
                                 f"rsra angles reset {path}, or give another posterior file")
    return state
