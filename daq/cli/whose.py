"""Which service a viewer shows (`rsra listen`, `rsra web`): ``--prefix``, ``--rig NAME``, or
the only rig publishing, from the instances registry (daq.runtime.instances)."""
from __future__ import annotations

import time
from typing import Any

REDISCOVER_S = 2.0  # while no rig is chosen, look for one this often


class Whose:
    """Which service the view shows (daq.runtime.instances): ``--prefix``, ``--rig NAME``, or
    the only rig publishing; several without a choice are a usage error listing them; none
    yet: the config's prefix, looked for again until one appears. Its liveliness token's
    DELETE says it stopped."""

    def __init__(self, session: Any, default_prefix: str, prefix: str | None,
                 rig: str | None) -> None:
        self._session = session
        self._default = default_prefix
        self._want_prefix, self._want_rig = prefix, rig
        self._root = (prefix or default_prefix).split("/")[0]
        #: the prefix subscribed to (None: a --rig not found yet)
        self.prefix: str | None = None
        #: the service shown, when its token was found
        self.instance: Any = None
        #: why no service is named (nothing publishing, none of that name)
        self.why: str | None = None
        self.stopped: str | None = None  # the UTC time its token went away
        self._alive: Any = None
        self._looked = 0.0

    def discover(self, now: float) -> None:
        """Look for the services publishing; raise UsageError when several could be meant."""
        from rsra.daq.cli.options import UsageError
        from rsra.daq.runtime.instances import choose, publishing

        self._looked = now
        found = publishing(self._session, f"{self._root}/**/alive/*/*/*/*")
        inst, why = choose(found, self._want_rig, self._want_prefix)
        if inst is None and found and self._want_rig is None and self._want_prefix is None:
            raise UsageError(f"{why}")
        self.why = why
        if inst is not None and (self.prefix is None or inst.prefix == self.prefix):
            self._follow(inst)
        elif self.prefix is None and self._want_rig is None:
            self.prefix = self._want_prefix or self._default

    def _follow(self, inst: Any) -> None:
        import zenoh

        self.instance, self.prefix, self.why, self.stopped = inst, inst.prefix, None, None
        if self._alive is None:
            self._alive = self._session.liveliness().declare_subscriber(
                f"{inst.prefix}/alive/*/*/*/*", handler=zenoh.handlers.RingChannel(64))

    def poll(self, now: float) -> None:
        """Hear the service stop (or another start on the prefix); look again while none."""
        import zenoh

        from rsra.daq.runtime.instances import parse

        while self._alive is not None and (s := self._alive.handler.try_recv()) is not None:
            inst = parse(str(s.key_expr))
            if inst is not None:
                self._hear(s.kind == zenoh.SampleKind.PUT, inst)
        if self.instance is None and now - self._looked >= REDISCOVER_S:
            self.discover(now)

    def _hear(self, put: bool, inst: Any) -> None:
        """A liveliness token of the prefix: ours gone (stopped), or another one started."""
        if not put and inst == self.instance:
            self.stopped = time.strftime("%H:%M:%S UTC", time.gmtime())
        elif put and inst != self.instance:
            self.instance, self.stopped = inst, None

    def title(self) -> str:
        if self.instance is not None:
            return self.instance.describe() + (f" — stopped at {self.stopped}"
                                               if self.stopped else "")
        return f"{self.why or 'no rig publishing'} — waiting on {self.prefix or '(no prefix)'}"

    def close(self) -> None:
        if self._alive is not None:
            self._alive.undeclare()
            self._alive = None
