"""What decides whether a recording's outputs are up to date (docs/user-guide.md "Campaigns").

A recording's output key is the hash of

* its **content**: every file the replay reads (the frame files and ``angles.jsonl``, the
  recorded angle schedule), each by its bytes;
* the **effective rig**: the recording's own ``config.json`` (or ``--config``), with each
  EDS file by its bytes instead of its path;
* the **software**: rsra's version and the build of the compiled hub kernel (the bytes of the
  extension module, or ``none``);
* the **schema version** of the dataset (:data:`SCHEMA_VERSION`) and the **options**.

Content hashes are cached in the dataset (``_cache/content.json``) by the file's resolved
path, size, modification time (``st_mtime_ns``) and inode: an unchanged file is never read
again, so planning a re-run of an unchanged campaign reads metadata only.
"""
from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from rsra.daq.bus.recorder import ANGLES_FILE, CONFIG_FILE, recorded_config_raw
from rsra.daq.bus.replay import expand
from rsra.daq.runtime.persistence import write_text_atomic

#: the layout and the columns of the dataset: a change re-runs every recording
SCHEMA_VERSION = 1
CACHE_MAX = 200_000  # content-hash cache entries kept (the most recent)
CHUNK = 1 << 20


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def canonical(obj: Any) -> str:
    """JSON text of ``obj`` that is the same for equal data (sorted keys, no spaces)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


class HashCache:
    """sha256 of files, cached by (resolved path, size, st_mtime_ns, st_ino)."""

    def __init__(self, path: Path | None):
        #: the cache file (None: in memory only)
        self.path = path
        #: resolved path -> [size, mtime_ns, inode, sha256]
        self.entries: dict[str, list] = {}
        #: files read (hashed) in this run
        self.read = 0
        self._changed = False
        if path is not None and path.is_file():
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
                if isinstance(data, dict):
                    self.entries = {k: v for k, v in data.items()
                                    if isinstance(v, list) and len(v) == 4}
            except (OSError, ValueError):
                self.entries = {}  # a damaged cache is only slower

    def file(self, p: Path) -> str:
        real = os.path.realpath(p)
        st = os.stat(real)
        stamp = [st.st_size, st.st_mtime_ns, st.st_ino]
        hit = self.entries.get(real)
        if hit is not None and hit[:3] == stamp:
            return str(hit[3])
        h = hashlib.sha256()
        with open(real, "rb") as f:
            while chunk := f.read(CHUNK):
                h.update(chunk)
        self.read += 1
        self.entries.pop(real, None)  # (re-inserted last: the most recent are kept)
        self.entries[real] = [*stamp, h.hexdigest()]
        self._changed = True
        return h.hexdigest()

    def save(self) -> None:
        if self.path is None or not self._changed:
            return
        keep = dict(list(self.entries.items())[-CACHE_MAX:])
        self.path.parent.mkdir(exist_ok=True)
        write_text_atomic(self.path, json.dumps(keep))
        self._changed = False


def content_files(source: Path) -> list[Path]:
    """The files of a recording its replay reads: frame files, and the angle schedule."""
    files = expand([source])
    if source.is_dir() and (source / ANGLES_FILE).is_file():
        files.append(source / ANGLES_FILE)
    return files


def content_hash(source: Path, cache: HashCache) -> str:
    h = hashlib.sha256()
    for f in content_files(source):
        h.update(f.name.encode() + b"\0" + cache.file(f).encode() + b"\0")
    return h.hexdigest()


def config_hash(raw: dict | None, eds: Iterable[Path], cache: HashCache) -> str:
    """The effective rig: its configuration (as recorded or loaded) with the EDS files by
    content (their paths differ between a recording folder and the packaged rig)."""
    raw = dict(raw or {})
    nodes = raw.get("nodes")
    if isinstance(nodes, list):
        raw["nodes"] = [{k: v for k, v in n.items() if k != "eds"} if isinstance(n, dict) else n
                        for n in nodes]
    eds_hashes = sorted({cache.file(p) for p in eds})
    return _sha(canonical({"config": raw, "eds": eds_hashes}).encode())


def recording_config_hash(source: Path, config: str | None, cache: HashCache,
                          loaded: dict[str, str]) -> str:
    """The config hash of a recording's effective rig (:func:`rsra.daq.bus.replay.config_for`'s
    choice: ``--config``, else the folder's ``config.json``, else the packaged rig), without
    parsing the EDS files; ``loaded`` caches the hash of a rig file given by path."""
    if config is None and source.is_dir() and (source / CONFIG_FILE).is_file():
        raw = recorded_config_raw(source)
        eds = [(source / n["eds"]) for n in (raw or {}).get("nodes", [])
               if isinstance(n, dict) and isinstance(n.get("eds"), str)]
        return config_hash(raw, eds, cache)
    name = config or ""
    if name not in loaded:
        from rsra.daq.rigmodel import load_rig

        cfg = load_rig(config)
        loaded[name] = config_hash(cfg.effective(), [n.eds for n in cfg.nodes], cache)
    return loaded[name]


def software_version() -> str:
    """rsra's version and the compiled hub kernel's build (the extension's bytes)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("rsra")
    except PackageNotFoundError:
        v = "unknown"
    try:
        from rsra.daq import _hubkernel

        kernel = _sha(Path(_hubkernel.__file__ or "").read_bytes())[:16]
    except (ImportError, OSError):
        kernel = "none"
    return f"{v}+kernel.{kernel}"


def output_key(content: str, config: str, software: str, options: dict) -> str:
    from rsra.daq.campaign.products import PRODUCTS

    # the products a task makes are part of the layout: a product added re-runs every one
    schema = [SCHEMA_VERSION, [p.name for p in PRODUCTS]]
    return _sha(canonical({"content": content, "config": config, "software": software,
                           "schema": schema, "options": options}).encode())[:32]


def recording_id(source: Path) -> str:
    """A stable, non-numeric id for a recording: its name (letters, digits, ``-_.``) and 8 hex
    digits of its resolved path (two recordings of one name in two folders differ)."""
    import re

    real = os.path.realpath(source)
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(real).name)[:40].strip(".") or "rec"
    if not name[0].isalpha():
        name = "r" + name
    return f"{name}-{_sha(real.encode())[:8]}"


def sources_of(paths: Sequence[str | Path]) -> list[Path]:
    """Recordings named on the command line: a recording folder (it holds frames.*) or a
    log file is one recording; a folder of recordings gives each recording in it (sorted)."""
    from rsra.daq.bus.recorder import frame_files
    from rsra.daq.bus.replay import LOG_SUFFIXES

    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir() and not frame_files(p):
            inner = sorted(q for q in p.iterdir()
                           if (q.is_dir() and frame_files(q)) or
                           (q.is_file() and {s.lower() for s in q.suffixes} & {*LOG_SUFFIXES}))
            out.extend(inner if inner else [p])  # (an empty folder: refused by expand)
        else:
            out.append(p)
    seen: dict[str, Path] = {}
    for p in out:
        seen.setdefault(os.path.realpath(p), p)
    return list(seen.values())
