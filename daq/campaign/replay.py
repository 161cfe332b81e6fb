"""The one seam through which a campaign replays a recording: :func:`replay_to_tables`.

It runs the service's replay path as a function in this process (the same records as
``rsra replay --out`` and ``rsra export``), pushes every published record into the
:class:`~rsra.daq.analysis.export.ParquetTables` of the recording, and returns what the
manifest needs. A faster replay path goes behind this one function.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import orjson

from rsra.config.rig import RigConfig
from rsra.daq.analysis.export import ParquetTables


class RecordingFailed(RuntimeError):
    """The recording cannot be processed (one line naming it and the fix): its row says
    ``failed``, the other recordings go on."""


def replay_to_tables(cfg: RigConfig, paths: Sequence[str | Path], tables: ParquetTables,
                     options: dict[str, Any],
                     observers: Sequence[Callable[[Any], None]] = (),
                     sinks: Sequence[Callable[[str, dict], None]] = ()) -> dict[str, Any]:
    """Replay ``paths`` (one recording) into ``tables``, every assembled sample shown to
    ``observers`` and every published record to ``sinks`` too; returns samples, lost samples, and accepted identification runs."""
    from can.io.blf import BLFParseError

    from rsra.config.rig import ConfigError
    from rsra.daq.jsonout import dumps
    from rsra.daq.runtime.service import Service, ServiceOptions
    from rsra.estimator.posterior import PosteriorFileError

    stats = {"accepted_runs": 0}

    def sink(key: str, payload: dict) -> None:
        # through the JSON text, as `rsra export` reads it: the same values, bit for bit
        # (orjson parses to the same objects as the json module, a few times faster)
        rec = orjson.loads(dumps(payload))
        if key == "angles" and rec.get("accepted") is True:
            stats["accepted_runs"] += 1
        if key in tables.schemas:
            tables.add(key, rec)

    service = Service(cfg, ServiceOptions(replay=[str(p) for p in paths], zenoh=False,
                                          recompute=bool(options.get("recompute")),
                                          identification=not options.get("no_identification")))
    service.add_sink(sink)
    for observe in observers:
        service.add_sample_observer(observe)
    for extra in sinks:
        service.add_sink(extra)
    try:
        summary = service.run()
    except (PosteriorFileError, ConfigError) as e:
        raise RecordingFailed(" ".join(str(e).split())) from None
    except (ValueError, OSError, BLFParseError) as e:  # a corrupt or truncated log file
        why = " ".join(str(e).split())
        raise RecordingFailed(f"cannot read the recording: {why}" + (
            "" if "fix:" in why else "; fix: give an undamaged recording")) from None
    return {**stats, "samples": _int(summary, "samples"),
            "lost_samples": _int(summary, "lost")}


def _int(summary: Any, name: str) -> int | None:
    v = summary.get(name) if isinstance(summary, dict) else None
    return int(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None
