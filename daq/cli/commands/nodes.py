"""`rsra nodes`: a bus check that starts nothing (docs/cli.md §10; docs/bus.md §1 "Nodes",
§3 "Boot and supervision").

For every configured node: was it heard (boot-up or heartbeat, through the same passive
:class:`daq.master.Supervisor` the service runs), its NMT state by its last heartbeat, and
over SDO its 0x1000, 0x1018 and TPDO communication / mapping parameters against its EDS —
the checks of the master's boot step 2 (one verifier, :mod:`rsra.daq.bus.nodecheck`), but
collecting *every* mismatch instead of stopping at the first. Nothing is written: no NMT command, no SYNC, no SDO download (0x1017 is left
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

from rsra.config.rig import RigConfig
from rsra.daq.bus.decoder import DecodeTable
from rsra.daq.bus.master import COB_EMCY, Supervisor
from rsra.daq.bus.nodecheck import IDENTITY_NAMES, Mismatch, verify_node

# canopen's default SDO response timeout (one retry): a node that is there answers in ms
SDO_TIMEOUT_S = 0.3


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
        """Fine for a start: matches, or optional and absent (docs/bus.md §3: its features stay off)."""
        return self.status == "ok" or (self.status == "missing" and not self.required)

    def to_dict(self) -> dict:
        return {"name": self.name, "node_id": self.node_id, "role": self.role,
                "required": self.required, "status": self.status, "ok": self.ok,
                "heard": self.heard, "state": self.state, "sdo": self.sdo,
                "device_type": self.device_type, "identity": self.identity,
                "emcy": self.emcy, "mismatches": [m.to_dict() for m in self.mismatches]}


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
    remote = {nl.name: _remote_node(network, nl) for nl in table.nodes}
    deadline = time.monotonic() + timeout_s
    for nl in table.nodes:  # a real-time protocol wait (heartbeats are periodic)
        sup.nodes[nl.name].heard.wait(max(0.0, deadline - time.monotonic()))
    return [_node_report(nl, sup.nodes[nl.name], remote[nl.name]) for nl in table.nodes]


def _remote_node(network: canopen.Network, nl) -> canopen.RemoteNode:
    """A configured node on the network, for its SDO answers."""
    node = canopen.RemoteNode(nl.node_id, nl.od)
    network.add_node(node)
    # canopen's EMCY consumer drops short frames and logs without bound: ours counts
    network.unsubscribe(COB_EMCY + nl.node_id, node.emcy.on_emcy)
    node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
    return node


def _node_report(nl, ns, node: canopen.RemoteNode) -> NodeReport:
    """One node's report: what its heartbeats said (``ns``, the supervisor's view) and what
    it answered over SDO against its EDS."""
    heard = ns.heard.is_set()
    rep = NodeReport(nl.name, nl.node_id, nl.role, nl.required, heard=heard,
                     state=ns.state if heard else None)
    facts = verify_node(nl, node)
    rep.sdo, rep.device_type = facts.sdo, facts.device_type
    rep.identity = facts.identity if facts.sdo else None
    if facts.sdo:
        rep.mismatches = facts.mismatches
    elif heard:  # silent over SDO: nothing else will answer either
        rep.mismatches = [Mismatch("SDO", problem="no answer (the node sends heartbeats "
                                   "but its SDO server does not reply: check its node id)")]
    rep.emcy = ns.emcy_count
    return rep


# ---------------------------------------------------------------------------------------------
# command line

def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

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
    from rsra.daq.cli.options import UsageError
    from rsra.daq.rigmodel import load_rig

    if args.interface is None:
        raise UsageError("give the bus: --interface I [--channel C], e.g. --interface socketcan "
                         "--channel vcan0")
    if args.timeout is not None and not args.timeout > 0:
        raise UsageError(f"--timeout {args.timeout}: must be a positive number of seconds")
    cfg = load_rig(args.config)
    table = DecodeTable(cfg)
    timeout = (args.timeout if args.timeout is not None
               else cfg.heartbeat.timeout_factor * cfg.heartbeat.producer_ms / 1000.0)
    network = _connect(args.interface, args.channel)
    # an absent node's SDO timeout is part of the answer, not an error to log
    sdo_log = logging.getLogger("canopen.sdo.client")
    level = sdo_log.level
    sdo_log.setLevel(logging.CRITICAL)
    try:
        reports = check_network(cfg, network, timeout, table)
    finally:
        sdo_log.setLevel(level)
        _disconnect(network)
    ok = all(r.ok for r in reports)
    if args.json:
        print(json.dumps({"ok": ok, "interface": args.interface, "channel": args.channel,
                          "nodes": [r.to_dict() for r in reports]}))
    else:
        _print_table(cfg, reports, args, ok)
    return 0 if ok else 1


def _connect(interface: str, channel: str | None) -> canopen.Network:
    """A canopen network on the bus; a bus that does not open: one line (exit 2)."""
    import can

    from rsra.daq.cli.options import UsageError

    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.1  # quick close
    try:
        kw: dict[str, Any] = {"interface": interface}
        if channel is not None:
            kw["channel"] = channel
        network.connect(**kw)
    except (can.CanError, OSError, ValueError, ImportError) as e:
        raise UsageError(f"cannot open the bus --interface {interface} --channel "
                         f"{channel}: {e}; check the interface and channel") from None
    return network


def _disconnect(network: canopen.Network) -> None:
    """The network closed; when the interface's own shutdown fails, the bus closed once,
    quietly."""
    bus = network.bus
    try:
        network.disconnect()
    except Exception:  # the interface's own shutdown failed: closed once, quietly
        from rsra.canbus import shutdown_bus

        if bus is not None:  # (connected above)
            shutdown_bus(bus)


def _identity_text(ident: dict | None) -> str:
    """vendor/product/revision in hex and #serial, ``?`` for what the node did not give."""
    if not ident:
        return "—"
    v, p, rev, ser = (ident.get(IDENTITY_NAMES[s]) for s in (1, 2, 3, 4))
    text = "/".join("?" if x is None else f"0x{x:X}" for x in (v, p, rev))
    return text + ("" if ser is None else f" #{ser}")


def _result_text(r: NodeReport) -> str:
    if r.status == "ok":
        return "[green]OK[/green]"
    if r.status == "mismatch":
        return f"[red]mismatch ({len(r.mismatches)})[/red]"
    return "[red]missing[/red]" if r.required else "[yellow]absent (optional)[/yellow]"


def _problem_lines(r: NodeReport) -> list[str]:
    """A node's mismatches against its EDS, or what its absence means."""
    lines = [f"node {r.name}: {m.text()}" for m in r.mismatches]
    if r.status == "missing":
        what = ("required: the service cannot start without it; check its power, wiring "
                "and node id") if r.required else "optional: its features stay off"
        lines.append(f"node {r.name} (id 0x{r.node_id:02X}): no heartbeat, boot-up or SDO "
                     f"answer — {what}")
    return lines


def _print_table(cfg: RigConfig, reports: list[NodeReport], args: argparse.Namespace,
                 ok: bool) -> None:
    from rich.table import Table

    from rsra.daq.cli.console import make_console

    console = make_console()
    if not console.is_terminal:
        console.width = max(console.width, 120)  # piped into a file: don't wrap the table
    t = Table(title=f"Nodes of rig {cfg.rig_name!r} on {args.interface}"
              + (f":{args.channel}" if args.channel else ""))
    for col in ("node", "id", "required", "NMT state", "identity: vendor/product/revision #serial",
                "result"):
        t.add_column(col)
    for r in reports:
        state = r.state or ("no heartbeat" if r.sdo else "—")
        t.add_row(r.name, f"0x{r.node_id:02X}", "yes" if r.required else "no", state,
                  _identity_text(r.identity), _result_text(r))
    console.print(t)
    for r in reports:
        for line in _problem_lines(r):
            console.print(line, highlight=False, markup=False)
    console.print("all required nodes answer and match their EDS" if ok
                  else "NOT ready: see above", highlight=False)
