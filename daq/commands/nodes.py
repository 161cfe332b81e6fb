"""`rsra nodes`: a bus check that starts nothing (cli.md; bus.md "Nodes", "Boot and supervision").

For every configured node: was it heard (boot-up or heartbeat, through the same passive
:class:`daq.master.Supervisor` the service runs), its NMT state by its last heartbeat, and
over SDO its 0x1000, 0x1018 and TPDO communication / mapping parameters against its EDS —
the checks of the master's boot step 2, but collecting *every* mismatch instead of stopping
at the first. Nothing is written: no NMT command, no SYNC, no SDO download (0x1017 is left
as it is), so it is safe beside a running service.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import canopen

from daq.config import RigConfig
from daq.decoder import TPDO_COMM, TPDO_MAP, DecodeTable, NodeLayout
from daq.master import (
    COB_EMCY,
    COB_RTR_NOT_ALLOWED,
    IDENTITY_COMPARED,
    IDENTITY_NAMES,
    Supervisor,
)

# canopen's default SDO response timeout (one retry): a node that is there answers in ms
SDO_TIMEOUT_S = 0.3


@dataclass(frozen=True)
class Mismatch:
    """One object that does not agree with the EDS (or cannot be read)."""

    object: str
    expected: Any = None
    actual: Any = None
    problem: str = ""

    def text(self) -> str:
        if self.problem:
            return f"{self.object} {self.problem}"
        return f"{self.object} reads {_fmt(self.actual)}, the EDS says {_fmt(self.expected)}"

    def to_dict(self) -> dict:
        return {"object": self.object, "expected": self.expected, "actual": self.actual,
                "problem": self.problem or None, "text": self.text()}


@dataclass
class NodeReport:
    """What the check found about one configured node."""

    name: str
    node_id: int
    role: str
    required: bool
    heard: bool = False  # boot-up or heartbeat seen
    state: str | None = None  # NMT state by its last heartbeat (None: no heartbeat)
    sdo: bool = False  # answered an SDO read
    identity: dict[str, int] | None = None
    device_type: int | None = None
    emcy: int = 0
    mismatches: list[Mismatch] = field(default_factory=list)

    @property
    def answered(self) -> bool:
        return self.heard or self.sdo

    @property
    def status(self) -> str:
        """"ok", "mismatch" (answers but disagrees with the EDS, or not over SDO) or
        "missing"."""
        if not self.answered:
            return "missing"
        return "mismatch" if self.mismatches else "ok"

    @property
    def ok(self) -> bool:
        """Fine for a start: matches, or optional and absent (bus.md: its features stay off)."""
        return self.status == "ok" or (self.status == "missing" and not self.required)

    def to_dict(self) -> dict:
        return {"name": self.name, "node_id": self.node_id, "role": self.role,
                "required": self.required, "status": self.status, "ok": self.ok,
                "heard": self.heard, "state": self.state, "sdo": self.sdo,
                "device_type": self.device_type, "identity": self.identity,
                "emcy": self.emcy, "mismatches": [m.to_dict() for m in self.mismatches]}


def _fmt(v: Any) -> str:
    return f"0x{v:08X}" if isinstance(v, int) else repr(v)


class _Unreadable(Exception):
    def __init__(self, mismatch: Mismatch, timeout: bool):
        self.mismatch, self.timeout = mismatch, timeout


def _read(nl: NodeLayout, node: canopen.RemoteNode, index: int, sub: int, name: str) -> int:
    """One SDO upload decoded with the EDS data type (as daq.master reads it)."""
    try:
        data = node.sdo.upload(index, sub)
    except canopen.SdoAbortedError as e:
        raise _Unreadable(Mismatch(name, problem=f"cannot be read: SDO abort {e}"), False) from None
    except canopen.SdoCommunicationError as e:
        raise _Unreadable(Mismatch(name, problem=f"cannot be read: {e}"), True) from None
    obj = nl.od[index]
    var = obj if sub == 0 and not hasattr(obj, "subindices") else obj[sub]
    return int(var.decode_raw(data))


def _compare(nl: NodeLayout, node: canopen.RemoteNode, index: int, sub: int, name: str,
             expected: int, out: list[Mismatch], mask: int = ~0) -> int | None:
    try:
        value = _read(nl, node, index, sub, name)
    except _Unreadable as e:
        out.append(e.mismatch)
        return None
    if value & mask != expected & mask:
        out.append(Mismatch(name, expected, value))
    return value


def verify_node(nl: NodeLayout, node: canopen.RemoteNode, report: NodeReport) -> None:
    """bus.md boot step 2 without the write: 0x1000, 0x1018 (vendor, product, revision; the
    serial number is reported, never compared) and every TPDO's COB-ID, transmission type
    and mapping against the EDS defaults. Fills ``report``."""
    out = report.mismatches
    try:
        dev = _read(nl, node, 0x1000, 0, "0x1000 (device type)")
    except _Unreadable as e:
        if e.timeout:  # silent over SDO: nothing else will answer either
            if report.heard:
                out.append(Mismatch("SDO", problem="no answer (the node sends heartbeats but "
                                    "its SDO server does not reply: check its node id)"))
            return
        out.append(e.mismatch)
        dev = None
    report.sdo = True
    report.device_type = dev
    if dev is not None and dev != nl.device_type:
        out.append(Mismatch("0x1000 (device type)", nl.device_type, dev))
    ident: dict[str, int] = {}
    for sub, expected in nl.identity.items():
        label = IDENTITY_NAMES.get(sub, str(sub))
        name = f"0x1018:{sub} ({label})"
        if sub in IDENTITY_COMPARED:
            value = _compare(nl, node, 0x1018, sub, name, expected, out)
        else:
            try:
                value = _read(nl, node, 0x1018, sub, name)
            except _Unreadable as e:
                out.append(e.mismatch)
                value = None
        if value is not None:
            ident[label] = value
    report.identity = ident
    for index in sorted(i for i in nl.od.indices if TPDO_COMM <= i < TPDO_COMM + 512):
        _verify_tpdo(nl, node, index - TPDO_COMM, out)


def _verify_tpdo(nl: NodeLayout, node: canopen.RemoteNode, k: int, out: list[Mismatch]) -> None:
    comm = nl.od[TPDO_COMM + k]
    n = k + 1
    for sub, what in ((1, "COB-ID"), (2, "transmission type")):
        if sub in comm:
            mask = ~COB_RTR_NOT_ALLOWED if sub == 1 else ~0  # bit 30 is the device's business
            _compare(nl, node, TPDO_COMM + k, sub, f"0x{TPDO_COMM + k:04X}:{sub} (TPDO{n} {what})",
                     comm[sub].default, out, mask)
    if TPDO_MAP + k not in nl.od:
        return
    mapping = nl.od[TPDO_MAP + k]
    count = _compare(nl, node, TPDO_MAP + k, 0,
                     f"0x{TPDO_MAP + k:04X}:0 (TPDO{n} number of mapped objects)",
                     mapping[0].default, out)
    if count != mapping[0].default:
        return  # entries of a different mapping cannot be compared one by one
    for s in range(1, count + 1):
        _compare(nl, node, TPDO_MAP + k, s, f"0x{TPDO_MAP + k:04X}:{s} (TPDO{n} mapped object {s})",
                 mapping[s].default, out)


def check_network(cfg: RigConfig, network: canopen.Network, timeout_s: float,
                  table: DecodeTable | None = None) -> list[NodeReport]:
    """Check every configured node on a connected canopen ``network`` (read only; the
    network gets a RemoteNode per configured node: use a network of its own).

    Waits up to ``timeout_s`` for a boot-up or heartbeat of each node (stops waiting as soon
    as every node was heard), then verifies every node over SDO — a node without heartbeat
    counts as present when it answers SDO."""
    table = table or DecodeTable(cfg)
    sup = Supervisor(cfg, table)
    for cob, cb in sup.callbacks().items():
        network.subscribe(cob, cb)
    remote: dict[str, canopen.RemoteNode] = {}
    for nl in table.nodes:
        node = canopen.RemoteNode(nl.node_id, nl.od)
        network.add_node(node)
        # canopen's EMCY consumer drops short frames and logs without bound: ours counts
        network.unsubscribe(COB_EMCY + nl.node_id, node.emcy.on_emcy)
        node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        remote[nl.name] = node
    deadline = time.monotonic() + timeout_s
    for nl in table.nodes:  # a real-time protocol wait (heartbeats are periodic)
        sup.nodes[nl.name].heard.wait(max(0.0, deadline - time.monotonic()))
    reports = []
    for nl in table.nodes:
        ns = sup.nodes[nl.name]
        heard = ns.heard.is_set()
        rep = NodeReport(nl.name, nl.node_id, nl.role, nl.required, heard=heard,
                         state=ns.state if heard else None)
        verify_node(nl, remote[nl.name], rep)
        rep.emcy = ns.emcy_count
        reports.append(rep)
    return reports


# ---------------------------------------------------------------------------------------------
# command line

def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from daq.cli import common_options

    p = sub.add_parser(
        name, help="bus check: which configured nodes answer, their state, identity and mapping",
        description="A read-only bus check that starts nothing (no NMT command, no SYNC, no SDO "
        "write). For every configured node: heard (boot-up or heartbeat) or answering SDO, its "
        "NMT state by its last heartbeat, its identity (0x1000, 0x1018) and TPDO communication "
        "and mapping parameters against its EDS, each mismatch naming the object and both "
        "values. Exit status 0 when every required node answers and every node that answers "
        "matches its EDS (an absent optional node is reported, not an error), 1 otherwise, 2 "
        "for a usage or configuration error.")
    common_options(p, units=False)
    p.add_argument("--interface", default=None, metavar="I",
                   help="python-can interface, e.g. socketcan (required)")
    p.add_argument("--channel", default=None, metavar="C",
                   help="python-can channel, e.g. vcan0 or can0")
    p.add_argument("--timeout", type=float, default=None, metavar="S",
                   help="wait up to S seconds for the nodes' heartbeats before the SDO checks "
                   "(default: the heartbeat watchdog time, heartbeat.timeout_factor × "
                   "heartbeat.producer_ms of the config); the wait ends early when every node "
                   "was heard. A node without heartbeat still counts when it answers SDO")
    p.add_argument("--json", action="store_true",
                   help='print {"ok", "interface", "channel", "nodes": [{"name", "node_id", '
                   '"role", "required", "status", "ok", "heard", "state", "sdo", "device_type", '
                   '"identity", "emcy", "mismatches": [{"object", "expected", "actual", '
                   '"problem", "text"}]}]} instead of the table')
    return p


def run(args: argparse.Namespace) -> int:
    import can

    from daq.cli import UsageError
    from daq.config import load_config

    if args.interface is None:
        raise UsageError("give the bus: --interface I [--channel C], e.g. --interface socketcan "
                         "--channel vcan0")
    if args.timeout is not None and not args.timeout > 0:
        raise UsageError(f"--timeout {args.timeout}: must be a positive number of seconds")
    cfg = load_config(args.config)
    table = DecodeTable(cfg)
    timeout = (args.timeout if args.timeout is not None
               else cfg.heartbeat.timeout_factor * cfg.heartbeat.producer_ms / 1000.0)
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.1  # quick close
    try:
        kw: dict[str, Any] = {"interface": args.interface}
        if args.channel is not None:
            kw["channel"] = args.channel
        network.connect(**kw)
    except (can.CanError, OSError, ValueError, ImportError) as e:
        raise UsageError(f"cannot open the bus --interface {args.interface} --channel "
                         f"{args.channel}: {e}; check the interface and channel") from None
    # an absent node's SDO timeout is part of the answer, not an error to log
    sdo_log = logging.getLogger("canopen.sdo.client")
    level = sdo_log.level
    sdo_log.setLevel(logging.CRITICAL)
    try:
        reports = check_network(cfg, network, timeout, table)
    finally:
        sdo_log.setLevel(level)
        bus = network.bus
        try:
            network.disconnect()
        except Exception:  # the interface's own shutdown failed: closed once, quietly
            from daq.sharedbus import shutdown_bus

            shutdown_bus(bus)
    ok = all(r.ok for r in reports)
    if args.json:
        print(json.dumps({"ok": ok, "interface": args.interface, "channel": args.channel,
                          "nodes": [r.to_dict() for r in reports]}))
    else:
        _print_table(cfg, reports, args, ok)
    return 0 if ok else 1


def _print_table(cfg: RigConfig, reports: list[NodeReport], args: argparse.Namespace,
                 ok: bool) -> None:
    from rich.table import Table

    from daq.console import make_console

    console = make_console()
    if not console.is_terminal:
        console.width = max(console.width, 120)  # piped into a file: don't wrap the table
    t = Table(title=f"Nodes of rig {cfg.rig_name!r} on {args.interface}"
              + (f":{args.channel}" if args.channel else ""))
    for col in ("node", "id", "required", "NMT state", "identity: vendor/product/revision #serial",
                "result"):
        t.add_column(col)
    for r in reports:
        ident = r.identity or {}
        if ident:
            v, p, rev, ser = (ident.get(IDENTITY_NAMES[s]) for s in (1, 2, 3, 4))
            ident_s = "/".join("?" if x is None else f"0x{x:X}" for x in (v, p, rev))
            ident_s += "" if ser is None else f" #{ser}"
        else:
            ident_s = "—"
        if r.status == "ok":
            result = "[green]OK[/green]"
        elif r.status == "mismatch":
            result = f"[red]mismatch ({len(r.mismatches)})[/red]"
        elif r.required:
            result = "[red]missing[/red]"
        else:
            result = "[yellow]absent (optional)[/yellow]"
        state = r.state or ("no heartbeat" if r.sdo else "—")
        t.add_row(r.name, f"0x{r.node_id:02X}", "yes" if r.required else "no", state, ident_s,
                  result)
    console.print(t)
    for r in reports:
        for m in r.mismatches:
            console.print(f"node {r.name}: {m.text()}", highlight=False, markup=False)
        if r.status == "missing":
            what = ("required: the service cannot start without it; check its power, wiring "
                    "and node id") if r.required else "optional: its features stay off"
            console.print(f"node {r.name} (id 0x{r.node_id:02X}): no heartbeat, boot-up or SDO "
                          f"answer — {what}", highlight=False, markup=False)
    console.print("all required nodes answer and match their EDS" if ok
                  else "NOT ready: see above", highlight=False)
