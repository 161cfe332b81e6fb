"""Zenoh telemetry (docs/telemetry.md): keys, strict-JSON payloads, queryables, liveliness.

Telemetry is read-only: the service declares no subscriber, and no queryable but
`state/*`. High-rate keys use congestion control DROP (a slow viewer never stalls
acquisition; loss shows through `seq`). State queries are answered in Zenoh's callback from
cached bytes (a dict read under a lock, no service thread involved).
"""
from __future__ import annotations

import contextlib
import json
import logging
import threading
from collections.abc import Iterable
from typing import Any

import zenoh

from rsra.config.rig import TelemetryConfig
from rsra.daq import stagetiming
from rsra.daq.jsonout import dumpb, dumps
from rsra.daq.payload_guard import PayloadGuard
from rsra.daq.runtime.schema import FIELDS, json_schema

log = logging.getLogger("rsra.telemetry")

HIGH_RATE_KEYS = ("hub_loads", "channels", "innovations")
LOW_RATE_KEYS = ("angles", "health")
STATE_KEYS = ("angles", "config", "health")

# Zenoh's mode-dependent default listen endpoints (all interfaces), read from the library.
_ZENOH_DEFAULT_LISTEN = json.loads(zenoh.Config().get_json("listen/endpoints"))
# Names whose values are secrets or point at them: never published in state/config.
_SECRET_NAMES = ("password", "private_key", "secret", "zenoh_config", "dictionary_file",
                 "known_keys_file")
REMOVED = "<removed>"


def redact_secrets(obj: Any) -> Any:
    """A copy of a config tree with every secret value (passwords, key paths, the Zenoh config
    file path) replaced by "<removed>" — state/config is readable by every viewer."""
    if isinstance(obj, dict):
        return {k: (REMOVED if obj[k] not in (None, "", [], {}) and
                    any(n in str(k).lower() for n in _SECRET_NAMES) else redact_secrets(obj[k]))
                for k in obj}
    if isinstance(obj, (list, tuple)):
        return [redact_secrets(v) for v in obj]
    return obj


def zenoh_config(
    tel: TelemetryConfig,
    *,
    listen: Iterable[str] | None = None,
    connect: Iterable[str] | None = None,
    config_file: str | None = None,
) -> zenoh.Config:
    """The session config: a Zenoh config file if given (TLS, auth, ACL), else the rig's
    telemetry table. Multicast scouting stays off, and a file without listen endpoints listens
    nowhere, unless the file or config says otherwise."""
    path = config_file or tel.zenoh_config
    if path:
        return _config_from_file(path)
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(tel.mode))
    lst = list(tel.listen if listen is None else listen)
    con = list(tel.connect if connect is None else connect)
    conf.insert_json5("listen/endpoints", json.dumps(lst))
    conf.insert_json5("connect/endpoints", json.dumps(con))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(tel.multicast_scouting)))
    return conf


def _config_from_file(path: str) -> zenoh.Config:
    """A Zenoh config file (TLS, auth, ACL) with multicast scouting off and no listener
    unless it says otherwise; a file that is not one: a ConfigError naming it."""
    from rsra.config.readfile import regular_file_problem
    from rsra.config.rig import ConfigError

    problem = regular_file_problem(path)  # a FIFO would block Zenoh's read, a device never end
    if problem is not None:
        raise ConfigError("telemetry.zenoh_config", str(path), problem,
                          "give a valid Zenoh JSON5 config file")
    try:
        conf = zenoh.Config.from_file(path)
    except Exception as e:  # zenoh raises ZError with the parser's message
        raise ConfigError("telemetry.zenoh_config", str(path), f"cannot load ({e})",
                          "give a valid Zenoh JSON5 config file") from None
    # Zenoh's own defaults are multicast scouting on and, for a peer, a listener on every
    # interface (tcp/[::]:0): a file that says nothing about them gets ours instead.
    if json.loads(conf.get_json("scouting/multicast/enabled")) is None:
        conf.insert_json5("scouting/multicast/enabled", "false")
    if json.loads(conf.get_json("listen/endpoints")) == _ZENOH_DEFAULT_LISTEN:
        conf.insert_json5("listen/endpoints", "[]")
    return conf


def payload_guard() -> PayloadGuard:
    """The guard of every received payload (viewers, the web gateway), checking each key
    against the schema its exports declare (daq/runtime/schema.py)."""
    return PayloadGuard({k: json_schema(k) for k in FIELDS})


def viewer_config(connect: Iterable[str], listen: Iterable[str] = ()) -> zenoh.Config:
    """A subscriber's config: peer, connect to the given endpoints, listen nowhere by
    default, multicast scouting off."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


class TelemetryPublisher:
    """Publishes the service's records under `<prefix>/…` and answers `state/*` queries."""

    def __init__(self, session: zenoh.Session, prefix: str, effective_config: dict | None = None):
        self.session = session
        self.prefix = prefix
        self.published = dict.fromkeys(HIGH_RATE_KEYS + LOW_RATE_KEYS, 0)
        self.errors = 0
        #: state queries that carried a payload or parameters (state/* takes neither: they
        #: are ignored and the query answered as any other)
        self.bad_queries = 0
        self._pubs: dict[str, zenoh.Publisher] = {}
        # every declaration is undeclared on close, in reverse order (errors ignored: a
        # session already closed)
        self._declared = contextlib.ExitStack()
        declared = self._declare
        for key in HIGH_RATE_KEYS:
            self._pubs[key] = declared(session.declare_publisher(
                f"{prefix}/{key}", encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.DROP,
                priority=zenoh.Priority.REAL_TIME, express=True))
        for key in LOW_RATE_KEYS:
            self._pubs[key] = declared(session.declare_publisher(
                f"{prefix}/{key}", encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.BLOCK))
        self._state: dict[str, bytes] = {}
        self._state_lock = threading.Lock()
        if effective_config is not None:
            self._state["config"] = dumps(redact_secrets(effective_config)).encode()
        self._token = declared(session.liveliness().declare_token(f"{prefix}/alive"))
        # who publishes: <prefix>/alive/<rig>/<host>/<pid>/<started> (daq.runtime.instances)
        from rsra.daq.runtime.instances import this_instance

        rig = ((effective_config or {}).get("rig") or {}).get("name") or "rig"
        self.instance = this_instance(prefix, str(rig))
        self._instance_token = declared(session.liveliness().declare_token(self.instance.key))
        self._state_keys = {n: zenoh.KeyExpr(f"{prefix}/state/{n}") for n in STATE_KEYS}
        # a callback queryable: zenoh's own thread runs _answer per query, so an idle service
        # has no thread polling for queries (a 10-ms poll woke the GIL 100 times a second)
        self._queryable = declared(session.declare_queryable(f"{prefix}/state/*", self._answer))

    def _declare(self, obj: Any) -> Any:
        """Hold ``obj`` (publisher, token, queryable) for undeclaring on close."""
        def undeclare() -> None:
            try:
                obj.undeclare()
            except Exception:  # a closed session at shutdown
                pass
        self._declared.callback(undeclare)
        return obj

    def publish(self, key: str, payload: dict) -> bytes:
        """Publish one record; returns its JSON text (UTF-8 bytes, as put)."""
        # a record the compiled hub path encoded carries its text (daq/runtime/hubpath.py)
        data = getattr(payload, "encoded", None) or dumpb(payload)
        timer = stagetiming.TIMER  # None unless a benchmark asked for the stage timing
        if timer is not None and key == "hub_loads":
            timer.handed_on(payload["seq"])
        try:
            self._pubs[key].put(data)
            self.published[key] += 1
            if timer is not None and key == "hub_loads":
                timer.put_done(payload["seq"])
        except Exception as e:  # a closed session at shutdown, a transport error
            self.errors += 1
            log.debug("publish %s failed: %s", key, e)
        if key in STATE_KEYS:
            with self._state_lock:
                self._state[key] = data
        return data

    def _answer(self, q: zenoh.Query) -> None:
        """Answer every state key the query's key expression intersects (state/*, state/config,
        prefix/**, …). What a query carries besides its key is untrusted and never read: a
        payload or parameters are counted (:attr:`bad_queries`), not decoded."""
        try:
            if q.payload is not None or str(q.parameters):
                self._count_bad_query()
            for n, key in self._state_keys.items():
                if not key.intersects(q.key_expr):
                    continue
                with self._state_lock:
                    data = self._state.get(n)
                if data is not None:
                    q.reply(key, data, encoding=zenoh.Encoding.APPLICATION_JSON)
        except Exception as e:
            log.debug("query failed: %s", e)
        finally:
            q.drop()

    def _count_bad_query(self) -> None:
        """A query with a payload or parameters: counted, logged the first time and every
        thousandth."""
        self.bad_queries += 1
        if self.bad_queries == 1 or self.bad_queries % 1000 == 0:
            log.warning("%d state queries with a payload or parameters (ignored)",
                        self.bad_queries)

    def close(self) -> None:
        self._declared.close()
        self._pubs.clear()
