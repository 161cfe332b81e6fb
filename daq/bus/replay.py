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
from rsra.daq.bus.reorder import FrameReorder, reordered
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


def config_for(paths: Sequence[str | Path], config: str | Path | None = None, *,
               several: str = "rig") -> RigConfig:
    """The rig to replay ``paths`` on, after the checks that they can be replayed right on it
    (docs/reliability.md "Replaying a recording"); :class:`ReplayError` (exit 2) otherwise.

    An explicit ``--config`` wins. Else every recording folder must hold a readable
    ``config.json`` (a folder without one needs ``--config``), and all of them the same rig
    (:data:`RIG_SECTIONS`); bare log files take the folders' rig, or the packaged default rig
    — and are refused, naming ``--config``, when more than :data:`MISFIT_FRACTION` of their
    first :data:`FIT_FRAMES` frames do not fit it. ``several``: ``"parts"`` (replay,
    export) takes several inputs only as consecutive parts of one recording
    (:func:`check_consecutive`); ``"rig"`` (calibrate, which pools separate stretches by
    design) only as recordings of one rig."""
    inputs = [Path(p) for p in paths]
    if config is not None:
        cfg = load_rig(config)
    else:
        raws = [(p, _folder_config(p)) for p in inputs if p.is_dir()]
        for (a, ra), (b, rb) in zip(raws, raws[1:]):
            differs = [k for k in RIG_SECTIONS if ra.get(k) != rb.get(k)]
            if differs:
                raise ReplayError(
                    f"{a} and {b} were recorded on different rigs ({', '.join(differs)} "
                    f"differ{'s' if len(differs) == 1 else ''}); fix: " + (
                        "calibrate the recordings of one rig together" if several == "rig"
                        else "replay one recording at a time"))
        if raws:
            cfg = recorded_config(raws[0][0]) or load_rig()
        else:
            cfg = load_rig()
        for p in inputs:
            if not p.is_dir():
                check_fits(p, cfg, "the recording folder's rig" if raws else
                           "the packaged default rig")
    if several == "parts":
        check_consecutive(inputs, cfg)
    return cfg


#: the sections of a recorded configuration that say which rig it was (recordings that differ
#: in these are two rigs; filter, identification, telemetry, … settings may differ)
RIG_SECTIONS = ("rig", "geometry", "mass", "cells", "inertial", "accelerometers", "rotor",
                "balance", "sync", "nodes", "calibration")
FIT_FRAMES = 20_000  # a bare log is judged by its first frames (decided early, bounded)
MISFIT_FRACTION = 0.01  # more than this of them not fitting the rig: refused (needs --config)
FIT_MIN_FRAMES = 100  # a log shorter than this is not judged (too few frames to say)
JOIN_GAP_S = 60.0  # consecutive parts: the next starts at most this long after the last ends


def _folder_config(folder: Path) -> dict:
    """A recording folder's own configuration (raw); refused when it has none readable."""
    from rsra.daq.bus.recorder import CONFIG_FILE, recorded_config_raw

    p = folder / CONFIG_FILE
    raw = recorded_config_raw(folder) if p.is_file() else None
    if raw is None:
        what = "no" if not p.exists() and not p.is_symlink() else "no readable"
        raise ReplayError(f"{folder}: {what} {CONFIG_FILE} (the rig it was recorded on; "
                          f"{'missing' if what == 'no' else 'not a regular file'}): replayed "
                          "on another rig its samples would be wrong; fix: give the rig's "
                          "file with --config")
    return raw


def check_fits(path: Path, cfg: RigConfig, rig: str) -> None:
    """A bare log's first :data:`FIT_FRAMES` frames against ``cfg``: a frame with an
    identifier the rig does not use, or a data frame of the wrong length, does not fit; more
    than :data:`MISFIT_FRACTION` of them: :class:`ReplayError` naming ``--config``."""
    from rsra.daq.bus.decoder import DecodeTable
    from rsra.daq.bus.reader import known_cob_ids

    table = DecodeTable(cfg)
    known = known_cob_ids(cfg, table)
    lengths = {cob: lay.length for cob, lay in table.tpdos.items()}
    n = bad = 0
    for f in expand([path]):
        frames = read_file(f)
        try:
            for msg in frames:
                if msg.is_error_frame:
                    continue
                n += 1
                cid = msg.arbitration_id
                if (msg.is_extended_id or cid not in known
                        or (not msg.is_remote_frame and len(msg.data) != lengths.get(cid,
                                                                                 len(msg.data)))):
                    bad += 1
                if n >= FIT_FRAMES:
                    break
        except ReplayError:
            pass  # a damaged file is read (and refused where it breaks) by the replay itself
        finally:
            frames.close()
        if n >= FIT_FRAMES:
            break
    if n >= FIT_MIN_FRAMES and bad > MISFIT_FRACTION * n:
        raise ReplayError(
            f"{path}: {bad} of its first {n} frames ({100 * bad / n:.1f} %) do not fit "
            f"{rig} ({cfg.rig_name}: identifiers it does not use, or wrong lengths): it was "
            "recorded on another rig; fix: give that rig's file with --config")


def _sync_ends(paths: list[Path], cfg: RigConfig, last: bool) -> tuple[float, int] | None:
    """The (time, counter) of the first (``last=False``) or last SYNC of one input."""
    sync = cfg.sync.cob_id
    ov = cfg.sync.counter_overflow
    files = expand(paths)
    found: tuple[float, int] | None = None
    for f in (reversed(files) if last else files):
        frames = _tail(f) if last and f.suffix.lower() == ".log" else read_file(f)
        try:
            for i, m in enumerate(frames):
                if (m.arbitration_id == sync and not m.is_extended_id and not m.is_error_frame
                        and len(m.data) == 1 and 1 <= m.data[0] <= ov):
                    found = (m.timestamp, m.data[0])
                    if not last:
                        return found
                if not last and i >= FIT_FRAMES:
                    return None
        except ReplayError:
            return found  # a damaged file: the replay refuses it where it breaks
        finally:
            if hasattr(frames, "close"):
                frames.close()
        if found is not None:
            return found
    return found


def _tail(f: Path, nbytes: int = 1 << 16) -> Iterator[can.Message]:
    """The frames of a candump log's last ``nbytes`` (its whole lines)."""
    with open(f, "rb") as fh:
        size = fh.seek(0, 2)
        fh.seek(max(0, size - nbytes))
        data = fh.read(nbytes)
    lines = data.decode("utf-8", "replace").splitlines(keepends=True)
    if size > nbytes:
        lines = lines[1:]  # the first may be cut
    reader = can.CanutilsLogReader(_Lines(x for x in lines if x.endswith("\n")))  # type: ignore[arg-type]
    try:
        yield from reader
    except Exception:  # a damaged tail: the replay itself names it
        return


class _Lines(list):
    def __init__(self, it: Iterable[str]):
        super().__init__(it)

    def close(self) -> None:
        pass


def check_consecutive(paths: Sequence[Path], cfg: RigConfig) -> None:
    """Several inputs only as consecutive parts of one recording: each next input's first
    SYNC continues the previous input's last one — later in time (by at most
    :data:`JOIN_GAP_S`) and, within ``GAP_S``, with the counter the time says. Else
    :class:`ReplayError` naming the two inputs."""
    from rsra.daq.bus.assembler import GAP_S, SyncClock

    for a, b in zip(paths, paths[1:]):
        end = _sync_ends([a], cfg, last=True)
        start = _sync_ends([b], cfg, last=False)
        if end is None or start is None:
            continue  # no SYNC to judge by (the replay counts what it finds)
        (ta, ca), (tb, cb) = end, start
        why = None
        if tb <= ta:
            why = f"{b} starts {ta - tb:.3f} s before {a} ends"
        elif tb - ta > JOIN_GAP_S:
            why = f"{tb - ta:.0f} s between them"
        elif tb - ta <= GAP_S:
            clock = SyncClock(cfg.sample_period_s, cfg.sync.counter_overflow)
            clock.stamp_sync(ca, ta, ta)
            clock.stamp_sync(cb, tb, ta)
            if clock.bad_timestamp or clock.duplicate or clock.jumped:
                why = (f"SYNC counter {cb} {tb - ta:.3f} s after {ca} does not continue it")
        if why:
            raise ReplayError(
                f"{a} and {b} are not consecutive parts of one recording ({why}); fix: "
                "give one recording's parts in order, or one recording at a time")


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
    if frames is None:  # a recording: into time order first (daq.bus.reorder; late: counted)
        r.monitor.reorder = FrameReorder()
        src = reordered(src, reorder=r.monitor.reorder, sync_id=cfg.sync.cob_id)
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
