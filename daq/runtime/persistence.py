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
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

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
        with os.fdopen(fd, "wb") as f:
            f.write(data)
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
