"""An output never replaces an input (docs/cli.md §16): the one place the rule is enforced.

Every command that writes a file checks each output it was given against every input it
reads — recording files, the files of a recording folder, results, posteriors and state
files, the rig files with every base they ``extends`` and every EDS file they name, scenario
files, Zenoh configs — before it reads anything: the same path, a symbolic link to an input, a
hard link to one (compared by device and inode, so no spelling of a path gets through), or a
name that would become part of an input recording folder (``frames*.log``, ``angles.jsonl``,
…) is refused with one line, exit 2. What the output itself is (a folder, a FIFO nobody
reads, a block device: refused) is judged by the one writer,
:class:`daq.runtime.persistence.OutputFile`, which then writes it: under a temporary name
renamed into place when complete (a failed run leaves the old file whole), or in place for a
character device or a read pipe.
"""
from __future__ import annotations

import os
import re
import stat
import tempfile
from collections.abc import Iterable
from pathlib import Path

from rsra.config.readfile import (
    TEXT_LIMIT,
    UnreadableFile,
    check_utf8,
    kind_of,
    regular_file_problem,
)
from rsra.daq.cli.options import UsageError
from rsra.daq.runtime.persistence import OutputFile, OutputRefused, temp_prefix

# the arguments that name inputs, over every command (absent ones are skipped)
INPUT_OPTIONS = {"logs": None, "inputs": None, "results": None, "files": None,
                 "config": "--config", "angles": "--angles", "zenoh_config": "--zenoh-config",
                 "state_file": "--state-file", "sim": "--sim", "scenario": "--scenario",
                 "truth": "--truth"}
# inputs that must be regular files (read whole: a FIFO would block, a device never end),
# refused before anything starts
FILE_OPTIONS = ("config", "zenoh_config", "files")  # (files: `rsra web`'s telemetry files)
# the arguments that name recordings, and the text files of a recording folder
RECORDING_OPTIONS = ("logs", "inputs", "angles")
RECORDING_TEXTS = ("angles.jsonl", "config.json")
# names that belong to a recording folder (daq/bus/recorder.py): an output of that name in an
# input recording folder would become part of that recording on its next replay
_RECORDING_NAME = re.compile(r"^(frames(_\d+)?\.[A-Za-z0-9]+|angles\.jsonl|config\.json|"
                             r"truth\.npz|eds)$")
FOLDER_FILES_MAX = 100_000
# what `rsra report --out DIR` and `rsra demo --report DIR` write there (daq.analysis.report)
REPORT_FILES = ("summary.json", "summary.md", "hub_loads.png", "hub_load_errors.png",
                "angles.png", "innovations.png", "spectra.png")  # a folder given as input is looked through to this many entries


def _strings(args: object, attr: str) -> list[str]:
    """The paths an argument gives (one or a list; absent, empty and non-text left out)."""
    value = getattr(args, attr, None)
    return [v for v in (value if isinstance(value, list) else [value])
            if v and isinstance(v, str)]


class Inputs:
    """The files a command reads, by (device, inode), with the name the user gave."""

    def __init__(self) -> None:
        self._files: dict[tuple[int, int], tuple[str, str]] = {}  # (label, path)
        self._folders: dict[tuple[int, int], str] = {}
        self._inner: dict[tuple[int, int], str] = {}  # folders inside an input folder (eds/)

    def add(self, path: str | os.PathLike[str], label: str | None = None) -> None:
        name = label or str(path)
        try:
            st = os.stat(path)
        except (OSError, ValueError):  # not there: the command's own check says so
            return
        if stat.S_ISDIR(st.st_mode):
            self._folders[(st.st_dev, st.st_ino)] = name
            self._add_folder(Path(path), name)
        elif stat.S_ISREG(st.st_mode):
            self._files.setdefault((st.st_dev, st.st_ino), (name, str(path)))

    def _add_folder(self, folder: Path, name: str) -> None:
        """The files of an input folder (to :data:`FOLDER_FILES_MAX` entries) and the folders
        inside it."""
        for n, f in enumerate(folder.rglob("*")):
            if n >= FOLDER_FILES_MAX:
                break
            try:
                fst = os.stat(f)
            except OSError:
                continue
            if stat.S_ISREG(fst.st_mode):
                self._files.setdefault((fst.st_dev, fst.st_ino), (f"{f}", f"{f}"))
            elif stat.S_ISDIR(fst.st_mode):
                self._inner.setdefault((fst.st_dev, fst.st_ino), name)

    def add_args(self, args: object, extra: Iterable[str | None] = (),
                 outputs: Iterable[str] = ()) -> Inputs:
        for attr, option in INPUT_OPTIONS.items():
            if attr in outputs:  # (--truth: an input of report, an output of run and sim)
                continue
            for v in _strings(args, attr):
                if v != "-":
                    self.add(v, f"{option} {v}" if option else str(v))
        for more in extra:
            if more:
                self.add(more)
        self.add_rig(getattr(args, "config", None))
        return self

    def add_rig(self, config: list[str] | str | None) -> None:
        """The packaged rig, the --config files and their bases (``extends``, transitively),
        the EDS files they name and the identification.state_file they set: read (or written
        only as a posterior) by the command, so never an output."""
        from rsra.config.rig import ConfigError, config_files, layer_paths, merge_layers

        files = config_files(config)
        for f in layer_paths(files):
            self.add(f, f"{f} (a rig or EDS file the command reads)")
        try:
            raw, _ = merge_layers(files)
        except ConfigError:
            return
        ident = raw.get("identification")
        state = ident.get("state_file") if isinstance(ident, dict) else None
        if isinstance(state, str) and state:
            self.add(state, f"identification.state_file {state}")

    def check(self, option: str, path: str | os.PathLike[str]) -> None:
        """Refuse ``path`` as the output of ``option`` if it is, or links to, an input."""
        p = Path(path)
        try:
            st = os.stat(p)
        except (OSError, ValueError):
            st = None
        if st is not None and (st.st_dev, st.st_ino) in self._files:
            what, where = self._files[(st.st_dev, st.st_ino)]
            raise UsageError(f"{option} {path}: {_how(p, where)} the input {what}; an output "
                             "never replaces an input; fix: give another file name")
        folder = self._recording_holding(p)
        if folder is not None:
            raise UsageError(f"{option} {path}: would become part of the input recording "
                             f"{folder}; fix: give another file name or folder")

    def _recording_holding(self, p: Path) -> str | None:
        """The input recording folder a new file ``p`` would become part of, or None."""
        try:
            pst = os.stat(p.resolve().parent)
        except (OSError, ValueError, RuntimeError):
            return None
        key = (pst.st_dev, pst.st_ino)
        folder = self._folders.get(key)
        if key in self._inner or (folder is not None and _RECORDING_NAME.match(p.resolve().name)):
            return folder or self._inner[key]
        return None

    def check_folder(self, option: str, folder: str | os.PathLike[str],
                     names: Iterable[str] = ()) -> None:
        """Refuse an output folder that is (or is inside) an input folder, or where a file the
        command writes there is an input."""
        try:
            st = os.stat(folder)
        except (OSError, ValueError):
            st = None
        if st is not None and not stat.S_ISDIR(st.st_mode):
            kind = kind_of(st.st_mode) or "is a file"
            raise UsageError(f"{option} {folder}: {kind}, not a folder; fix: give a folder")
        if st is not None:
            key = (st.st_dev, st.st_ino)
            what = self._folders.get(key) or self._inner.get(key)
            if what is not None:
                raise UsageError(f"{option} {folder}: is (inside) the input folder {what}; an "
                                 "output never goes into an input; fix: give another folder")
        for name in names:
            self.check(option, Path(folder) / name)


def _how(p: Path, where: str) -> str:
    """How an output path ``p`` is the input file at ``where``."""
    if p.is_symlink():
        return "is a symbolic link to"
    if os.path.realpath(p) == os.path.realpath(where):
        return "is"
    return "is the same file as (a hard link to)"


def check_outputs(args: object, outputs: dict[str, str | tuple[str, ...]],
                  more_inputs: Iterable[str] = ()) -> None:
    """The command's outputs against its inputs, before it reads anything. ``outputs`` maps an
    argument to ``"file"``, ``"folder"`` or the names it writes into a folder."""
    check_input_files(args)
    inputs: Inputs | None = None
    for attr, kind in outputs.items():
        value = getattr(args, attr, None)
        if not value or value == "-" or not isinstance(value, str):
            continue
        if inputs is None:
            inputs = Inputs().add_args(args, [getattr(args, a, None) for a in more_inputs],
                                       outputs)
        option = "--" + attr.replace("_", "-")
        if kind == "file":
            inputs.check(option, value)
            probe_file(option, value)
        else:
            inputs.check_folder(option, value, () if kind == "folder" else kind)


def check_input_files(args: object) -> None:
    """The inputs read whole by name (rig TOMLs, a Zenoh config) are regular files within the
    size limit (config.readfile): a FIFO, a device or a folder refused in one line before
    anything opens it (a FIFO would block that open, a device never end). A recording
    folder's text files (``angles.jsonl``, ``config.json``) are regular files of UTF-8 text:
    a bad byte is one line naming the file and the line, not a decoding error later."""
    for attr in FILE_OPTIONS:
        for v in _strings(args, attr):
            if os.path.lexists(v):  # (not there: the command's own check says so)
                _check_whole_file(attr, v)
    _check_recording_texts(args)


def _check_recording_texts(args: object) -> None:
    """The text files of every recording folder given (its ``config.json`` only when the
    rig is not given: then the recording's own is not read)."""
    texts = [n for n in RECORDING_TEXTS
             if not (n == "config.json" and getattr(args, "config", None))]
    folders = [v for attr in RECORDING_OPTIONS for v in _strings(args, attr) if os.path.isdir(v)]
    for v in folders:
        for name in texts:
            check_text_file(Path(v) / name)


def _check_whole_file(attr: str, v: str) -> None:
    problem = regular_file_problem(v, None if attr == "files" else TEXT_LIMIT)
    if problem is not None:
        option = "" if attr == "files" else f"--{attr.replace('_', '-')} "
        raise UsageError(f"{option}{v}: {problem}; fix: give the path of the file itself")


def check_text_file(path: Path) -> None:
    """A text file rsra reads line by line (a recording's ``angles.jsonl``, its
    ``config.json``): if there, a regular file of UTF-8 text (streamed: no size limit) —
    else a UsageError naming it."""
    if not os.path.lexists(path):
        return
    try:
        check_utf8(path)
    except UnreadableFile as e:
        if path.name != "config.json":
            raise UsageError(str(e)) from None
        # the rig a recording was made on: without it the replay needs the rig's file
        raise UsageError(f"{path}: {e.problem}: the rig the recording was made on is not "
                         "readable; fix: give the rig's file with --config") from None


def probe_file(option: str, path: str | os.PathLike[str]) -> None:
    """An output file that cannot be there (:class:`OutputFile`'s rule: a folder, a FIFO
    nobody reads, a block device) or cannot be written there (a read-only or virtual file
    system such as /proc, no permission, no such folder) refused at once: for a new or regular
    file a temporary file is made beside it and removed again."""
    try:
        OutputFile(path).check()
    except OutputRefused as e:
        raise UsageError(f"{option} {e}") from None
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return  # a character device or a read pipe (/dev/stdout): written in place
    except OSError:
        pass
    p = Path(os.path.realpath(path))
    parent = p.parent
    if not parent.is_dir():
        raise UsageError(f"{option} {path}: no folder {parent}; fix: create it or write elsewhere")
    try:
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(p), suffix=".tmp", dir=parent)
    except OSError as e:
        raise UsageError(f"{option} {path}: cannot be written there ({e.strerror or e}); fix: "
                         "write elsewhere") from None
    os.close(fd)
    os.unlink(tmp)
