"""Replay of recordings through the reader (docs/bus.md §5 "Recording and replay", docs/cli.md §6).

Recordings are read with python-can's :class:`can.LogReader` (candump ``.log``, ``.blf``,
``.asc``, …), either

* as fast as possible straight into the reader (:func:`replay`): the frames go through the
  same :class:`daq.reader.FrameTap` → canopen subscribe → assembler/supervisor code path as
  on the live bus, so a ``.log`` or ``.blf`` recording assembles exactly the samples the live
  reader did (``.asc`` keeps relative times only); or
* at recorded timing (:func:`replay_to_bus`, ``can.MessageSync``) onto any python-can bus,
  for a live reader (or any other tool) on that bus.

Recordings that start mid-flight, without the boot sequence, decode by the EDS mapping: the
decode tables never depend on having seen the boot.
"""
from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import can

from rsra.daq.bus.assembler import Sample
from rsra.config.rig import RigConfig
from rsra.daq.rigmodel import load_rig
from rsra.daq.bus.reader import HealthReport, OfflineReader, ReaderBase
from rsra.daq.bus.recorder import frame_files, recorded_config
from rsra.daq.bus.logfiles import (  # noqa: F401  (the replay's names, where its users import them)
    ReplayError,
    candump_frames,
    cut_line_dropped,
    read_file,
)

LOG_SUFFIXES = (".log", ".blf", ".asc", ".trc", ".csv", ".mf4")
log = logging.getLogger(__name__)


def expand(paths: Sequence[str | Path]) -> list[Path]:
    """Frame files in replay order: a folder gives its frame files (closed files first), a
    file is taken as given; order of the arguments is kept."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            files = frame_files(p)
            if not files:
                raise ReplayError(f"{p}: no frames.* recording files in this folder")
            out.extend(files)
        elif p.exists() and not p.is_file():
            raise ReplayError(f"{p}: not a regular file (a device, a pipe or a socket); fix: give "
                              "a recording file or folder")
        elif p.is_file():
            suffixes = [s.lower() for s in p.suffixes]
            if not suffixes or not ({*suffixes} & {*LOG_SUFFIXES}):
                raise ReplayError(f"{p}: unknown log format (use one of "
                                  f"{', '.join(LOG_SUFFIXES)})")
            out.append(p)
        else:
            raise ReplayError(f"{p}: no such file or folder")
    return out


def read_frames(paths: Sequence[str | Path]) -> Iterator[can.Message]:
    """Every frame of the recordings, in order (python-can LogReader per file).

    A file that cannot be read — not the format its name says, damaged, a line that is not a
    frame, a time stamp that is not a finite number — raises :class:`ReplayError` naming the
    file (and the line of a text log) where it stops; the frames before it have been
    yielded. Recordings that hold no frame at all raise :class:`ReplayError` at their end (an
    empty recording is an error, not an empty replay)."""
    n = 0
    for f in expand(paths):
        for msg in read_file(f):
            n += 1
            yield msg
    if n == 0:
        raise ReplayError(f"{', '.join(map(str, paths))}: no CAN frames in it (an empty "
                          "recording); fix: give a recording that holds frames")


def check_readable(paths: Sequence[str | Path]) -> None:
    """Each recording file readable at its start and the recordings not empty, checked before
    any work (:func:`read_frames` would find either only when it gets there)."""
    empty = True
    for f in expand(paths):
        frames = read_file(f)
        try:
            empty = next(frames, None) is None and empty
        finally:
            frames.close()
    if empty:
        raise ReplayError(f"{', '.join(map(str, paths))}: no CAN frames in it (an empty "
                          "recording); fix: give a recording that holds frames")


def config_for(paths: Sequence[str | Path], config: str | Path | None = None) -> RigConfig:
    """An explicit ``--config`` wins; else a recording folder's own effective configuration;
    else the packaged default rig."""
    if config is not None:
        return load_rig(config)
    for p in map(Path, paths):
        if p.is_dir():
            cfg = recorded_config(p)
            if cfg is not None:
                return cfg
    return load_rig()


def replay(cfg: RigConfig, paths: Sequence[str | Path] | None = None, *,
           frames: Iterable[can.Message] | None = None, realtime: bool = False,
           reader: ReaderBase | None = None, finish: bool = False, streaming: bool = False
           ) -> Iterator[Sample | HealthReport]:
    """Samples and 1 Hz health reports of recordings, in order, through the reader's code
    path. ``realtime`` paces the frames at their recorded timing (``can.MessageSync``).
    ``finish`` also passes on the last, incomplete sample when the recording ends.

    Recordings read from ``paths`` as fast as possible take the columnar path
    (daq.bus.columnar: the file read in blocks, the clean SYNC periods assembled per block,
    every other frame through the reader one by one), which gives the same items;
    ``streaming`` (or ``frames``, or ``realtime``) feeds every frame one by one."""
    r = reader or OfflineReader(cfg)
    if frames is None and not realtime and not streaming:
        from rsra.daq.bus.columnar import replay_columnar

        yield from replay_columnar(r, expand(paths or ()), finish=finish, names=paths or ())
        return
    src = frames if frames is not None else read_frames(paths or ())
    if realtime:
        src = can.MessageSync(src, timestamps=True, gap=0.0)
    feed, poll = r.feed, r.poll
    pending = r.items.queue.queue  # the queue's deque: a length test, not qsize()'s lock per frame
    for msg in src:
        feed(msg)
        if pending:
            yield from poll()
    if finish:
        r.assembler.finish()
    yield from poll()


def replay_to_bus(paths: Sequence[str | Path], bus: can.BusABC, *,
                  realtime: bool = True) -> int:
    """Send recorded frames onto ``bus`` (at recorded timing unless ``realtime=False``).
    Returns the number of frames sent. Error frames are sent as recorded where the
    interface can (python-can's virtual bus can)."""
    n = 0
    src: Iterable[can.Message] = read_frames(paths)
    if realtime:
        src = can.MessageSync(src, timestamps=True, gap=0.0)
    for msg in src:
        bus.send(msg)
        n += 1
    return n
