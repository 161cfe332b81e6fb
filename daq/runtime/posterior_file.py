"""The posterior files: which ones are ours, which rig they belong to, and the temporary files
a killed writer leaves (docs/identification.md "Saved posterior", docs/reliability.md).

The service and the commands replace only a file they can prove they wrote — a posterior of
our format — and never create, rename or delete anything else: ``identification.state_file``
naming a folder or a file that is not a valid posterior is a configuration error before
acquisition starts, and `rsra angles reset` leaves such a file alone.
"""
from __future__ import annotations

import logging
import os
import stat
from pathlib import Path
from typing import Literal

from rsra.config.rig import ConfigError, RigConfig
from rsra.daq.runtime.persistence import load_posterior, own_temp_pid
from rsra.estimator.posterior import (
    PosteriorFileError,
    PosteriorState,
    check_posterior,
    rig_fingerprint,
)

log = logging.getLogger("rsra.posterior")

FORMAT_TAG = '"format": "rsra-posterior"'
TAG_WITHIN = 200  # characters: save_posterior writes the tag first, even a torn file has it

Kind = Literal["absent", "posterior", "damaged", "foreign"]


def classify(path: str | Path) -> tuple[Kind, PosteriorState | None, str | None]:
    """What is at ``path``: ``absent``; a valid ``posterior`` (with its state); a ``damaged``
    one of ours (empty, or tagged as a posterior but unreadable); or ``foreign`` — a folder,
    a device, a pipe, any other file — which nobody here may replace. Returns (kind, state,
    problem)."""
    path = Path(path)
    try:
        st = os.stat(path)  # through a symbolic link: the file it names
    except FileNotFoundError:
        return "absent", None, None
    except OSError as e:
        return "foreign", None, f"cannot be examined ({e.strerror})"
    if stat.S_ISDIR(st.st_mode):
        return "foreign", None, "is a folder"
    if not stat.S_ISREG(st.st_mode):
        return "foreign", None, "is not a regular file"
    try:
        with open(path, "rb") as f:
            head = f.read(TAG_WITHIN)
    except OSError as e:
        return "foreign", None, f"cannot be read ({e.strerror})"
    if head.strip() and FORMAT_TAG.encode() not in head:
        return "foreign", None, "is not a posterior file"
    try:
        return "posterior", load_posterior(path), None
    except PosteriorFileError as e:
        return "damaged", None, e.problem


def rig_of(cfg: RigConfig) -> dict:
    return rig_fingerprint(cfg.rig_model().geometry)


def load_checked(cfg: RigConfig, path: str | Path, names=None, *,
                 accept_rig_mismatch: bool = False) -> tuple[PosteriorState, str | None]:
    """A posterior to start from (``--angles``): readable, of this rig (or
    ``accept_rig_mismatch``), every angle within ±``identification.angle_limit_deg``. Raises
    :class:`PosteriorFileError` (one line naming the file and the problem); returns the state
    and a one-line warning (version-1 file, or an accepted mismatch) or None."""
    state = load_posterior(path, names)
    warning = check_posterior(state, path, rig=rig_of(cfg),
                              angle_names=cfg.rig_model().geometry.angle_names,
                              angle_limit_rad=cfg.identification.angle_limit_rad,
                              accept_rig_mismatch=accept_rig_mismatch)
    return state, warning


def remove_own_temp_files(path: str | Path) -> list[Path]:
    """Remove the temporary files a killed writer of ``path`` left beside it — only ours, by
    their exact name (``.<name>.rsra-tmp.<pid>.<random>.tmp``, daq.persistence), regular
    files only, and only when the process that made it is gone. Returns what was removed."""
    target = Path(os.path.realpath(path))
    removed: list[Path] = []
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return removed
    for entry in entries:
        pid = own_temp_pid(entry.name, target.name)
        if pid is None or _alive(pid):
            continue
        try:
            if not entry.is_file(follow_symlinks=False):
                continue
            os.unlink(entry.path)
            removed.append(Path(entry.path))
        except OSError:
            continue
    return removed


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return pid > 0  # someone else's live process (or an absurd pid: not ours to judge)
    return True


def prepare_state_file(cfg: RigConfig, *, accept_rig_mismatch: bool = False) -> list[str]:
    """Before acquisition: may the service write ``identification.state_file``? Yes when it
    does not exist or holds a valid posterior of this rig; anything else — a folder, a device,
    a file that is not a posterior, a damaged one, another rig's (unless
    ``accept_rig_mismatch``) — is a :class:`ConfigError` naming the key, and is left as it
    was. Removes our own temporary files beside it. Returns warnings to report."""
    path = cfg.identification.state_file
    if not path:
        return []
    key = "identification.state_file"
    folder = Path(os.path.realpath(path)).parent
    if not folder.is_dir():  # never created for it: nothing the user did not name
        raise ConfigError(key, path, f"its folder {folder} does not exist",
                          "create the folder, or name a file in an existing one")
    kind, state, problem = classify(path)
    if kind == "foreign":
        raise ConfigError(key, path, f"{problem}; the service writes only its own posterior "
                          "files", "name a posterior file (or a new one) there, or \"\" for none")
    if kind == "damaged":
        raise ConfigError(key, path, f"a damaged posterior ({problem})",
                          f"rsra angles reset {path} (rewrites it with the prior), or delete it")
    warnings = []
    if state is not None and state.rig is not None:  # a version-1 file: ours, replaced
        try:
            w = check_posterior(state, path, rig=rig_of(cfg),
                                angle_names=cfg.rig_model().geometry.angle_names,
                                angle_limit_rad=float("inf"),  # replaced, not used: any angles
                                accept_rig_mismatch=accept_rig_mismatch)
        except PosteriorFileError as e:
            raise ConfigError(key, path, e.problem, "name another file, or pass "
                              "--accept-rig-mismatch to replace it") from None
        if w:
            warnings.append(w)
    removed = remove_own_temp_files(path)
    if removed:
        log.info("%s: removed %d temporary file(s) left by an interrupted save", path,
                 len(removed))
    return warnings

