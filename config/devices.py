"""The device profile of each sensor role (docs/bus.md §1 "Nodes"): which object of a node's
dictionary carries which channel, in which engineering unit, scaled how from the bus count,
and which CANopen data type the simulated node sends it as — the way a CiA 404/410 profile
fixes it for every vendor of a device class.

This table is the one place a role is described: the rig file's choice of roles
(config.rigfile), the reader's decode tables (daq.bus.decoder), the units of the DBC export
(daq.analysis.export) and the simulated nodes and their codec check (sim_bus.nodes,
sim_bus.nodeset) all read it. A new sensor role is one :class:`DeviceProfile` entry in
:data:`DEVICE_PROFILES` plus its EDS file. What is *not* fixed here is the node's COB-IDs and
TPDO layout: those come from the EDS, evaluated for the configured node id.

Everything is read from :data:`DEVICE_PROFILES` when used, never copied at import: a role
added to it (a test's monkeypatch included) is seen by every reader of the table.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from rsra.config.units import G0

MILLI_G = 1.0e-3 * G0  # accelerometers: 1 count = 1 mg of specific force, in m/s^2
TURN = "turn"  # marker: an unsigned angle that spans one turn (0 … 2^bits ↔ 0 … 2π)


@dataclass(frozen=True)
class ChannelProfile:
    """One channel of a role: ``value = scale · count`` in ``unit`` (before calibration)."""

    #: the channel's name ("<node>.<name>" in [calibration], fault specs and the DBC)
    name: str
    #: the device-profile object that carries it: index and sub-index
    index: int
    subindex: int
    #: engineering units per bus count; :data:`TURN` for an unsigned angle spanning one turn;
    #: None for a status byte (a bit field, never calibrated)
    scale: float | str | None
    #: the engineering unit, plain ASCII as a DBC file holds it ("" for a status byte)
    unit: str
    #: the CANopen basic data type (CiA 301 name, as in canopen.objectdictionary.datatypes)
    #: the simulated node encodes the channel to; the EDS must map the object with it
    data_type: str
    #: a rig whose EDS maps no such object is refused at load
    required: bool = True


@dataclass(frozen=True)
class DeviceProfile:
    """A sensor role: its channels in the order of the node's TPDO mapping entries."""

    #: the role's name (``role`` of a [[nodes]] block)
    role: str
    #: the channels, in mapping order (TPDO1 entry 1, 2, …, TPDO2 …)
    channels: tuple[ChannelProfile, ...]
    _by_object: dict[tuple[int, int], ChannelProfile] = field(init=False, repr=False,
                                                              compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_by_object",
                           {(c.index, c.subindex): c for c in self.channels})

    @property
    def names(self) -> tuple[str, ...]:
        """The channel names, in mapping order."""
        return tuple(c.name for c in self.channels)

    @property
    def required(self) -> tuple[str, ...]:
        """The channels a rig's EDS must map."""
        return tuple(c.name for c in self.channels if c.required)

    def at(self, index: int, subindex: int) -> ChannelProfile | None:
        """The channel object ``index``:``subindex`` carries (None: not one of the profile's)."""
        return self._by_object.get((index, subindex))

    def channel(self, name: str) -> ChannelProfile:
        """The channel called ``name`` (KeyError when the role has none)."""
        for c in self.channels:
            if c.name == name:
                return c
        raise KeyError(name)


def _balance() -> tuple[ChannelProfile, ...]:
    """The reference balance: the six hub-load components X, Y, Z (N) and L, M, N (N·m)."""
    return tuple(ChannelProfile(n, 0x2200, k, 1.0, "N" if k <= 3 else "Nm", "REAL32")
                 for k, n in enumerate("XYZLMN", start=1))


#: The device profile of every role, by role name (the rig file's choices, in this order).
DEVICE_PROFILES: dict[str, DeviceProfile] = {p.role: p for p in (
    DeviceProfile("load_cell", (
        ChannelProfile("force", 0x6130, 1, 1.0, "N", "REAL32"),
        # bit 0 over-range, bit 1 sensor fault
        ChannelProfile("status", 0x6150, 1, None, "", "UNSIGNED8"))),
    DeviceProfile("accelerometer", tuple(
        ChannelProfile(a, 0x6401, k, MILLI_G, "m/s^2", "INTEGER16")
        for k, a in enumerate("xyz", start=1))),
    DeviceProfile("rotor_speed", (
        ChannelProfile("omega", 0x2100, 1, 1.0, "rad/s", "REAL32"),
        ChannelProfile("azimuth", 0x2100, 2, TURN, "rad", "UNSIGNED16"))),
    DeviceProfile("balance", _balance()),
    DeviceProfile("drive_load", (
        ChannelProfile("torque", 0x2300, 1, 1.0, "Nm", "REAL32", required=False),)),
)}


def device_profile(role: str) -> DeviceProfile:
    """The profile of ``role`` (KeyError naming the known roles when there is none)."""
    try:
        return DEVICE_PROFILES[role]
    except KeyError:
        raise KeyError(f"unknown role {role!r} (one of {', '.join(DEVICE_PROFILES)})") from None
