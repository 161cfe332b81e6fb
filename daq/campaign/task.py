"""The per-recording task (runs on a worker): paths and options in, files written, a small
summary out. Never raises for a recording that cannot be processed: its summary says
``failed`` with one line (an exception of ours is not retried; a worker that dies is)."""
from __future__ import annotations

import logging
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any


def run_recording(job: dict[str, Any]) -> dict[str, Any]:
    """``job``: recording, source, dataset, config (or None), options, provenance (JSON-ready
    strings). Returns the manifest row's fields the task knows."""
    rsra_log = logging.getLogger("rsra")
    level = rsra_log.level
    rsra_log.setLevel(logging.ERROR)  # a worker's log is not the user's (restored below:
    try:  # a task run in the caller's process — a bench, a test — leaves its logging as it was)
        return _run_recording(job)
    finally:
        rsra_log.setLevel(level)


def _run_recording(job: dict[str, Any]) -> dict[str, Any]:
    t0 = time.perf_counter()
    out: dict[str, Any] = {"recording": job["recording"], "status": "ok", "reason": None}
    staging = Path(tempfile.mkdtemp(prefix=f".{job['recording']}.", dir=job["dataset"]))
    ctx = None
    try:
        ctx = _context(job, staging)
        from rsra.daq.campaign.products import PRODUCTS, write_table

        products = [p for p in PRODUCTS if p.wanted is None or p.wanted(ctx.options)]
        for product in products:
            if product.prepare is not None:
                product.prepare(ctx)
        for product in products:
            result = product.build(ctx)
            if result is not None:
                write_table(ctx, product.name, result)
        out["tables"] = ctx.commit()
        out.update(ctx.stats)
        out["rig_name"] = ctx.cfg.rig_name
        out["rig_fingerprint"] = ctx.metadata["rsra.rig_fingerprint"]
    except Exception as e:  # of ours or of the data: this recording fails, one line
        if ctx is not None:
            ctx.discard()
        out["status"] = "failed"
        out["reason"] = _one_line(e)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    out["wall_s"] = time.perf_counter() - t0
    return out


def _context(job: dict[str, Any], staging: Path):
    from rsra.daq.bus.replay import config_for, expand, read_frames
    from rsra.daq.campaign.keys import canonical
    from rsra.daq.campaign.products import ProductContext
    from rsra.daq.campaign.replay import RecordingFailed
    from rsra.daq.runtime.posterior_file import rig_of

    source = Path(job["source"])
    try:
        paths = expand([source])
        cfg = config_for([source], job.get("config"))
        first = next(read_frames(paths), None)
    except Exception as e:  # a recording that cannot be read or configured
        raise RecordingFailed(_one_line(e)) from None
    fingerprint = canonical(rig_of(cfg))
    metadata = {**job["provenance"], "rsra.recording": job["recording"],
                "rsra.rig": cfg.rig_name, "rsra.rig_fingerprint": fingerprint}
    ctx = ProductContext(source=source, paths=paths, cfg=cfg, options=job["options"],
                         staging=staging, dataset=Path(job["dataset"]),
                         recording=job["recording"], metadata=metadata)
    ctx.stats["t_start"] = None if first is None else float(first.timestamp)
    return ctx


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    if type(e).__module__.split(".")[0] not in ("rsra", "builtins"):
        text = f"{type(e).__name__}: {text}"
    return text[:400]


def check_visible(paths: list[str]) -> list[str]:
    """Of ``paths``, those this worker cannot see (the cluster check before a campaign)."""
    import os

    return [p for p in paths if not os.path.exists(p)]
