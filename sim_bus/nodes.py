"""Simulated CANopen slave nodes of the aircraft (docs/bus.md §1 "Nodes"), built on canopen's LocalNode.

canopen's ``LocalNode`` gives us the object dictionary parsed from the node's EDS and a
working SDO server. Everything else it does badly (docs/bus.md §6 "Library pitfalls", measured with
canopen 2.4.1) is replaced here:

* NMT: LocalNode stays in INITIALISING after a reset. ``SimNode`` runs its own CiA 301 state
  machine (boot-up frame on start and after every reset, then pre-operational; start, stop,
  enter pre-operational; reset communication restores 0x1000–0x1FFF, reset application the
  whole dictionary) and keeps LocalNode's ``nmt`` state in step with it (through the NMT
  slave's own command handler: no private state of canopen's is written).
* Heartbeat: LocalNode produces it with python-can's wall-clock periodic send and restarts
  that task on every write to 0x1017 (:class:`QuietLocalNode` declines that). ``SimNode``
  instead reports the heartbeats that are due at the acquisition clock's time (model §8.3
  "Time"): simulated time in lock-step, the wall clock live. A write to 0x1017 re-arms that
  schedule.
* TPDOs: LocalNode sends none on SYNC and does not share TPDO values with its SDO server.
  ``SimNode.sync`` encodes every valid TPDO from the mapping *currently in its dictionary*
  (0x1800…/0x1A00…, re-read after any SDO write to them), honours the transmission type
  (0: on change, 1…240: every n-th SYNC, with the SYNC start value when the EDS has one) and
  only in OPERATIONAL; an SDO read of a mapped process object returns what the last TPDO
  carried.
* EMCY: frames are built here with the error register 0x1001 kept up to date.

A node returns the frames it wants to send as ``Frame`` tuples; the bus simulator
(sim_bus.bus_sim) stamps, fault-injects, records and transmits them. Only SDO responses go
straight through ``network.send_message`` (LocalNode's SDO server), so a network whose
``send_message`` is overridden sees them too.
"""
from __future__ import annotations

import contextlib
import logging
import math
import struct
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import canopen
from canopen import objectdictionary as od_mod
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.sdo import SdoAbortedError

from rsra.config.devices import DEVICE_PROFILES, TURN, device_profile

log = logging.getLogger(__name__)

# The channels of each node role and their bus units are the device profile's
# (config.devices: in the order of the node's TPDO mapping entries, docs/bus.md §1 "Nodes"); the
# OD objects that carry them come from the EDS mapping, never from here.

# CiA 301 NMT states (the heartbeat byte) and command specifiers.
INITIALISING, STOPPED, OPERATIONAL, PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F
STATE_NAMES = {INITIALISING: "INITIALISING", STOPPED: "STOPPED", OPERATIONAL: "OPERATIONAL",
               PRE_OPERATIONAL: "PRE-OPERATIONAL"}
NMT_START, NMT_STOP, NMT_PRE_OPERATIONAL, NMT_RESET_NODE, NMT_RESET_COMM = 0x01, 0x02, 0x80, 0x81, 0x82
# the command that leads to each state (a reset ends in INITIALISING)
_COMMAND_TO = {INITIALISING: NMT_RESET_NODE, STOPPED: NMT_STOP, OPERATIONAL: NMT_START,
               PRE_OPERATIONAL: NMT_PRE_OPERATIONAL}

# CiA 301 function codes (COB-ID = function code + node id where the EDS gives no other).
COB_NMT, COB_EMCY_BASE, COB_SDO_TX, COB_SDO_RX, COB_HEARTBEAT = 0x000, 0x080, 0x580, 0x600, 0x700
PDO_NOT_VALID = 1 << 31
PDO_RTR_NOT_ALLOWED = 1 << 30
COB_ID_MASK = 0x7FF
EMCY_STRUCT = struct.Struct("<HB5s")
_F32 = struct.Struct("<f")

# SDO abort codes used by the mapping checks (CiA 301 table 22).
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_TOO_LONG = 0x06040042

TIME_EPS = 1e-9  # due-time comparisons tolerate float rounding (recordings resolve 1 µs)

# Error-register bits (CiA 301 object 0x1001).
ERR_GENERIC = 0x01
ERR_MANUFACTURER = 0x80


class Frame(NamedTuple):
    """One frame a node wants to send: kind ("bootup", "heartbeat", "tpdo", "emcy"), COB-ID,
    payload, and for TPDOs the TPDO number (1-based)."""

    kind: str
    cob_id: int
    data: bytes
    tpdo: int = 0


@dataclass(frozen=True)
class MapEntry:
    index: int
    subindex: int
    bits: int
    var: ODVariable | None  # None for a dummy entry (index 1…7): sent as zeros


@dataclass(frozen=True)
class TpdoConfig:
    number: int  # 1-based
    cob_id: int
    valid: bool
    trans_type: int
    sync_start: int
    entries: tuple[MapEntry, ...]
    packer: struct.Struct | None  # fast path when every entry is a whole struct type

    @property
    def length(self) -> int:
        return (sum(e.bits for e in self.entries) + 7) // 8


# --------------------------------------------------------------------------------------------
# Generic channel codec from the EDS data type: engineering units <-> the raw value a TPDO
# carries (SimNode.update). The bus simulator feeds its nodes from sim_bus.offline's
# ChannelCodec instead, the one encoder it shares with the off-line API (which also saturates
# the accelerometers at their full scale); a test checks the two agree inside the range.

def _int_range(var: ODVariable) -> tuple[int, int]:
    bits = len(var)
    if var.data_type in od_mod.SIGNED_TYPES:
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    return 0, (1 << bits) - 1


def _counts_per_unit(role: str, channel: str) -> float | str | None:
    """Bus counts per engineering unit of a channel (the profile's scale inverted), TURN for
    an angle spanning one turn, None where count and unit are one (a factor of 1, a status)."""
    scale = device_profile(role).channel(channel).scale
    if scale == TURN:
        return TURN
    return None if scale is None or scale == 1.0 else 1.0 / float(scale)


def encode_channel(role: str, channel: str, value: float, var: ODVariable) -> int | float:
    """Engineering value -> the raw value of OD variable ``var`` (the device profile's units,
    config.devices).

    Scaled channels (accelerometer axes: m/s² -> mg counts): rounded half-to-even and
    saturated to the data type. An angle spanning one turn (the azimuth): rad -> 0…2^bits
    over 0…2π, wrapped. Integers elsewhere: rounded and saturated. Floats: the value itself
    (the packer rounds to REAL32).
    """
    dt = var.data_type
    if dt == od_mod.REAL32:
        return _F32.unpack(_F32.pack(float(value)))[0]  # what the frame will carry
    if dt in od_mod.FLOAT_TYPES:
        return float(value)
    lo, hi = _int_range(var)
    per_unit = _counts_per_unit(role, channel)
    if per_unit == TURN:
        span = hi - lo + 1
        return int(round((float(value) % (2 * math.pi)) / (2 * math.pi) * span)) % span + lo
    if isinstance(per_unit, float):
        value = float(value) * per_unit
    if not math.isfinite(value):
        return hi if value > 0 else lo
    return int(min(max(round(value), lo), hi))


def decode_channel(role: str, channel: str, raw: int | float, var: ODVariable) -> float:
    """The inverse of ``encode_channel`` (to the encoding's resolution)."""
    if var.data_type in od_mod.FLOAT_TYPES:
        return float(raw)
    per_unit = _counts_per_unit(role, channel)
    if per_unit == TURN:
        lo, hi = _int_range(var)
        return (int(raw) - lo) / (hi - lo + 1) * 2 * math.pi
    if isinstance(per_unit, float):
        return float(raw) / per_unit
    return float(raw)


# --------------------------------------------------------------------------------------------

_OD_CACHE: dict[tuple[str, int], "canopen.ObjectDictionary"] = {}


def load_od(eds: str | Path, node_id: int) -> "canopen.ObjectDictionary":
    """The node's object dictionary from its EDS ($NODEID substituted). Parsed once per
    (file, id): the dictionary itself is never mutated (values live in LocalNode.data_store)."""
    key = (str(Path(eds).resolve()), int(node_id))
    if key not in _OD_CACHE:
        _OD_CACHE[key] = canopen.import_od(key[0], node_id)
    return _OD_CACHE[key]


def _record(od: "canopen.ObjectDictionary", index: int) -> ODRecord | ODArray:
    """Object ``index`` of ``od``, a record or an array (a PDO parameter, CiA 301)."""
    obj = od[index]
    if isinstance(obj, ODVariable):
        raise TypeError(f"object 0x{index:04X} is a variable, not a record or an array")
    return obj


def role_channel_vars(od: "canopen.ObjectDictionary", role: str) -> list[tuple[str, ODVariable]]:
    """The role's channels paired with the OD variables of the EDS's default TPDO mapping, in
    order (TPDO1 entry 1, 2, …, TPDO2 …). Raises ValueError when the EDS maps fewer objects."""
    names = device_profile(role).names
    mapped: list[ODVariable] = []
    for n in range(512):
        if 0x1A00 + n not in od:
            break
        arr = _record(od, 0x1A00 + n)
        count = int(arr[0].default or 0)
        for s in range(1, count + 1):
            word = int(arr[s].default or 0)
            idx, sub = word >> 16, (word >> 8) & 0xFF
            if idx < 0x1000:  # dummy entry
                continue
            obj = od[idx]
            mapped.append(obj if isinstance(obj, ODVariable) else obj[sub])
    if len(mapped) < len(names):
        raise ValueError(f"EDS maps {len(mapped)} objects for role {role!r}, needs "
                         f"{len(names)} ({', '.join(names)})")
    return list(zip(names, mapped))


class HeartbeatSchedule:
    """When a node's heartbeats are due (CiA 301 producer heartbeat time, 0x1017), on the
    acquisition clock: due times are ``base + n·period`` (no accumulated rounding)."""

    def __init__(self) -> None:
        self.period = 0.0  # s; 0: no heartbeat
        self._base, self._n = 0.0, 1
        self.next: float | None = None  # the next due time (None: none produced)

    def arm(self, t: float, ms: int) -> None:
        """(Re)start at time ``t`` with a period of ``ms`` milliseconds (0: off): the first
        heartbeat one period later."""
        self.period = ms / 1000.0
        self._base, self._n = t, 1
        self.next = t + self.period if ms > 0 else None

    def due(self, t: float) -> list[float]:
        """The due times up to time ``t``, consumed. After a long gap (a stalled clock) at
        most one period's worth of backlog is kept: a real node would not burst."""
        out: list[float] = []
        if self.next is None:
            return out
        p = self.period
        if t - self.next > 10 * p:
            self._n = int((t - self._base) / p)
            self.next = self._base + self._n * p
        while self.next <= t + TIME_EPS:
            out.append(self.next)
            self._n += 1
            self.next = self._base + self._n * p
        return out


class TpdoProducer:
    """A node's process image and its synchronous TPDOs, from the mapping *currently in its
    dictionary* (0x1800…/0x1A00…, re-read after any change to them): which are due at a SYNC
    (transmission type, SYNC start value), their bytes, and what the last ones carried (an
    SDO read of a mapped process object returns that)."""

    def __init__(self, od: "canopen.ObjectDictionary", local: canopen.LocalNode):
        self.od, self.local = od, local
        self.process: dict[tuple[int, int], int | float] = {}  # current raw process image
        self.carried: dict[tuple[int, int], int | float] = {}  # what the last TPDOs carried
        self._tpdos: list[TpdoConfig] | None = None  # cache, rebuilt after writes/resets
        self._sync_count: dict[int, int] = {}
        self._started_counting: dict[int, bool] = {}
        self._last_sent: dict[int, bytes] = {}

    def restart_counting(self) -> None:
        """SYNC counting and change detection start afresh (boot, NMT start)."""
        self._sync_count.clear()
        self._started_counting.clear()
        self._last_sent.clear()

    def remapped(self) -> None:
        """The communication or mapping parameters changed: re-read at the next SYNC."""
        self._tpdos = None
        self._started_counting.clear()
        self._last_sent.clear()

    def configs(self) -> list[TpdoConfig]:
        """The TPDO configuration as the dictionary holds it now (SDO writes included)."""
        if self._tpdos is None:
            self._tpdos = self._read_tpdos()
        return self._tpdos

    def value(self, index: int, sub: int) -> int:
        obj = self.od[index]
        var = obj if isinstance(obj, ODVariable) else obj[sub]
        return int(var.decode_raw(self.local.get_data(index, sub)))

    def entry(self, word: int) -> MapEntry:
        """A mapping entry (0x1A0x sub-index value); SdoAbortedError when not mappable."""
        idx, sub, bits = word >> 16, (word >> 8) & 0xFF, word & 0xFF
        if 1 <= idx <= 7:
            return MapEntry(idx, sub, bits, None)
        if idx not in self.od:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        obj = self.od[idx]
        if not isinstance(obj, ODVariable):
            if sub not in obj:
                raise SdoAbortedError(ABORT_NOT_MAPPABLE)
            obj = obj[sub]
        if not obj.pdo_mappable or len(obj) != bits:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        return MapEntry(idx, sub, bits, obj)

    def check_mapping_write(self, index: int, subindex: int, od: ODVariable,
                            data: bytes) -> None:
        """An SDO write to a mapping parameter (0x1A00…0x1BFF): aborted (SdoAbortedError)
        when an entry is not mappable or the TPDO would exceed 64 bits."""
        value = int(od.decode_raw(data))
        if subindex == 0:
            total = 0
            for s in range(1, value + 1):
                total += self.entry(self.value(index, s)).bits
            if total > 64:
                raise SdoAbortedError(ABORT_PDO_TOO_LONG)
        elif value:
            self.entry(value)  # aborts when not mappable

    def _read_tpdos(self) -> list[TpdoConfig]:
        out = []
        for n in range(512):
            com, mp = 0x1800 + n, 0x1A00 + n
            if com not in self.od or mp not in self.od:
                break
            cob = self.value(com, 1)
            trans = self.value(com, 2)
            start = self.value(com, 6) if 6 in _record(self.od, com) else 0
            count = self.value(mp, 0)
            entries = tuple(self.entry(self.value(mp, s)) for s in range(1, count + 1))
            fmt = "<"  # "": not every entry a whole struct type (no packer)
            for e in entries:
                dt = e.var.data_type if e.var is not None else None
                st = ODVariable.STRUCT_TYPES.get(dt) if dt is not None else None
                if st is None or not isinstance(st, struct.Struct) or e.bits != 8 * st.size:
                    fmt = ""
                    break
                fmt += st.format.lstrip("<")
            out.append(TpdoConfig(number=n + 1, cob_id=cob & COB_ID_MASK,
                                  valid=not cob & PDO_NOT_VALID, trans_type=trans,
                                  sync_start=start, entries=entries,
                                  packer=struct.Struct(fmt) if fmt else None))
        return out

    @staticmethod
    def _default(var: ODVariable) -> int | float:
        v = var.value if var.value is not None else var.default
        return v if v is not None else 0

    def _pack(self, cfg: TpdoConfig) -> tuple[bytes, list[tuple[tuple[int, int], int | float]]]:
        vals: list[tuple[tuple[int, int], int | float]] = []
        for e in cfg.entries:
            key = (e.index, e.subindex)
            if e.var is None:
                vals.append((key, 0))
            else:
                v = self.process.get(key)
                vals.append((key, self._default(e.var) if v is None else v))
        if cfg.packer is not None:
            return cfg.packer.pack(*(v for _, v in vals)), vals
        # general bit-granular packing (CiA 301: entries are concatenated LSB first)
        acc, shift = 0, 0
        for e, (_, v) in zip(cfg.entries, vals):
            if e.var is not None:
                raw = int.from_bytes(e.var.encode_raw(v), "little")
                acc |= (raw & ((1 << e.bits) - 1)) << shift
            shift += e.bits
        return acc.to_bytes(cfg.length, "little"), vals

    def sync(self, counter: int | None,
             carried: list[dict[tuple[int, int], int | float]] | None) -> list[Frame]:
        """The TPDOs due at one SYNC, in TPDO order (the node is OPERATIONAL): see
        :meth:`SimNode.sync`."""
        frames = []
        for cfg in self.configs():
            if not cfg.valid or not cfg.entries:
                continue
            t = cfg.trans_type
            if t > 240:
                continue  # 241…251 reserved; 252…255 not synchronous
            if not self._started_counting.get(cfg.number):
                if cfg.sync_start and counter is not None and counter != cfg.sync_start:
                    continue
                self._started_counting[cfg.number] = True
                self._sync_count[cfg.number] = 0
            data, vals = self._pack(cfg)
            if t == 0:
                if self._last_sent.get(cfg.number) == data:
                    continue
            else:
                c = self._sync_count[cfg.number] = self._sync_count[cfg.number] + 1
                if c % t:
                    continue
            self._last_sent[cfg.number] = data
            if carried is None:
                self.carried.update(vals)
            else:
                carried.append(dict(vals))
            frames.append(Frame("tpdo", cfg.cob_id, data, cfg.number))
        return frames

    def snapshot(self) -> tuple:
        return (dict(self.process), dict(self._sync_count), dict(self._started_counting),
                dict(self._last_sent), self._tpdos)

    def restore(self, snap: tuple) -> None:
        (self.process, self._sync_count, self._started_counting, self._last_sent,
         self._tpdos) = (dict(snap[0]), dict(snap[1]), dict(snap[2]), dict(snap[3]), snap[4])


class ErrorState:
    """A node's active errors and its error register (0x1001), and the EMCY frames that
    report them appearing and going away (CiA 301)."""

    def __init__(self) -> None:
        self.active: dict[int, int] = {}  # EMCY code -> register bits
        self.register = 0

    def _update(self) -> None:
        self.register = 0
        for bits in self.active.values():
            self.register |= bits

    def raise_error(self, cob_id: int, code: int, register_bits: int, info: bytes) -> Frame:
        self.active[code] = register_bits | ERR_GENERIC
        self._update()
        return Frame("emcy", cob_id, EMCY_STRUCT.pack(code, self.register, info))

    def clear_error(self, cob_id: int, code: int) -> Frame | None:
        if self.active.pop(code, None) is None:
            return None
        self._update()
        # CiA 301: code 0x0000 with the remaining error register; the cleared code as info
        return Frame("emcy", cob_id, EMCY_STRUCT.pack(0, self.register, struct.pack("<H", code)))

    def clear(self) -> None:
        self.active.clear()
        self.register = 0


class QuietLocalNode(canopen.LocalNode):
    """canopen's LocalNode without its wall-clock heartbeat: LocalNode registers its NMT
    slave's ``on_write``, which starts python-can's periodic send on every write to 0x1017;
    a simulated node reports its heartbeats on the acquisition clock instead
    (:class:`HeartbeatSchedule`), so that one registration is declined. Every other write
    callback is kept."""

    def add_write_callback(self, callback: Callable[..., None]) -> None:
        nmt = getattr(self, "nmt", None)  # (registered from LocalNode.__init__)
        if nmt is not None and callback == nmt.on_write:
            return
        super().add_write_callback(callback)


class SimNode:
    """One simulated CANopen slave: a LocalNode from the EDS with the NMT, heartbeat, SYNC/TPDO
    and EMCY behaviour of CiA 301 done properly (see the module docstring).

    ``clock`` is the acquisition clock (seconds): the node asks it when an SDO write re-arms
    the heartbeat. Frames the node wants to send are returned, never sent, except SDO
    responses, which LocalNode's SDO server sends through ``network.send_message``. The NMT
    state machine and the canopen glue are here; the heartbeat schedule, the process image
    with its TPDOs and the error state are parts (:class:`HeartbeatSchedule`,
    :class:`TpdoProducer`, :class:`ErrorState`).
    """

    def __init__(self, name: str, role: str, node_id: int, eds: str | Path,
                 clock: Callable[[], float], lock: "threading.RLock | None" = None):
        if role not in DEVICE_PROFILES:
            raise ValueError(f"node {name!r}: unknown role {role!r}")
        self.name, self.role, self.node_id = name, role, int(node_id)
        self.eds = Path(eds)
        self.od = load_od(eds, node_id)
        self.local = QuietLocalNode(self.node_id, self.od)
        self._clock = clock
        self._lock = lock if lock is not None else contextlib.nullcontext()
        #: the role's channels (the device profile's, config.devices) with the OD variables
        #: of the EDS's default mapping that carry them
        self.channels = role_channel_vars(self.od, role)
        #: the channel names, in the profile's order
        self.channel_names: tuple[str, ...] = tuple(ch for ch, _ in self.channels)
        self._channel_key = {ch: (v.index, v.subindex) for ch, v in self.channels}
        self.state = INITIALISING
        self.silent = False  # fault: the node neither sends nor hears anything
        self.tpdos = TpdoProducer(self.od, self.local)
        self.errors = ErrorState()
        self._heartbeat = HeartbeatSchedule()
        self.network: canopen.Network | None = None
        # called before anything from outside a SYNC cycle (NMT, boot/reset, an SDO request)
        # changes what the node answers: the bus simulator undoes a cycle it built ahead of
        # its SYNC (real time) then, so the event applies to the state it would have met
        self.before_change: Callable[[], None] | None = None
        self.local.add_read_callback(self._on_sdo_read)
        self.local.add_write_callback(self._on_sdo_write)  # (0x1017 re-arms our heartbeat)

    # ---- network --------------------------------------------------------------------------
    def attach(self, network: canopen.Network) -> None:
        """Add the LocalNode to ``network`` for its SDO server. NMT commands are not taken from
        the network (LocalNode would stall in INITIALISING): the owner calls ``nmt()``."""
        network[self.node_id] = self.local
        network.unsubscribe(COB_NMT, self.local.nmt.on_command)
        network.unsubscribe(self.local.sdo.rx_cobid, self.local.sdo.on_request)
        network.subscribe(self.local.sdo.rx_cobid, self._on_sdo_request)
        self.network = network

    def detach(self) -> None:
        if self.network is not None:
            self.network.unsubscribe(self.local.sdo.rx_cobid, self._on_sdo_request)
            self.network.subscribe(COB_NMT, self.local.nmt.on_command)  # what remove_network expects
            self.network.subscribe(self.local.sdo.rx_cobid, self.local.sdo.on_request)
            del self.network[self.node_id]
            self.network = None

    def _on_sdo_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:  # the SDO server runs in the bus thread; SYNC may run elsewhere
            if self.before_change is not None:
                self.before_change()
            if not self.silent:
                self.local.sdo.on_request(can_id, data, timestamp)

    # ---- NMT --------------------------------------------------------------------------------
    @property
    def state_name(self) -> str:
        return STATE_NAMES[self.state]

    def _set_state(self, state: int) -> None:
        self.state = state
        # LocalNode's view (and its users) kept in step through its NMT slave's own command
        # handler, given the command that leads to the state (no frame is sent)
        self.local.nmt.on_command(COB_NMT, bytes((_COMMAND_TO[state], self.node_id)), 0.0)

    def boot(self, t: float | None = None) -> list[Frame]:
        """Power-on (or the end of a reset): boot-up frame, then PRE-OPERATIONAL; the heartbeat
        producer starts one period later (CiA 301)."""
        t = self._clock() if t is None else t
        if self.before_change is not None:
            self.before_change()
        self._set_state(INITIALISING)
        self.tpdos.restart_counting()
        self.tpdos.remapped()
        frames = [Frame("bootup", COB_HEARTBEAT + self.node_id, b"\x00")]
        self._set_state(PRE_OPERATIONAL)
        self._arm_heartbeat(t)
        return frames

    def reset(self, communication_only: bool = False, t: float | None = None) -> list[Frame]:
        """NMT reset node (the whole dictionary back to the EDS defaults, errors cleared) or
        reset communication (0x1000–0x1FFF only), then boot."""
        if self.before_change is not None:
            self.before_change()
        store = self.local.data_store
        for index in list(store):
            if not communication_only or 0x1000 <= index <= 0x1FFF:
                del store[index]
        if not communication_only:
            self.tpdos.process.clear()
            self.tpdos.carried.clear()
            self.errors.clear()
        return self.boot(t)

    def nmt(self, command: int, target: int, t: float | None = None) -> list[Frame]:
        """Apply an NMT command frame (command specifier, target node id; 0 = all)."""
        if self.before_change is not None:
            self.before_change()
        if self.silent or target not in (0, self.node_id) or self.state == INITIALISING:
            return []
        if command == NMT_START:
            if self.state != OPERATIONAL:
                self.tpdos.restart_counting()
            self._set_state(OPERATIONAL)
        elif command == NMT_STOP:
            self._set_state(STOPPED)
        elif command == NMT_PRE_OPERATIONAL:
            self._set_state(PRE_OPERATIONAL)
        elif command == NMT_RESET_NODE:
            return self.reset(False, t)
        elif command == NMT_RESET_COMM:
            return self.reset(True, t)
        return []

    # ---- heartbeat --------------------------------------------------------------------------
    def _heartbeat_ms(self) -> int:
        if 0x1017 not in self.od:
            return 0
        return self.tpdos.value(0x1017, 0)

    def _arm_heartbeat(self, t: float) -> None:
        self._heartbeat.arm(t, self._heartbeat_ms())

    @property
    def heartbeat_period_s(self) -> float:
        return self._heartbeat.period

    @property
    def next_heartbeat(self) -> float | None:
        return self._heartbeat.next

    def heartbeats(self, t: float) -> list[tuple[float, Frame]]:
        """Heartbeats due by time ``t``, each with its due time (none while INITIALISING;
        after a long gap at most one period's backlog: HeartbeatSchedule.due)."""
        if self.state == INITIALISING:
            return []
        dues = self._heartbeat.due(t)
        if not dues:
            return []
        frame = Frame("heartbeat", COB_HEARTBEAT + self.node_id, bytes([self.state]))
        return [(due, frame) for due in dues]

    # ---- process data and TPDOs -------------------------------------------------------------
    def update(self, values: Sequence[float] | dict[str, float]) -> None:
        """New measured values in engineering units (the device profile's channel order, or
        by name)."""
        items = values.items() if isinstance(values, dict) else zip(self.channel_names, values)
        chans = dict(self.channels)
        process = self.tpdos.process
        for ch, v in items:
            var = chans[ch]
            process[(var.index, var.subindex)] = encode_channel(self.role, ch, v, var)

    def set_raws(self, raws: Sequence[int | float]) -> None:
        """Raw bus values of every channel, in the profile's order (already encoded)."""
        process = self.tpdos.process
        for (ch, var), v in zip(self.channels, raws):
            process[(var.index, var.subindex)] = v

    def set_raw(self, channel: str, raw: int | float) -> None:
        """Set one channel's raw bus value directly (faults: a stuck or saturated channel)."""
        self.tpdos.process[self._channel_key[channel]] = raw

    def raw(self, channel: str) -> int | float | None:
        return self.tpdos.process.get(self._channel_key[channel])

    def tpdo_configs(self) -> list[TpdoConfig]:
        """The TPDO configuration as the dictionary holds it now (SDO writes included)."""
        return self.tpdos.configs()

    def sync(self, counter: int | None = None,
             carried: list[dict[tuple[int, int], int | float]] | None = None) -> list[Frame]:
        """React to one SYNC (with its counter byte, if any): the TPDOs due, in TPDO order.
        Only in OPERATIONAL. Transmission type 0 sends when the data changed; 1…240 every n-th
        SYNC (from the SYNC whose counter equals the SYNC start value, when one is set).

        ``carried``: a cycle built ahead of its SYNC collects what the TPDOs carry there (the
        caller applies it with ``carry()`` when the SYNC comes), so an SDO read in between
        still returns what the bus has carried so far."""
        if self.state != OPERATIONAL:
            return []
        return self.tpdos.sync(counter, carried)

    def carry(self, carried: list[dict[tuple[int, int], int | float]]) -> None:
        """What TPDOs built ahead of their SYNC (``sync(…, carried)``) carried, now sent."""
        for vals in carried:
            self.tpdos.carried.update(vals)

    def snapshot(self) -> tuple:
        """The state a SYNC cycle changes (process image, TPDO counting, errors), to undo a
        cycle built ahead of its SYNC that the SYNC cannot use (``restore``)."""
        return self.tpdos.snapshot(), dict(self.errors.active), self.errors.register

    def restore(self, snap: tuple) -> None:
        tpdos, active, register = snap
        self.tpdos.restore(tpdos)
        self.errors.active, self.errors.register = dict(active), register

    # ---- EMCY ---------------------------------------------------------------------------------
    @property
    def emcy_cob_id(self) -> int:
        if 0x1014 in self.od:
            return self.tpdos.value(0x1014, 0) & COB_ID_MASK
        return COB_EMCY_BASE + self.node_id

    @property
    def error_register(self) -> int:
        return self.errors.register

    def has_error(self, code: int) -> bool:
        """The error ``code`` is active (raised, not cleared)."""
        return code in self.errors.active

    def raise_error(self, code: int, register_bits: int = ERR_GENERIC,
                    info: bytes = b"") -> Frame:
        """An error appears: EMCY with the code, the updated error register and ``info``."""
        return self.errors.raise_error(self.emcy_cob_id, code, register_bits, info)

    def clear_error(self, code: int) -> Frame | None:
        """An error goes away; when none is left, the EMCY error reset (code 0x0000)."""
        return self.errors.clear_error(self.emcy_cob_id, code)

    # ---- SDO server hooks ---------------------------------------------------------------------
    def _on_sdo_read(self, index: int, subindex: int, od: ODVariable):
        if index == 0x1001:
            return self.errors.register
        return self.tpdos.carried.get((index, subindex))

    def _on_sdo_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        if 0x1A00 <= index <= 0x1BFF:
            self.tpdos.check_mapping_write(index, subindex, od, data)
        if 0x1800 <= index <= 0x1BFF:
            self.tpdos.remapped()  # re-read the maps at the next SYNC
        if index == 0x1017:
            # store first so _arm_heartbeat reads the new value
            self.local.data_store.setdefault(index, {})[subindex] = bytes(data)
            self._arm_heartbeat(self._clock())
