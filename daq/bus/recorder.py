"""Recording of every frame seen on the bus (docs/bus.md §5 "Recording and replay").

A recording folder holds:

* ``frames.<fmt>`` (the file being written) and ``frames_NNNNNN.<fmt>`` (closed files, in
  order), written by python-can's :class:`can.SizedRotatingLogger` (candump ``.log`` by
  default, ``.blf`` or ``.asc`` on request), rotated by size;
* ``angles.jsonl``: the starting posterior, then every published ``angles`` record verbatim
  (written by the service through :meth:`Recorder.write_angles`);
* ``config.json``: the effective configuration, with the EDS files copied beside it in
  ``eds/`` so that the folder replays on its own.

The recorder is a :class:`can.Listener` on the bus thread. It flushes at least every
``flush_s`` of acquisition time (frame timestamps), so a crash loses at most that much. A
total-size cap or a full disk stops the recording with a loud error in health while
acquisition goes on. Nothing is ever deleted or overwritten.

Live (``threaded=True``: the reader runs on the wall clock) the frames go through a bounded
queue to a writer thread, so a slow or stalled disk never stalls the bus thread: when the
queue is full a frame is not recorded, and counted (``dropped``, ``queue.overflow`` in
health). In lock-step and replay (``threaded=False``) the frames are written inline: nothing
runs in real time there, so a slow disk only slows the run and nothing is dropped.
"""
from __future__ import annotations

import json
import logging
import os
import queue
import re
import shutil
import threading
from pathlib import Path

import can

from rsra.config.rig import RigConfig
from rsra.daq.jsonout import sanitise

log = logging.getLogger(__name__)

FRAMES_STEM = "frames"
ANGLES_FILE = "angles.jsonl"
CONFIG_FILE = "config.json"
EDS_DIR = "eds"
FORMATS = ("log", "blf", "asc")
_ROTATED = re.compile(rf"^{FRAMES_STEM}_(\d+)\.(log|blf|asc|mf4)$")
MB = 1_000_000
CAP_CHECK_MASK = 0xFF  # check the size cap every 256 frames
WRITER_QUEUE = 16384  # frames (≈ 6 s of the default bus at 200 samples/s; a few MB at most)
WRITER_STOP_S = 10.0  # how long stop() waits for the writer thread to drain the queue


class RecordingError(RuntimeError):
    """The recording cannot start (folder already holds one, format not available, …)."""


def frame_files(folder: Path) -> list[Path]:
    """The frame files of a recording folder in time order (closed files, then the live one)."""
    rotated = []
    current = []
    for p in folder.iterdir():
        m = _ROTATED.match(p.name)
        if m:
            rotated.append((int(m.group(1)), p))
        elif p.stem == FRAMES_STEM and p.suffix.lstrip(".") in FORMATS + ("mf4",):
            current.append(p)
    return [p for _, p in sorted(rotated)] + sorted(current)


class _FolderStart:
    """The files and folders one recording's start creates in ``folder`` (the folder and its
    missing parents, the effective configuration and its EDS files, then the recording's own
    files), noted as they are made so that a start that fails removes exactly them: never
    anything that was there before."""

    def __init__(self, folder: Path):
        self.folder = folder
        #: created by this start, outermost first
        self.created: list[Path] = []

    def new(self, path: Path) -> Path:
        """``path``, noted as created by this start unless it was there already."""
        if not (path.exists() or path.is_symlink()):
            self.created.append(path)
        return path

    def make_folder(self) -> None:
        missing = []
        p = self.folder
        while not p.exists():
            missing.append(p)
            p = p.parent
        self.folder.mkdir(parents=True, exist_ok=True)
        self.created.extend(reversed(missing))  # outermost first

    def write_config(self, cfg: RigConfig) -> None:
        """The effective configuration (config.json) with copies of its EDS files."""
        eff = cfg.effective()
        eds_dir = self.new(self.folder / EDS_DIR)
        eds_dir.mkdir(exist_ok=True)
        nodes = []
        for raw_node, nc in zip(eff.get("nodes", []), cfg.nodes):
            d = dict(raw_node)
            target = eds_dir / nc.eds.name
            if not target.exists():
                shutil.copyfile(nc.eds, self.new(target))
            d["eds"] = f"{EDS_DIR}/{nc.eds.name}"
            nodes.append(d)
        if nodes:
            eff["nodes"] = nodes
        with open(self.new(self.folder / CONFIG_FILE), "w", encoding="utf-8") as f:
            json.dump(sanitise(eff), f, indent=1, allow_nan=False)

    def remove_created(self) -> None:
        """Remove what this start created, innermost first (a folder only if empty)."""
        for p in reversed(self.created):
            try:
                if p.is_dir() and not p.is_symlink():
                    p.rmdir()  # only if empty: never anything we did not write
                else:
                    p.unlink()
            except OSError:
                pass
        self.created = []


class Recorder(can.Listener):
    """Writes every frame it is given to a rotating log in ``folder`` (see module docstring)."""

    def __init__(self, folder: str | Path, cfg: RigConfig, fmt: str | None = None,
                 rotate_mb: float | None = None, cap_mb: float | None = None,
                 flush_s: float | None = None, threaded: bool = False,
                 queue_size: int = WRITER_QUEUE, channel: str = "can"):
        self.folder = Path(folder)
        #: the channel name written on every frame (rsra.canbus.recording_channel)
        self.channel = channel
        #: angles.jsonl stays open through :meth:`stop` (also when python-can's Notifier stops
        #: its listeners): the service still records the last windows' results, then calls
        #: :meth:`close_angles`
        self.keep_angles_open = False
        self.fmt = (fmt or cfg.recording.format).lstrip(".")
        if self.fmt not in FORMATS:
            raise RecordingError(f"recording format {self.fmt!r} is not available here; "
                                 f"use one of {', '.join(FORMATS)}")
        rec = cfg.recording
        self.rotate_bytes = int((rotate_mb if rotate_mb is not None else rec.rotate_mb) * MB)
        self.cap_bytes = int((cap_mb if cap_mb is not None else rec.cap_mb) * MB)
        self.flush_s = flush_s if flush_s is not None else cfg.recording.flush_s
        if self.folder.exists() and not self.folder.is_dir():
            raise RecordingError(f"{self.folder} is a file, not a folder: give a new folder")
        if self.folder.exists() and (frame_files(self.folder)
                                     or (self.folder / ANGLES_FILE).exists()):
            raise RecordingError(f"{self.folder} already holds a recording; nothing is ever "
                                 "overwritten: give a new folder")
        # what this start creates, removed again if the start fails (a full disk, no
        # permission): a recording that never started leaves nothing behind
        start = _FolderStart(self.folder)
        try:
            self._start_files(cfg, start)
        except OSError as e:
            for fh in (getattr(self, "_angles", None),):
                if fh is not None:
                    try:
                        fh.close()
                    except OSError:
                        pass
            start.remove_created()
            raise OSError(e.errno, f"cannot start the recording ({e.strerror or e}); nothing "
                          "was recorded", str(self.folder)) from None
        self._lock = threading.Lock()  # angles.jsonl is written from the service thread
        self._io_lock = threading.Lock()  # frames: bus thread, and the live idle tick
        self._rotated: list[Path] = []
        self._closed_bytes = 0
        self.frames = 0
        self.dropped = 0  # frames seen after the recording stopped
        self.error: str | None = None
        self.active = True
        self._last_flush: float | None = None
        self._logger.namer = self._name_rotated
        self._size = 0  # bytes_written as of the writer's last check (health reads this live)
        # live: a bounded queue to a writer thread (a slow disk must not stall the bus thread)
        self.queue_size = int(queue_size)
        self.overflow = 0  # frames not recorded because the writer queue was full
        self.queued = 0  # frames handed to the writer thread
        self.max_depth = 0
        self._queue: queue.Queue | None = None
        self._writer: threading.Thread | None = None
        if threaded:
            self._queue = queue.Queue(self.queue_size)
            self._writer = threading.Thread(target=self._write_loop, name="rsra-recorder",
                                            daemon=True)
            self._writer.start()

    # -- files -------------------------------------------------------------------------------
    def _start_files(self, cfg: RigConfig, start: _FolderStart) -> None:
        start.make_folder()
        start.write_config(cfg)
        self._angles = open(start.new(self.folder / ANGLES_FILE), "w", encoding="utf-8")
        base = start.new(self.folder / f"{FRAMES_STEM}.{self.fmt}")
        self._logger = can.SizedRotatingLogger(base_filename=base, max_bytes=self.rotate_bytes)

    def _name_rotated(self, default_name: str | os.PathLike[str]) -> str:
        # deterministic, sortable names (python-can's default uses the wall-clock date)
        p = self.folder / f"{FRAMES_STEM}_{self._logger.rollover_count:06d}.{self.fmt}"
        self._rotated.append(p)
        return str(p)

    # -- can.Listener --------------------------------------------------------------------------
    def on_message_received(self, msg: can.Message) -> None:
        q = self._queue
        if q is None:
            with self._io_lock:
                self._record(msg)
            return
        if not self.active:
            self.dropped += 1
            return
        try:
            q.put_nowait(msg)
        except queue.Full:  # the disk is behind: never wait on the bus thread
            if not self.overflow:
                log.error("recording: the disk is behind, writer queue full (%d frames); "
                          "frames are being dropped (counted in health)", self.queue_size)
            self.overflow += 1
            self.dropped += 1
            return
        self.queued += 1
        depth = len(q.queue)  # a statistic: no need for qsize()'s lock (per frame)
        if depth > self.max_depth:
            self.max_depth = depth

    def _write_loop(self) -> None:
        q = self._queue
        assert q is not None  # the writer thread is made with its queue
        while True:
            item = q.get()
            if item is None:
                return
            with self._io_lock:
                if isinstance(item, float):  # an idle tick (acquisition time)
                    self._tick(item)
                else:
                    self._record(item)

    def _record(self, msg: can.Message) -> None:
        if not self.active:
            self.dropped += 1
            return
        written = False
        try:
            n_rot = len(self._rotated)
            msg.channel = self.channel  # stable and short, whatever the interface put there
            self._logger.on_message_received(msg)
            self.frames += 1
            written = True
            if len(self._rotated) != n_rot:
                self._closed_bytes += sum(p.stat().st_size for p in self._rotated[n_rot:])
            t = msg.timestamp
            if self._last_flush is None:
                self._last_flush = t
            elif t - self._last_flush >= self.flush_s:
                self._last_flush = t
                self.flush()
            elif not self.frames & CAP_CHECK_MASK:
                self._size = self.bytes_written
                if self._size >= self.cap_bytes:
                    self.flush()  # between flushes too: the cap is overshot by a few kB at most
        except OSError as e:  # full disk, removed medium, …
            self.dropped += not written  # the frame in hand is not recorded either
            self._fail(f"recording stopped: {e.strerror or e} ({self.folder}); "
                       "acquisition goes on, frames are no longer recorded")
        except Exception as e:  # never let the recorder stop the bus thread
            self.dropped += not written
            self._fail(f"recording stopped: {type(e).__name__}: {e}")

    def tick(self, now: float) -> None:
        """Live idle tick (acquisition clock): flush frames still buffered when the bus went
        quiet, so a crash loses at most ``flush_s`` of them."""
        if self._queue is not None:  # the writer thread flushes (never wait on a slow disk)
            if self._queue.empty():  # else it is busy: the tick after it drains will do
                try:
                    self._queue.put_nowait(float(now))
                except queue.Full:
                    pass
            return
        with self._io_lock:
            self._tick(now)

    def _tick(self, now: float) -> None:
        if self.active and self._last_flush is not None and \
                now - self._last_flush >= self.flush_s:
            self._last_flush = now
            try:
                self.flush()
            except OSError as e:
                self._fail(f"recording stopped: {e.strerror or e} ({self.folder})")

    def flush(self) -> None:
        """Push buffered frames to the OS; stop at the size cap."""
        if not self.active:
            return
        w = self._logger.writer
        if isinstance(w, can.BLFWriter):
            w._flush()  # BLF buffers a whole container in memory otherwise
        f = getattr(w, "file", None)
        if f is not None:
            f.flush()
        total = self._size = self.bytes_written
        if total >= self.cap_bytes:
            self._fail(f"recording stopped at the size cap ({total / MB:.3g} MB >= "
                       f"{self.cap_bytes / MB:.3g} MB, recording.cap_mb); acquisition goes on")

    def _fail(self, message: str) -> None:
        self.error = message
        log.error("%s", message)
        self._close_frames()

    def _close_frames(self) -> None:
        """Close the frame file (python-can writes the BLF header here); count its size."""
        if not self.active:
            return
        self.active = False
        try:
            self._logger.stop()
        except Exception as e:  # the file may be unwritable by now
            self.error = self.error or f"closing the recording failed: {e}"
            log.error("closing the recording failed: %s", e)
        try:
            self._closed_bytes += Path(self._logger.base_filename).stat().st_size
        except OSError:
            pass
        self._size = self._closed_bytes

    def on_error(self, exc: Exception) -> None:  # bus errors are the reader's business
        pass

    @property
    def bytes_written(self) -> int:
        size = 0
        if self.active:
            try:
                size = self._logger.writer.file_size()
            except (OSError, ValueError):
                size = 0
        return self._closed_bytes + size

    # -- the service's angle records -------------------------------------------------------
    def write_angles(self, record: dict) -> None:
        """Append one ``angles`` record verbatim (strict JSON line), flushed at once.

        Written even after the frame recording hit its cap (a few hundred bytes per run),
        so the angle schedule of the recorded frames is never lost."""
        line = json.dumps(sanitise(record), allow_nan=False, separators=(",", ":"))
        with self._lock:
            if self._angles.closed:
                return
            try:
                self._angles.write(line + "\n")
                self._angles.flush()
            except OSError as e:  # (the first failure stays the recording's error)
                text = f"angles.jsonl not written: {e.strerror or e}"
                self.error = self.error or text
                log.error("%s", text)

    def status(self) -> dict:
        """The ``recording`` part of the health payload."""
        q = self._queue
        # live: the size as of the writer's last check (the file belongs to the writer thread)
        size = self._size if q is not None else self.bytes_written
        out = {"active": self.active, "dir": str(self.folder), "format": self.fmt,
               "frames": self.frames, "bytes": size, "files": len(self._rotated) + 1,
               "dropped": self.dropped, "error": self.error}
        if q is not None:
            out["queue"] = {"depth": q.qsize(), "size": self.queue_size, "queued": self.queued,
                            "max_depth": self.max_depth, "overflow": self.overflow}
        return out

    def stop(self, *, angles: bool | None = None) -> None:
        """Stop recording frames (the queued ones written first) and — unless ``angles`` is
        False (by default: unless :attr:`keep_angles_open`), when the service still writes the
        results of the last windows (it then calls :meth:`close_angles`) — close
        angles.jsonl."""
        if angles is None:
            angles = not self.keep_angles_open
        if self._writer is not None:
            assert self._queue is not None  # the writer thread is made with its queue
            try:  # the frames still queued are written first
                self._queue.put(None, timeout=WRITER_STOP_S)
            except queue.Full:
                pass
            self._writer.join(WRITER_STOP_S)
            if self._writer.is_alive():  # a stalled disk: leave it, do not hang the shutdown
                self.error = self.error or (f"recording writer stalled at shutdown; "
                                            f"{self._queue.qsize()} frames not written")
                log.error("%s", self.error)
                with self._lock:
                    if not self._angles.closed:
                        self._angles.close()
                return
            self._writer = None
        with self._io_lock:
            self._close_frames()
        if angles:
            self.close_angles()

    def close_angles(self) -> None:
        with self._lock:
            if not self._angles.closed:
                self._angles.close()


def recorded_config_raw(folder: str | Path) -> dict | None:
    """The effective configuration a recording folder holds (None if it has none)."""
    from rsra.config.rig import ConfigError

    p = Path(folder) / CONFIG_FILE
    if not p.is_file():
        return None
    try:
        with open(p, encoding="utf-8") as f:
            raw = json.load(f)
    except (ValueError, UnicodeDecodeError) as e:  # cut short, damaged
        raise ConfigError("<file>", str(p), f"not valid JSON ({e}): cut short or damaged",
                          "give the rig config the recording was made with (--config), or "
                          "repair the file") from None
    if not isinstance(raw, dict):
        raise ConfigError("<file>", str(p), "not a recorded configuration (not a JSON object)",
                          "give the rig config the recording was made with (--config)")
    return raw


def recorded_config(folder: str | Path) -> RigConfig | None:
    """The recording's configuration as a RigConfig (EDS paths relative to the folder)."""
    from rsra.daq.rigmodel import parse_rig

    raw = recorded_config_raw(folder)
    if raw is None:
        return None
    return parse_rig(raw, source=str(Path(folder) / CONFIG_FILE), base_dir=Path(folder))


