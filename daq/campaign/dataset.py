"""The campaign dataset on disk (docs/user-guide.md "Campaigns").

::

    DIR/manifest.parquet                       one row per recording (MANIFEST_SCHEMA)
    DIR/<table>/recording=<id>/part.parquet    hub_loads, channels, innovations, angles,
                                               health, … (hive-partitioned by recording id)
    DIR/_cache/content.json                    content hashes (daq.campaign.keys)
    DIR/_lock                                  held by the one `campaign run` writing DIR

The manifest is the truth: a recording's tables are those of its ``ok`` row; only the
driver writes the manifest (atomically, after each finished recording), the tasks write
their own tables (each file under a temporary name, renamed once all are written). Names
starting with ``_`` or ``.`` are skipped by pyarrow.dataset, DuckDB's ``*/*/*.parquet``
globs and polars alike.
"""
from __future__ import annotations

import fcntl
import os
import re
import shutil
from collections.abc import Iterable
from pathlib import Path
from typing import Any

MANIFEST = "manifest.parquet"
CACHE = "_cache/content.json"
LOCK = "_lock"
PART = "part.parquet"
DATASET_TAG = "rsra.campaign"  # the manifest's schema metadata key that says rsra wrote it


class CampaignError(ValueError):
    """Bad usage of a campaign command (one line naming the input and the fix; exit 2)."""


def manifest_schema():
    import pyarrow as pa

    return pa.schema([
        ("recording", pa.string()), ("source", pa.string()), ("content_hash", pa.string()),
        ("rig_name", pa.string()), ("rig_fingerprint", pa.string()),
        ("config_hash", pa.string()), ("rsra_version", pa.string()), ("options", pa.string()),
        ("key", pa.string()), ("status", pa.string()), ("reason", pa.string()),
        ("samples", pa.int64()), ("lost_samples", pa.int64()),
        ("accepted_runs", pa.int64()), ("wall_s", pa.float64()), ("t_start", pa.float64()),
        ("processed_utc", pa.string()),
    ], metadata={DATASET_TAG: "1"})


def check_dataset(path: Path) -> None:
    """``--dataset`` must be missing, an empty folder, or a dataset rsra wrote."""
    if not path.exists():
        return
    if not path.is_dir():
        raise CampaignError(f"--dataset {path}: is not a folder; fix: give a new or empty "
                            "folder, or a campaign dataset")
    if not any(path.iterdir()):
        return
    m = path / MANIFEST
    if not m.is_file() and not started_by_rsra(path):
        raise CampaignError(f"--dataset {path}: a folder with other files and no "
                            f"{MANIFEST}; fix: give a new or empty folder, or a dataset "
                            "`rsra campaign run` wrote")
    if m.is_file():
        read_manifest(path)


#: what the lock file of a dataset `campaign run` writes says (a first run stopped before
#: its manifest leaves a dataset known by it)
LOCK_TAG = b"rsra campaign dataset\n"
_STALE_FILE = re.compile(r"^\.part\.parquet\.rsra-tmp\.\d+\.[A-Za-z0-9_]+\.tmp$")
_STALE_STAGING = re.compile(r"^\.[A-Za-z0-9_.-]+\.[A-Za-z0-9_]{8}$")


def started_by_rsra(path: Path) -> bool:
    """A folder whose lock file a `campaign run` wrote (one stopped before its manifest)."""
    try:
        with open(path / LOCK, "rb") as f:
            return f.read(len(LOCK_TAG)) == LOCK_TAG
    except OSError:
        return False


def remove_stale(path: Path) -> int:
    """Under the lock: the temporary files and staging folders of tasks that never finished
    (a run killed outright), by the names only our writers give them; returns how many."""
    n = 0
    for p in path.iterdir():
        if p.is_dir() and not p.is_symlink() and _STALE_STAGING.match(p.name):
            shutil.rmtree(p, ignore_errors=True)
            n += 1
    for table in tables_of(path):
        for part in (path / table).glob("recording=*"):
            for p in part.iterdir():
                if p.is_file() and not p.is_symlink() and _STALE_FILE.match(p.name):
                    p.unlink(missing_ok=True)
                    n += 1
    return n


def read_manifest(path: Path) -> dict[str, dict[str, Any]]:
    """recording id -> its manifest row ({} when the dataset has none yet)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    m = path / MANIFEST
    if not m.exists():
        return {}
    try:
        t = pq.read_table(m)
    except (OSError, pa.ArrowException) as e:
        raise CampaignError(f"{m}: not readable ({' '.join(str(e).split())[:120]}); fix: "
                            "give a dataset `rsra campaign run` wrote") from None
    if not t.schema.metadata or DATASET_TAG.encode() not in t.schema.metadata:
        raise CampaignError(f"{m}: not a manifest rsra wrote; fix: give a new or empty "
                            "folder, or a dataset `rsra campaign run` wrote")
    return {r["recording"]: r for r in t.to_pylist()}


def write_manifest(path: Path, rows: Iterable[dict[str, Any]]) -> None:
    """The manifest, sorted by recording id, written atomically."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from rsra.daq.runtime.persistence import AtomicOutput

    sch = manifest_schema()
    rows = sorted(rows, key=lambda r: r["recording"])
    table = pa.Table.from_pylist([{f.name: r.get(f.name) for f in sch} for r in rows],
                                 schema=sch)
    out = AtomicOutput(path / MANIFEST, "wb")
    try:
        pq.write_table(table, out.open())
        out.commit()
    finally:
        out.discard()


def partition(path: Path, table: str, recording: str) -> Path:
    return path / table / f"recording={recording}"


def tables_of(path: Path) -> list[str]:
    """The tables of a dataset (folders not starting with ``_`` or ``.``)."""
    return sorted(p.name for p in path.iterdir()
                  if p.is_dir() and not p.name.startswith(("_", ".")))


def remove_recording(path: Path, recording: str, keep: Iterable[str] = ()) -> None:
    """Remove a recording's partitions (those of tables not in ``keep``): a failed
    recording has no rows in the dataset, a re-run one none of a table it no longer has."""
    keep = set(keep)
    for table in tables_of(path):
        if table in keep:
            continue
        p = partition(path, table, recording)
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)


class DatasetLock:
    """An exclusive lock on the dataset (``DIR/_lock``, flock): one `campaign run` at a
    time writes a dataset."""

    def __init__(self, path: Path):
        self.path = path / LOCK
        self.fd: int | None = None

    def __enter__(self) -> DatasetLock:
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self.fd)
            self.fd = None
            raise CampaignError(f"--dataset {self.path.parent}: another `rsra campaign run` "
                                "is writing it; fix: wait for it to finish") from None
        os.ftruncate(self.fd, 0)
        os.pwrite(self.fd, LOCK_TAG, 0)
        remove_stale(self.path.parent)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
