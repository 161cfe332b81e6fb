"""PDO decode tables built from the EDS mapping (docs/bus.md §1 "Nodes", §2 "SYNC and samples").

Nothing here is hard-coded per rig: every COB-ID, frame layout and data type comes from the
EDS default of each node's TPDO communication (0x1800+n) and mapping (0x1A00+n) parameters,
evaluated for the node id of the rig config, and every gain/offset from
``cfg.calibration["<node>.<channel>"]``. What *is* fixed is the device profile of each role
(which mapped object is which physical channel and its unit: config.devices), the same way a
CiA 404/410 profile fixes it for every vendor.

One precompiled little-endian :class:`struct.Struct` per COB-ID (CANopen is little-endian),
and one for a whole sample (every TPDO's frame, joined in bit order): the hot path keeps the
frame per TPDO and unpacks once per sample (see daq.assembler).
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path

import canopen
import numpy as np
from canopen.objectdictionary import ODVariable, datatypes

from rsra.config.devices import TURN, device_profile
from rsra.config.rig import ConfigError, RigConfig
from rsra.config.rigfile import predefined_cob_ids

# CANopen basic data types -> struct codes (CiA 301 §7.1.4); the bit length in the mapping
# entry must agree with the type.
_STRUCT_CODE = {
    datatypes.BOOLEAN: "?", datatypes.INTEGER8: "b", datatypes.INTEGER16: "h",
    datatypes.INTEGER32: "i", datatypes.INTEGER64: "q", datatypes.UNSIGNED8: "B",
    datatypes.UNSIGNED16: "H", datatypes.UNSIGNED32: "I", datatypes.UNSIGNED64: "Q",
    datatypes.REAL32: "f", datatypes.REAL64: "d",
}
_UNSIGNED = (datatypes.UNSIGNED8, datatypes.UNSIGNED16, datatypes.UNSIGNED32, datatypes.UNSIGNED64)

# Status bits of a load cell (docs/bus.md §1: 0x6150:1 bit 0 over-range, bit 1 sensor fault).
STATUS_OVERRANGE = 0x01
STATUS_FAULT = 0x02

TPDO_COMM = 0x1800
TPDO_MAP = 0x1A00
MAX_TPDOS = 512  # CiA 301: 0x1800…0x19FF
COB_INVALID = 1 << 31  # PDO does not exist / is not valid
COB_EXTENDED = 1 << 29
COB_MASK_11BIT = 0x7FF


@dataclass(frozen=True)
class Channel:
    """One decoded value: ``value = gain * (scale * raw) + offset`` (engineering units)."""

    key: str  # "<node>.<channel>"
    node: str
    name: str
    index: int
    subindex: int
    scale: float
    gain: float  # calibration gain (config), 1 when absent
    offset: float  # calibration offset (config), engineering units
    is_status: bool
    wrap: float | None  # 2π for angles that span one turn


@dataclass(frozen=True)
class TpdoLayout:
    """One TPDO of one node as the EDS describes it."""

    node: str
    node_index: int  # position in DecodeTable.nodes
    number: int  # 1-based TPDO number
    cob_id: int
    transmission_type: int
    mapping: tuple[int, ...]  # raw 0x1A00+n entries (index<<16 | sub<<8 | bits)
    struct: struct.Struct
    codes: str  # struct code of each mapped value (no padding)
    length: int  # bytes the frame must carry
    start: int  # first channel of this TPDO in the raw vector
    stop: int
    bit: int  # this TPDO's bit in the per-sample "reported" mask


@dataclass(frozen=True)
class NodeLayout:
    name: str
    role: str
    node_id: int
    required: bool
    eds: Path
    od: canopen.ObjectDictionary
    tpdos: tuple[TpdoLayout, ...]
    start: int  # channel slice of this node
    stop: int
    mask: int  # OR of its TPDO bits
    device_type: int  # EDS default of 0x1000
    identity: dict[int, int]  # EDS defaults of 0x1018:1…4 (vendor, product, revision, serial)


def od_variable(od: canopen.ObjectDictionary, index: int, sub: int) -> ODVariable:
    """Object ``index``:``sub`` of an object dictionary, a plain variable being its own
    sub-index 0. KeyError where the dictionary does not define it; TypeError for a
    sub-index of a plain variable (a damaged EDS)."""
    obj = od[index]
    if isinstance(obj, ODVariable):
        if sub:
            raise TypeError(f"0x{index:04X} is a plain variable: it has no sub-index {sub}")
        return obj
    return obj[sub]


def _default(od: canopen.ObjectDictionary, index: int, sub: int | None = None) -> int | None:
    try:
        obj = od[index]
        if sub is None:
            var = obj
        elif isinstance(obj, ODVariable):  # a sub-index of a plain variable (bad EDS)
            return None
        else:
            var = obj[sub]
    except (KeyError, TypeError):
        return None
    if not isinstance(var, ODVariable):
        return None
    return var.default


def _mapping_struct(node: str, role: str, od: canopen.ObjectDictionary, n: int,
                    entries: list[int]) -> tuple[str, list[tuple[int, int, int]]]:
    """Struct format and the (index, sub, data_type) of each mapped value, in frame order."""
    fmt = "<"
    values = []
    for e in entries:
        index, sub, bits = e >> 16, (e >> 8) & 0xFF, e & 0xFF
        if 0x0001 <= index <= 0x0007:  # dummy mapping: padding of the type's size
            if bits % 8:
                raise ConfigError(f"eds[{node}] 0x{TPDO_MAP + n - 1:04X}", hex(e),
                                  "dummy entry not a whole number of bytes",
                                  "map whole bytes (Granularity=8)")
            fmt += f"{bits // 8}x"
            continue
        try:
            var = od_variable(od, index, sub)
        except (KeyError, TypeError):  # TypeError: a sub-index of a plain variable
            raise ConfigError(f"eds[{node}] 0x{TPDO_MAP + n - 1:04X}", f"0x{e:08X}",
                              f"maps object 0x{index:04X}:{sub} that the EDS does not define",
                              "fix the mapping or add the object to the EDS") from None
        dtype = var.data_type
        code = None if dtype is None else _STRUCT_CODE.get(dtype)
        if dtype is None or code is None or struct.calcsize("<" + code) * 8 != bits:
            raise ConfigError(f"eds[{node}] 0x{TPDO_MAP + n - 1:04X}", f"0x{e:08X}",
                              f"object 0x{index:04X}:{sub} of type 0x{dtype:04X} "
                              f"cannot be mapped with {bits} bits",
                              "map numeric objects with their full bit length")
        fmt += code
        values.append((index, sub, dtype))
    return fmt, values


def _check_cob_clashes(cfg: RigConfig, tpdos: dict[int, "TpdoLayout"]) -> None:
    """Every TPDO COB-ID the EDS files give against the SYNC and every node's NMT, EMCY, SDO
    and heartbeat COB-ID: two uses of one COB-ID are indistinguishable on the bus (a SYNC
    taken for a TPDO, or the reverse, and no sample is ever assembled)."""
    fixed = {cfg.sync.cob_id: "the SYNC (sync.cob_id)"}
    for nc in cfg.nodes:
        for cob, use in predefined_cob_ids(nc.node_id).items():
            if not use.startswith(("TPDO", "RPDO")):
                fixed.setdefault(cob, f"the {use} of node {nc.name!r}")
    for cob, lay in tpdos.items():
        if cob in fixed:
            key = "sync.cob_id" if cob == cfg.sync.cob_id else f"eds[{lay.node}]"
            raise ConfigError(key, hex(cob), f"{lay.node} TPDO{lay.number} COB-ID 0x{cob:03X} is "
                              f"also {fixed[cob]}", "give every COB-ID one use (sync.cob_id = "
                              "0x80, the CANopen default, and the nodes' predefined COB-IDs)")


class DecodeTable:
    """Every TPDO of every configured node: layouts, channel list and calibration vectors.

    The raw vector of one sample holds every channel of every node, node after node, TPDO
    after TPDO, in mapping order; ``gain``/``offset`` calibrate it in one vector operation.
    """

    def __init__(self, cfg: RigConfig):
        self.cfg = cfg
        nodes: list[NodeLayout] = []
        channels: list[Channel] = []
        tpdos: dict[int, TpdoLayout] = {}
        bit = 1
        used_cal: set[str] = set()
        ni = 0
        try:
            for ni, nc in enumerate(cfg.nodes):
                try:
                    od = canopen.import_od(str(nc.eds), nc.node_id)
                except Exception as e:  # canopen raises assorted errors on a bad EDS
                    why = " ".join(str(e).split())  # one line: configparser's text spans several
                    raise ConfigError(f"nodes[{ni}].eds", str(nc.eds), f"cannot be read ({why})",
                                      "give a valid CiA 306 EDS file") from None
                profile = device_profile(nc.role)
                node_start = len(channels)
                node_tpdos = []
                node_mask = 0
                for n in range(1, MAX_TPDOS + 1):
                    if TPDO_COMM + n - 1 not in od:
                        continue
                    cob = _default(od, TPDO_COMM + n - 1, 1)
                    if cob is None:
                        continue
                    if cob & COB_INVALID:
                        continue  # PDO disabled by default: not part of the samples
                    if cob & COB_EXTENDED:
                        raise ConfigError(f"eds[{nc.name}] 0x{TPDO_COMM + n - 1:04X}:1", hex(cob),
                                          "29-bit COB-IDs are not used on this bus",
                                          "use an 11-bit COB-ID")
                    ttype = _default(od, TPDO_COMM + n - 1, 2)
                    if ttype != 1:
                        raise ConfigError(f"eds[{nc.name}] 0x{TPDO_COMM + n - 1:04X}:2", ttype,
                                          "samples are assembled per SYNC (docs/bus.md §2): every TPDO must "
                                          "have transmission type 1", "set the default to 1")
                    count = _default(od, TPDO_MAP + n - 1, 0) or 0
                    entries = [_default(od, TPDO_MAP + n - 1, s) or 0 for s in range(1, count + 1)]
                    fmt, values = _mapping_struct(nc.name, nc.role, od, n, entries)
                    st = struct.Struct(fmt)
                    if st.size > 8:
                        raise ConfigError(f"eds[{nc.name}] 0x{TPDO_MAP + n - 1:04X}", fmt,
                                          f"maps {st.size} bytes, a classic CAN frame carries 8",
                                          "split the mapping over two TPDOs")
                    start = len(channels)
                    for index, sub, dtype in values:
                        known = profile.at(index, sub)  # an object outside the profile:
                        name, scale = (known.name, known.scale) if known else (  # by its address
                            f"0x{index:04X}_{sub}", 1.0)
                        key = f"{nc.name}.{name}"
                        gain, offset = cfg.calibration.get(key, (1.0, 0.0))
                        wrap = None
                        if scale is None:
                            if key in cfg.calibration:
                                raise ConfigError(f"calibration.{key}", cfg.calibration[key],
                                                  "a status byte is a bit field, not a measurement",
                                                  "remove the entry")
                            scale_f = 1.0
                        elif scale == TURN:
                            if dtype not in _UNSIGNED:
                                raise ConfigError(f"eds[{nc.name}] 0x{index:04X}:{sub}", hex(dtype),
                                                  "an angle spanning one turn must be unsigned",
                                                  "map an UNSIGNED8/16/32 object")
                            bits = 8 * struct.calcsize("<" + _STRUCT_CODE[dtype])
                            scale_f = 2.0 * math.pi / 2.0**bits
                            wrap = 2.0 * math.pi
                        else:
                            scale_f = float(scale)
                        used_cal.add(key)
                        channels.append(Channel(key=key, node=nc.name, name=name, index=index,
                                                subindex=sub, scale=scale_f, gain=float(gain),
                                                offset=float(offset), is_status=scale is None,
                                                wrap=wrap))
                    cob11 = cob & COB_MASK_11BIT
                    if cob11 in tpdos:
                        other = tpdos[cob11]
                        raise ConfigError(f"nodes[{ni}]", nc.name,
                                          f"TPDO{n} COB-ID 0x{cob11:03X} already used by "
                                          f"{other.node} TPDO{other.number}",
                                          "give every node its own node id / COB-IDs")
                    lay = TpdoLayout(node=nc.name, node_index=ni, number=n, cob_id=cob11,
                                     transmission_type=ttype, mapping=tuple(entries), struct=st,
                                     codes="".join(_STRUCT_CODE[d] for _, _, d in values),
                                     length=st.size, start=start, stop=len(channels), bit=bit)
                    tpdos[cob11] = lay
                    node_tpdos.append(lay)
                    node_mask |= bit
                    bit <<= 1
                names = {c.name for c in channels[node_start:]}
                for need in profile.required:
                    if need not in names:
                        raise ConfigError(f"nodes[{ni}].eds", str(nc.eds),
                                          f"no TPDO maps the {nc.role} channel {need!r}",
                                          "use the EDS of the role's device profile (docs/bus.md §1)")
                identity = {s: _default(od, 0x1018, s) for s in (1, 2, 3, 4)}
                nodes.append(NodeLayout(
                    name=nc.name, role=nc.role, node_id=nc.node_id, required=nc.required,
                    eds=Path(nc.eds), od=od, tpdos=tuple(node_tpdos), start=node_start,
                    stop=len(channels), mask=node_mask, device_type=_default(od, 0x1000) or 0,
                    identity={k: v for k, v in identity.items() if v is not None}))
        except ConfigError:
            raise
        except Exception as e:  # anything else a damaged EDS provokes: name the file
            nc = cfg.nodes[ni]
            why = " ".join(f"{type(e).__name__}: {e}".split())
            raise ConfigError(f"nodes[{ni}].eds", str(nc.eds), f"cannot be used ({why})",
                              "give a valid CiA 306 EDS file") from None
        for key in cfg.calibration:
            if key not in used_cal:
                raise ConfigError(f"calibration.{key}", cfg.calibration[key],
                                  "no such channel", "use one of: " + ", ".join(
                                      c.key for c in channels if not c.is_status))
        _check_cob_clashes(cfg, tpdos)
        self.nodes: tuple[NodeLayout, ...] = tuple(nodes)
        self.channels: tuple[Channel, ...] = tuple(channels)
        self.tpdos: dict[int, TpdoLayout] = tpdos
        self.all_bits = bit - 1
        # TPDOs in bit order, which is also channel order (both follow the EDS scan above):
        # the frames of one sample joined in this order unpack with ONE struct into the raw
        # vector (the assembler keeps the frames and unpacks once per sample, not per frame)
        self.layouts: tuple[TpdoLayout, ...] = tuple(sorted(tpdos.values(),
                                                            key=lambda lay: lay.bit))
        self.sample_struct = struct.Struct(
            "<" + "".join(lay.struct.format.lstrip("<") for lay in self.layouts))
        self.zero_frames: tuple[bytes, ...] = tuple(bytes(lay.length) for lay in self.layouts)
        # value = gain*scale*raw + offset, one multiply-add per sample (status: identity)
        self.gain = np.array([c.gain * c.scale for c in channels])
        self.offset = np.array([c.offset for c in channels])
        self._index = {c.key: i for i, c in enumerate(channels)}
        self._node = {n.name: n for n in nodes}

    # -- lookups ---------------------------------------------------------------------------
    def index(self, key: str) -> int:
        """Position of channel "<node>.<channel>" in the raw vector."""
        return self._index[key]

    def node(self, name: str) -> NodeLayout:
        return self._node[name]

    def has_channel(self, key: str) -> bool:
        return key in self._index

    @property
    def n_channels(self) -> int:
        return len(self.channels)

    # -- decoding (tests, tools; the hot path inlines the same steps) ----------------------
    def decode(self, cob_id: int, data: bytes) -> dict[str, float]:
        """Calibrated values of one TPDO frame by channel key (raises on unknown/malformed)."""
        lay = self.tpdos[cob_id]
        if len(data) != lay.length:
            raise ValueError(f"COB-ID 0x{cob_id:03X}: {len(data)} bytes, expected {lay.length}")
        raw = lay.struct.unpack(data)
        out = {}
        for i, v in zip(range(lay.start, lay.stop), raw):
            c = self.channels[i]
            x = float(v) if c.is_status else self.gain[i] * float(v) + self.offset[i]
            out[c.key] = x
        return out

    def encode(self, values: dict[str, float], cob_id: int) -> bytes:
        """Inverse of :meth:`decode` for one TPDO (tests, tools): engineering values -> frame."""
        lay = self.tpdos[cob_id]
        raw = []
        for i in range(lay.start, lay.stop):
            c = self.channels[i]
            v = values[c.key]
            if c.is_status:
                raw.append(int(v))
                continue
            r = (v - self.offset[i]) / self.gain[i]
            code = lay.codes[i - lay.start]
            if code in "fd":
                raw.append(r)
            else:
                lo, hi = _int_range(code)
                r = round(r)
                if c.wrap is not None:
                    r %= hi + 1
                raw.append(min(max(r, lo), hi))
        return lay.struct.pack(*raw)


def _int_range(code: str) -> tuple[int, int]:
    bits = 8 * struct.calcsize("<" + code)
    if code.islower() and code != "?":
        return -(2 ** (bits - 1)), 2 ** (bits - 1) - 1
    return 0, 2**bits - 1


