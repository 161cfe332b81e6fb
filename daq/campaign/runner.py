"""The driver of a campaign: plan (what runs, what is skipped and why), run the tasks on an
engine, keep the manifest (docs/user-guide.md "Campaigns").

Only the driver writes the manifest: after each finished recording (at most once a second)
and at the end, atomically. Ctrl-C cancels what is pending, keeps what finished, and leaves
the manifest saying exactly that.
"""
from __future__ import annotations

import concurrent.futures as cf
import datetime as dt
import os
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rsra.daq.campaign import dataset as ds
from rsra.daq.campaign import keys
from rsra.daq.campaign.dataset import CampaignError

MANIFEST_EVERY_S = 1.0


@dataclass
class Item:
    """One recording of the plan."""

    recording: str
    source: Path
    action: str  # "run" | "skip" | "fail"
    why: str
    key: str = ""
    content_hash: str = ""
    config_hash: str = ""
    size: int = 0
    row: dict[str, Any] = field(default_factory=dict)


@dataclass
class Plan:
    items: list[Item]
    dataset: Path
    options: dict[str, Any]
    config: str | None
    software: str
    manifest: dict[str, dict[str, Any]]
    cache: keys.HashCache

    def of(self, action: str) -> list[Item]:
        return [i for i in self.items if i.action == action]


def make_plan(inputs: list[str], dataset: Path, config: str | None, options: dict[str, Any],
              retry_failed: bool = False) -> Plan:
    ds.check_dataset(dataset)
    for p in inputs:
        if not os.path.lexists(p):
            raise CampaignError(f"{p}: no such file or folder; fix: give recording folders, "
                                "log files, or folders holding recordings")
    if config is not None and not os.path.isfile(config):
        raise CampaignError(f"--config {config}: no such file; fix: give a rig TOML file")
    manifest = ds.read_manifest(dataset) if dataset.is_dir() else {}
    cache = keys.HashCache(dataset / ds.CACHE)
    software = keys.software_version()
    opts_text = keys.canonical(options)
    loaded: dict[str, str] = {}
    items = []
    for src in keys.sources_of(inputs):
        rid = keys.recording_id(src)
        try:
            content = keys.content_hash(src, cache)
            conf = keys.recording_config_hash(src, config, cache, loaded)
        except Exception as e:  # unreadable, not a recording, a damaged config.json
            items.append(Item(rid, src, "fail", " ".join(str(e).split())[:400]))
            continue
        key = keys.output_key(content, conf, software, options)
        size = sum(f.stat().st_size for f in keys.content_files(src))
        old = manifest.get(rid)
        item = Item(rid, src, "run", "", key, content, conf, size)
        if old is None:
            item.why = "new"
        elif old.get("key") == key and (old.get("status") == "ok" or not retry_failed):
            item.action = "skip"
            item.why = ("unchanged" if old.get("status") == "ok" else
                        "failed before, unchanged (--retry-failed runs it again)")
        else:
            item.why = _changed(old, item, software, opts_text) or "retry of a failed recording"
        items.append(item)
    return Plan(items, dataset, options, config, software, manifest, cache)


def _changed(old: dict, item: Item, software: str, opts_text: str) -> str:
    what = [name for name, a, b in (
        ("content changed", old.get("content_hash"), item.content_hash),
        ("rig changed", old.get("config_hash"), item.config_hash),
        ("software changed", old.get("rsra_version"), software),
        ("options changed", old.get("options"), opts_text)) if a != b]
    if not what and old.get("key") != item.key:
        what = ["dataset schema changed"]
    return ", ".join(what)


def _row(plan: Plan, item: Item, result: dict[str, Any] | None) -> dict[str, Any]:
    row: dict[str, Any] = {"recording": item.recording, "source": str(item.source),
           "content_hash": item.content_hash, "config_hash": item.config_hash,
           "rsra_version": plan.software, "options": keys.canonical(plan.options),
           "key": item.key,
           "processed_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")}
    if result is None:
        row.update(status="failed", reason=item.why)
    else:
        row.update({k: result.get(k) for k in (
            "status", "reason", "rig_name", "rig_fingerprint", "samples", "lost_samples",
            "accepted_runs", "wall_s", "t_start")})
    return row


def provenance(plan: Plan, item: Item) -> dict[str, str]:
    return {"rsra.source": str(item.source), "rsra.content_hash": item.content_hash,
            "rsra.config_hash": item.config_hash, "rsra.version": plan.software,
            "rsra.options": keys.canonical(plan.options),
            "rsra.schema_version": str(keys.SCHEMA_VERSION), "rsra.key": item.key}


def job_of(plan: Plan, item: Item) -> dict[str, Any]:
    return {"recording": item.recording, "source": str(item.source.resolve()),
            "dataset": str(plan.dataset.resolve()), "config": (
                None if plan.config is None else str(Path(plan.config).resolve())),
            "options": plan.options, "provenance": provenance(plan, item)}


class Runner:
    """Runs a plan's ``run`` items on an engine; ``rows`` the manifest as it stands."""

    def __init__(self, plan: Plan, progress: Any):
        self.plan = plan
        self.progress = progress
        self.rows: dict[str, dict[str, Any]] = dict(plan.manifest)
        #: recordings finished in this run (their rows), and those a task ran for
        self._finished: dict[str, dict[str, Any]] = {}
        self._finished_run: set[str] = set()
        self._written = 0.0
        self._dirty = False

    def run(self, open_engine: Any) -> int:
        plan = self.plan
        for item in plan.of("fail"):
            self.finish(item, None)
        todo = plan.of("run")
        if not todo:
            self.save(force=True)
            return 1 if plan.of("fail") else 0
        self._clean_leftovers()
        try:
            return self._run(open_engine, todo)
        except KeyboardInterrupt:
            self._clean_leftovers()  # (the workers are gone: what they left half-written)
            raise

    def _run(self, open_engine: Any, todo: list[Item]) -> int:
        plan = self.plan
        with open_engine() as engine:
            self.progress.start(len(todo), sum(i.size for i in todo), engine.describe)
            self._check_visible(engine, todo)
            from rsra.daq.campaign.task import run_recording

            futures = {engine.submit(run_recording, job_of(plan, i)): i for i in todo}
            try:
                for fut in cf.as_completed(futures):
                    self.finish(futures[fut], _result(fut, futures[fut]))
            except KeyboardInterrupt:
                for fut in futures:
                    fut.cancel()
                done = {f for f in futures if f.done() and not f.cancelled()}
                for fut in done:  # finished meanwhile: kept
                    if futures[fut].recording not in self._finished:
                        self.finish(futures[fut], _result(fut, futures[fut]))
                self.save(force=True)
                self.progress.interrupted(len(todo) - len(self._finished_run))
                raise
        self.save(force=True)
        self._clean_leftovers()  # (a worker that died left its task's files half-written)
        return 1 if any(r.get("status") == "failed" for r in self._finished.values()) else 0

    def finish(self, item: Item, result: dict[str, Any] | None) -> None:
        row = _row(self.plan, item, result)
        if row["status"] != "ok":  # a failed recording has no rows in the dataset
            ds.remove_recording(self.plan.dataset, item.recording)
        else:
            ds.remove_recording(self.plan.dataset, item.recording,
                                keep=(result or {}).get("tables", ()))
        self.rows[item.recording] = row
        self._finished[item.recording] = row
        if result is not None:
            self._finished_run.add(item.recording)
        self._dirty = True
        self.progress.done(item, row)
        self.save()

    def save(self, force: bool = False) -> None:
        now = time.monotonic()
        if self._dirty and (force or now - self._written >= MANIFEST_EVERY_S):
            self.plan.dataset.mkdir(parents=True, exist_ok=True)
            ds.write_manifest(self.plan.dataset, self.rows.values())
            self._written, self._dirty = now, False
        if force:
            self.plan.cache.save()

    def _check_visible(self, engine: Any, todo: list[Item]) -> None:
        paths = [str(self.plan.dataset.resolve())] + [str(i.source.resolve()) for i in todo]
        if self.plan.config:
            paths.append(str(Path(self.plan.config).resolve()))
        missing = engine.missing(paths)
        if missing:
            worker, what = next(iter(missing.items()))
            more = f" (and {len(missing) - 1} more workers)" if len(missing) > 1 else ""
            raise CampaignError(f"worker {worker}{more} cannot see {what[0]}"
                                f"{f' and {len(what) - 1} more paths' if len(what) > 1 else ''}"
                                "; fix: put the recordings and --dataset on storage every "
                                "worker mounts at the same path")

    def _clean_leftovers(self) -> None:
        """Staging folders and temporary part files of tasks killed in an earlier run
        (their names are ours: ``.<recording>.<random>`` folders, persistence's temp names)."""
        from rsra.daq.runtime.persistence import own_temp_pid

        root = self.plan.dataset
        if not root.is_dir():
            return
        ids = {i.recording for i in self.plan.items}
        for p in root.iterdir():
            m = re.fullmatch(r"\.(.+)\.[A-Za-z0-9_]{8}", p.name)
            if p.is_dir() and m and m.group(1) in ids:
                shutil.rmtree(p, ignore_errors=True)
        for table in ds.tables_of(root):
            for part in (root / table).glob("recording=*"):
                for f in part.iterdir():
                    if own_temp_pid(f.name, ds.PART) is not None:
                        f.unlink(missing_ok=True)


def _result(fut: cf.Future, item: Item) -> dict[str, Any]:
    try:
        return fut.result()
    except cf.CancelledError:
        return {"status": "failed", "reason": "cancelled"}
    except Exception as e:  # the worker died twice (KilledWorker), or the pool broke
        why = " ".join(str(e).split())[:200] or type(e).__name__
        return {"status": "failed",
                "reason": f"{type(e).__name__}: {why} (a worker died running it twice: out "
                "of memory? run it alone with --workers 1)"}
