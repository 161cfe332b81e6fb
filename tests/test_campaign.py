"""`rsra campaign` (daq/campaign): the dataset row for row what `rsra export --parquet` gives,
the manifest and its provenance, each incremental rule, failures isolated, a killed worker
retried, Ctrl-C, a hand-started Dask cluster on loopback, and `campaign compare`."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from helpers_net import free_tcp_port

from rsra.daq.campaign import keys
from rsra.daq.campaign.dataset import MANIFEST, read_manifest
from rsra.daq.campaign.runner import make_plan
from rsra.daq.cli import main

TABLES = ("hub_loads", "channels", "innovations", "angles", "health")
VOLATILE = ("wall_s", "processed_utc")  # manifest columns that differ between two runs
BIN = Path(sys.executable).parent


def _record(folder: Path, seed: int, duration: str = "2", *more: str) -> Path:
    assert main(["run", "--sim", "ground-test", "--speed", "max", "--duration", duration,
                 "--seed", str(seed), "--record", str(folder),
                 "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", *more]) == 0
    return folder


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> Path:
    """A folder of three short ground recordings."""
    d = tmp_path_factory.mktemp("campaign") / "recs"
    d.mkdir()
    for seed in (1, 2, 3):
        _record(d / f"g{seed}", seed)
    return d


@pytest.fixture(scope="module")
def dataset(recordings, tmp_path_factory) -> Path:
    """The default engine (a Dask local cluster, 2 workers) over the three recordings."""
    ds = tmp_path_factory.mktemp("ds") / "ds"
    assert main(["campaign", "run", "--dataset", str(ds), "--workers", "2",
                 str(recordings)]) == 0
    return ds


def _rid(src: Path) -> str:
    return keys.recording_id(src)


def _manifest(ds: Path) -> dict[str, dict]:
    return {k: {c: v for c, v in r.items() if c not in VOLATILE}
            for k, r in read_manifest(ds).items()}


def _tables(ds: Path) -> dict[tuple[str, str], pa.Table]:
    out = {}
    for table in TABLES:
        for part in sorted((ds / table).glob("recording=*")):
            out[table, part.name] = pq.read_table(part / "part.parquet")
    return out


def test_the_dataset_is_row_for_row_the_export_of_each_recording(recordings, dataset,
                                                                 tmp_path):
    for rec in sorted(recordings.iterdir()):
        out = tmp_path / rec.name
        assert main(["export", str(rec), "--parquet", str(out)]) == 0
        for f in out.glob("*.parquet"):
            exported = pq.read_table(f)
            part = dataset / f.stem / f"recording={_rid(rec)}" / "part.parquet"
            ours = pq.read_table(part)
            assert ours.schema.remove_metadata().equals(exported.schema.remove_metadata())
            assert ours.to_pylist() == exported.to_pylist(), (rec.name, f.stem)


def test_the_manifest_and_the_provenance_of_every_file(recordings, dataset):
    m = read_manifest(dataset)
    assert sorted(m) == sorted(_rid(r) for r in recordings.iterdir())
    for rid, row in m.items():
        assert row["status"] == "ok" and row["reason"] is None
        assert row["samples"] == 400 and row["lost_samples"] == 0
        assert not rid.split("-")[0].isdigit() and row["rig_name"] == "bench"
        assert json.loads(row["rig_fingerprint"])["angle_names"][0] == "delta_A"
        assert row["t_start"] > 1e9 and row["wall_s"] > 0
        meta = pq.read_schema(dataset / "hub_loads" / f"recording={rid}" / "part.parquet"
                              ).metadata
        assert meta[b"rsra.content_hash"].decode() == row["content_hash"]
        assert meta[b"rsra.version"].decode() == row["rsra_version"]
        assert meta[b"rsra.recording"].decode() == rid
    # every engine reads it with a glob: DuckDB (the user guide's query), pyarrow.dataset
    import duckdb
    import pyarrow.dataset as pads

    q = (f"SELECT recording, sqrt(avg(\"H.Z\"^2)) FROM read_parquet("
         f"'{dataset}/hub_loads/*/*.parquet', hive_partitioning = true) GROUP BY 1")
    assert len(duckdb.sql(q).fetchall()) == 3
    d = pads.dataset(dataset / "hub_loads", format="parquet", partitioning="hive")
    assert d.to_table(columns=["recording"]).num_rows == 1200


def test_an_unchanged_rerun_submits_nothing_and_writes_nothing(recordings, dataset,
                                                               monkeypatch, capsys):
    before = {p: p.stat().st_mtime_ns for p in dataset.rglob("*") if p.is_file()}
    import rsra.daq.campaign.engine as engine

    def refuse(*a, **k):
        raise AssertionError("an engine was opened")

    monkeypatch.setattr(engine, "open_engine", refuse)
    assert main(["campaign", "run", "--dataset", str(dataset), str(recordings)]) == 0
    assert "nothing to do" in capsys.readouterr().out
    after = {p: p.stat().st_mtime_ns for p in dataset.rglob("*") if p.is_file()}
    assert after == before
    plan = make_plan([str(recordings)], dataset, None, {"recompute": False,
                                                         "no_identification": False})
    assert [i.action for i in plan.items] == ["skip"] * 3
    assert plan.cache.read == 0  # the content of an unchanged file is not read again


def test_each_incremental_rule(recordings, dataset, tmp_path, monkeypatch):
    opts = {"recompute": False, "no_identification": False}
    ds = tmp_path / "ds"
    shutil.copytree(dataset, ds)
    # a new recording runs alone
    new = _record(tmp_path / "g9", 9)
    plan = make_plan([str(recordings), str(new)], ds, None, opts)
    assert {i.recording: (i.action, i.why) for i in plan.items if i.action == "run"} == {
        _rid(new): ("run", "new")}
    # a changed option, rig or software runs all
    plan = make_plan([str(recordings)], ds, None, {**opts, "recompute": True})
    assert {(i.action, i.why) for i in plan.items} == {("run", "options changed")}
    rig = tmp_path / "rig.toml"
    rig.write_text('[telemetry]\ninnovations_hz = 10.0\n')
    plan = make_plan([str(recordings)], ds, str(rig), opts)
    assert {(i.action, i.why) for i in plan.items} == {("run", "rig changed")}
    monkeypatch.setattr(keys, "software_version", lambda: "9.9.9+kernel.x")
    plan = make_plan([str(recordings)], ds, None, opts)
    assert {(i.action, i.why) for i in plan.items} == {("run", "software changed")}
    monkeypatch.undo()
    # changed content (same size and name) runs that one; the cache sees the new mtime
    rec = tmp_path / "copy"
    shutil.copytree(recordings / "g1", rec)
    assert main(["campaign", "run", "--dataset", str(ds), "--pool", "--workers", "1",
                 str(rec)]) == 0
    frames = rec / "frames.log"
    text = frames.read_text()  # one hex digit of the last frame's data changed
    frames.write_text(text[:-2] + ("0" if text[-2] != "0" else "1") + "\n")
    plan = make_plan([str(rec)], ds, None, opts)
    assert [(i.action, i.why) for i in plan.items] == [("run", "content changed")]
    assert plan.cache.read == 1


def test_a_corrupt_recording_fails_in_one_line_and_the_rest_complete(recordings, tmp_path,
                                                                     capsys):
    bad = tmp_path / "bad"
    shutil.copytree(recordings / "g1", bad)
    lines = (bad / "frames.log").read_text().splitlines(keepends=True)
    lines[len(lines) // 2] = "(1700000000.000000) can0 this-is-not-a-frame\n"
    (bad / "frames.log").write_text("".join(lines))
    garbage = tmp_path / "garbage.blf"
    garbage.write_bytes(b"\x00not a blf file" * 10)
    ds = tmp_path / "ds"
    rc = main(["campaign", "run", "--dataset", str(ds), "--pool", "--workers", "2",
               str(recordings / "g2"), str(bad), str(garbage)])
    assert rc == 1
    m = read_manifest(ds)
    assert m[_rid(recordings / "g2")]["status"] == "ok"
    for src in (bad, garbage):
        row = m[_rid(src)]
        assert row["status"] == "failed" and "\n" not in row["reason"]
        assert str(src.name) in row["reason"] and "fix:" in row["reason"]
        assert not any(ds.glob(f"*/recording={_rid(src)}"))  # no rows of a failed recording
    assert "failed" in capsys.readouterr().out
    assert not [p for p in ds.rglob(".*") if p.name != ".rsra"]  # no temporary left


def test_bad_usage_is_one_line_and_exit_2(recordings, tmp_path, capsys):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    assert main(["campaign", "run", "--dataset", str(foreign), str(recordings)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--dataset" in err and "fix:" in err
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]
    assert main(["campaign", "run", "--dataset", str(tmp_path / "d"),
                 str(tmp_path / "nothing")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
    assert main(["campaign", "run", "--dataset", str(recordings / "g1"),
                 str(recordings)]) == 2  # into an input recording
    capsys.readouterr()


def _changed_copy(src: Path, dst: Path, rid: str, sigmas: float) -> None:
    shutil.copytree(src, dst)
    part = dst / "hub_loads" / f"recording={rid}" / "part.parquet"
    t = pq.read_table(part)
    z = t.column("H.Z").to_pylist()
    s = t.column("sigma_filter.Z").to_pylist()
    k = len(z) // 2
    z[k] = z[k] + sigmas * s[k]
    t = t.set_column(t.schema.get_field_index("H.Z"), "H.Z", pa.array(z, pa.float64()))
    pq.write_table(t, part)


def test_compare_passes_an_unchanged_campaign_and_catches_an_injected_change(
        recordings, dataset, tmp_path, capsys):
    assert main(["campaign", "compare", str(dataset), str(dataset)]) == 0
    rid = _rid(recordings / "g2")
    _changed_copy(dataset, tmp_path / "new", rid, 5.0)
    assert main(["campaign", "compare", str(dataset), str(tmp_path / "new")]) == 1
    out = capsys.readouterr().out
    assert "REGRESSION" in out and rid in out and "hub loads moved" in out
    _changed_copy(dataset, tmp_path / "small", rid, 0.01)  # within the tolerance
    assert main(["campaign", "compare", str(dataset), str(tmp_path / "small")]) == 0


def test_status_lists_the_recordings(dataset, capsys):
    assert main(["campaign", "status", str(dataset)]) == 0
    assert "3 recordings, 3 ok, 0 failed" in capsys.readouterr().out


# -- processes: a killed worker, Ctrl-C, a cluster started by hand ------------------------
def _rsra(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([str(BIN / "rsra"), *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True, **kw)


def _children(pid: int) -> list[int]:
    out = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout
    return [int(x) for x in out.split()]


def _listening(pids) -> set[str]:
    """The addresses processes ``pids`` and their children listen on."""
    import psutil

    out = set()
    for pid in pids:
        top = psutil.Process(pid)
        for proc in (top, *top.children(recursive=True)):
            out |= {c.laddr.ip for c in proc.net_connections(kind="inet")
                    if c.status == psutil.CONN_LISTEN}
    return out


def _wait_for(cond, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


@pytest.fixture(scope="module")
def long_recording(tmp_path_factory) -> Path:
    return _record(tmp_path_factory.mktemp("long") / "long", 5, "8")


def test_a_killed_worker_is_retried_once(long_recording, tmp_path):
    ds = tmp_path / "ds"
    p = _rsra("campaign", "run", "--dataset", str(ds), "--workers", "1", str(long_recording))
    try:
        # the task has started when its staging folder appears
        _wait_for(lambda: ds.is_dir() and any(x.name.startswith(".long-") for x in
                                               ds.iterdir()), 120, "the task to start")
        # the local cluster's worker: the driver's child process (forked by its nanny),
        # not multiprocessing's resource tracker
        workers = [c for c in _children(p.pid)
                   if "resource_tracker" not in Path(f"/proc/{c}/cmdline").read_text()]
        assert workers
        os.kill(workers[0], signal.SIGKILL)
        out, _ = p.communicate(timeout=300)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert p.returncode == 0, out
    assert read_manifest(ds)[_rid(long_recording)]["status"] == "ok"
    assert not list(ds.rglob(".*"))  # what the killed task left is gone


def test_ctrl_c_keeps_the_finished_and_leaves_the_manifest_consistent(recordings,
                                                                     long_recording, tmp_path):
    ds = tmp_path / "ds"
    p = _rsra("campaign", "run", "--dataset", str(ds), "--workers", "1",
              str(recordings / "g1"), str(long_recording))
    try:
        _wait_for(lambda: (ds / MANIFEST).exists(), 180, "the first recording to finish")
        os.killpg(p.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the workers get it too
        out, _ = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert p.returncode == 130, out
    assert "interrupted" in out and "Traceback" not in out
    m = read_manifest(ds)
    assert [r["status"] for r in m.values()] == ["ok"] * len(m) and len(m) >= 1
    assert not list(ds.rglob(".*"))  # no staging folder or temporary file left
    for rid in m:  # every row's tables are there, whole
        for table in TABLES:
            pq.read_table(ds / table / f"recording={rid}" / "part.parquet")
    def none_left() -> bool:  # the cluster's processes go with it
        return not subprocess.run(["pgrep", "-s", str(p.pid)], capture_output=True,
                                  text=True).stdout.split()

    _wait_for(none_left, 30, "the cluster's processes to end")


def test_a_dask_cluster_started_by_hand_gives_the_same_dataset(recordings, dataset, tmp_path):
    sched_file = tmp_path / "scheduler.json"
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False",
           "DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": "1"}
    # as the user guide starts them ("On a cluster", one machine): --no-dashboard alone
    # still serves the scheduler's and each worker's HTTP routes on every interface
    procs = [subprocess.Popen([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1",
                               "--port", "0", "--no-dashboard", "--dashboard-address",
                               "127.0.0.1:0", "--scheduler-file", str(sched_file)],
                              env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, start_new_session=True)]
    try:
        _wait_for(sched_file.exists, 60, "the scheduler")
        for _ in range(2):
            procs.append(subprocess.Popen(
                [str(BIN / "dask"), "worker", "--scheduler-file", str(sched_file),
                 "--host", "127.0.0.1", "--nthreads", "1", "--nworkers", "1",
                 "--no-dashboard", "--dashboard-address", "127.0.0.1:0"], env=env, stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL, start_new_session=True))
        from distributed import Client

        with Client(scheduler_file=str(sched_file), timeout="30s") as c:
            c.wait_for_workers(2, timeout=60)
            addr = c.scheduler.address
        assert addr.startswith("tcp://127.0.0.1:")
        assert _listening(p.pid for p in procs) <= {"127.0.0.1"}  # loopback only
        ds = tmp_path / "ds"
        assert main(["campaign", "run", "--dataset", str(ds), "--scheduler", addr,
                     str(recordings)]) == 0
        # what each worker cannot see (the check before a campaign on a cluster)
        from rsra.daq.campaign.engine import DaskEngine

        eng = DaskEngine(Client(scheduler_file=str(sched_file), timeout="30s"))
        try:
            missing = eng.missing([str(recordings), str(tmp_path / "elsewhere")])
        finally:
            eng.close()
        assert len(missing) == 2 and all(m == [str(tmp_path / "elsewhere")]
                                         for m in missing.values())
    finally:
        for p in reversed(procs):
            os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
    assert _manifest(ds) == _manifest(dataset)
    a, b = _tables(ds), _tables(dataset)
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].equals(b[k]), k


def test_the_user_guide_queries_answer_across_recordings(dataset):
    """Every DuckDB query of docs/user-guide.md "Campaigns" runs on a dataset as written."""
    import re

    import duckdb

    text = (Path(__file__).resolve().parents[1] / "docs" / "user-guide.md").read_text()
    section = text.split("## Campaigns", 1)[1].split("\n## ", 1)[0]
    queries = re.findall(r"```sql\n(.*?)```", section, re.S)
    assert len(queries) >= 3
    recordings = set(read_manifest(dataset))
    for q in queries:
        rows = duckdb.sql(q.replace("'campaign/", f"'{dataset}/")).fetchall()
        if "UNPIVOT" in q:  # (these short recordings hold no identification run)
            continue
        assert {r[0] for r in rows} == recordings, q


def test_progress_live_bar_and_plain_lines_and_summary(tmp_path):
    import io

    from rsra.daq.campaign.progress import Progress
    from rsra.daq.campaign.runner import Item, Plan

    items = [Item("a-00000000", tmp_path / "a", "run", "new", size=10),
             Item("b-00000000", tmp_path / "b", "run", "new", size=30)]
    plan = Plan(items, tmp_path, {}, None, "v", {}, keys.HashCache(None))
    rows = {"a-00000000": {"status": "ok", "samples": 400, "wall_s": 1.0},
            "b-00000000": {"status": "failed", "reason": "bad.log:3: not a frame; fix: x"}}
    for live in (True, False):
        out = io.StringIO()
        p = Progress(out, live=live)
        p.start(2, 40, "test engine")
        for item in items:
            p.done(item, rows[item.recording])
        p.summary(plan, rows)
        text = out.getvalue()
        assert "1 failed" in text and "bad.log:3" in text and "a-00000000" in text
        if not live:
            assert "[1/2] a-00000000: ok, 400 samples" in text and "samples/s" in text


def test_campaign_calibrate_pools_the_recordings_a_campaign_run_wrote(tmp_path, capsys):
    """The whole loop of issue 47 item 6 through the dataset: `campaign run` writes each
    recording's information product; `campaign calibrate` pools them into a posterior in the
    state-file format that `rsra angles show` reads (two seeds are two aircraft: their angles
    differ, and the homogeneity test refuses to pool them)."""
    recs = tmp_path / "recs"
    recs.mkdir()
    for name in ("k4a", "k4b"):  # one aircraft (a seed draws its angles) recorded twice
        _record(recs / name, 4, "11")
    ds = tmp_path / "ds"
    assert main(["campaign", "run", "--dataset", str(ds), "--workers", "1", "--pool",
                 str(recs)]) == 0
    parts = sorted((ds / "information").glob("recording=*/part.parquet"))
    assert len(parts) == 2 and all(pq.read_table(p).num_rows >= 1 for p in parts)
    assert not (ds / "survey").exists()  # the loads survey only when asked (--survey)
    # the task derives it from its one replay (the telemetry's samples): the same table, to
    # the bit, as the recording read on its own for its known loads
    from rsra.daq.analysis.information import recording_information
    from rsra.daq.bus.replay import config_for

    for name in ("k4a", "k4b"):
        src = recs / name
        alone = recording_information(config_for([src]), src, _rid(src))
        part = pq.read_table(ds / "information" / f"recording={_rid(src)}" / "part.parquet")
        assert part.num_rows == alone.num_rows
        assert part.equals(alone.drop_columns(["recording"]).select(part.column_names))
    capsys.readouterr()
    post = tmp_path / "P.json"
    assert main(["campaign", "calibrate", "--dataset", str(ds), "--out", str(post)]) == 0
    assert post.is_file()
    assert main(["angles", "show", str(post)]) == 0
    assert "delta_A" in capsys.readouterr().out


def test_a_run_killed_before_its_manifest_leaves_a_dataset_the_next_run_takes(tmp_path):
    """A first `campaign run` killed outright (no manifest yet) leaves its lock file, task
    staging folders and temporary partition files: the next run takes the folder as the
    dataset rsra started and removes those by their names; a folder rsra never locked is
    still refused, and a file not named as ours is never touched."""
    from rsra.daq.campaign import dataset as ds
    from rsra.daq.campaign.dataset import CampaignError

    d = tmp_path / "ds"
    d.mkdir()
    with ds.DatasetLock(d):
        pass  # the killed run's lock
    part = d / "hub_loads" / "recording=r1-7b3691ef"
    stale = part / ".part.parquet.rsra-tmp.12494.chfa09yl.tmp"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"half")
    staging = d / ".r1-7b3691ef.6ri8qmot"
    staging.mkdir()
    theirs = part / "notes.txt"
    theirs.write_text("mine")
    ds.check_dataset(d)  # not refused
    with ds.DatasetLock(d):
        assert not stale.exists() and not staging.exists() and theirs.read_text() == "mine"
    other = tmp_path / "other"
    other.mkdir()
    (other / "_lock").write_text("")
    with pytest.raises(CampaignError, match="no manifest.parquet"):
        ds.check_dataset(other)
