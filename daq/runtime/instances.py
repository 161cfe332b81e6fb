"""Which rsra services publish, and whose telemetry a viewer shows (docs/telemetry.md,
`<prefix>/alive/…`).

Every service declares, beside its `<prefix>/alive` token, a Zenoh liveliness token whose key
says who it is: ``<prefix>/alive/<rig>/<host>/<pid>/<started>`` (``started``: UTC,
``20261207T210800Z``). A viewer asks ``**/alive/*/*/*/*`` for the services its session
reaches, picks one (``rsra listen --rig NAME``, or the only one), names it, and hears of it
stopping (the token's DELETE). A service that finds another's token under its own prefix
refuses to start: two processes never publish into one stream.
"""
from __future__ import annotations

import os
import re
import socket
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

#: the liveliness keys of every instance a session reaches
ALIVE_QUERY = "**/alive/*/*/*/*"
STARTED_FORMAT = "%Y%m%dT%H%M%SZ"
_CHUNK = re.compile(r"[^A-Za-z0-9._-]+")
LOOKUP_TIMEOUT_S = 1.0  # the liveliness query at a start: tokens of reached peers answer at once


def _chunk(text: str) -> str:
    """A key chunk (no `/`, `*`, `$`, `#`, `?`, spaces): other characters become `_`."""
    return _CHUNK.sub("_", text).strip("_") or "_"


@dataclass(frozen=True)
class RigInstance:
    """One running service as its liveliness key says."""

    prefix: str
    rig: str
    host: str
    pid: int
    started: str  # STARTED_FORMAT, UTC

    @property
    def key(self) -> str:
        return f"{self.prefix}/alive/{self.rig}/{self.host}/{self.pid}/{self.started}"

    def describe(self) -> str:
        try:
            since = time.strftime("%Y-%m-%d %H:%M:%S UTC",
                                  time.strptime(self.started, STARTED_FORMAT))
        except ValueError:
            since = self.started
        return (f"rig {self.rig} on {self.prefix} — host {self.host}, pid {self.pid}, "
                f"since {since}")


def this_instance(prefix: str, rig: str, now: float | None = None) -> RigInstance:
    started = time.strftime(STARTED_FORMAT, time.gmtime(time.time() if now is None else now))
    return RigInstance(prefix=prefix, rig=_chunk(rig), host=_chunk(socket.gethostname()),
                       pid=os.getpid(), started=started)


def parse(key: str) -> RigInstance | None:
    """The instance a liveliness key names, None for any other key."""
    parts = str(key).split("/")
    if len(parts) < 6 or parts[-5] != "alive" or not parts[-2].isdigit():
        return None
    prefix = "/".join(parts[:-5])
    if not prefix:
        return None
    return RigInstance(prefix=prefix, rig=parts[-4], host=parts[-3], pid=int(parts[-2]),
                       started=parts[-1])


def publishing(session: Any, key_expr: str = ALIVE_QUERY,
               timeout: float = LOOKUP_TIMEOUT_S) -> list[RigInstance]:
    """The instances the session reaches (their liveliness tokens), in a stable order."""
    found = set()
    for reply in session.liveliness().get(key_expr, timeout=timeout):
        ok = getattr(reply, "ok", None)
        inst = parse(str(ok.key_expr)) if ok is not None else None
        if inst is not None:
            found.add(inst)
    return sorted(found, key=lambda i: (i.prefix, i.rig, i.host, i.pid, i.started))


def choose(instances: Iterable[RigInstance], rig: str | None = None,
           prefix: str | None = None) -> tuple[RigInstance | None, str | None]:
    """The instance a viewer shows: by ``rig`` name or ``prefix`` when given, else the only
    one. Returns (the instance, None), or (None, why not) — nothing publishing, none of that
    name, or several to choose from (each listed)."""
    inst = list(instances)
    pick = [i for i in inst if (rig is None or i.rig == rig)
            and (prefix is None or i.prefix == prefix)]
    if len(pick) == 1:
        return pick[0], None
    listing = "; ".join(i.describe() for i in inst)
    if not inst:
        return None, "no rig publishing"
    if not pick:
        want = f"rig {rig}" if rig is not None else f"prefix {prefix}"
        return None, f"no {want} publishing (publishing: {listing})"
    return None, (f"{len(pick)} rigs publishing: {'; '.join(i.describe() for i in pick)} — "
                  "choose one with --rig NAME" + (" or --prefix P" if rig is not None else ""))
