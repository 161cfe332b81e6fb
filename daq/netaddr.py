"""Whether a host a server binds to (or a browser names) is this machine's loopback: the one
test the shared bus (`rsra bus`), the Foxglove relay and the web gateway ask before they warn
that a wider bind lets other machines in."""
from __future__ import annotations

import ipaddress


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and a loopback address (``127.0.0.0/8``, ``::1``, an IPv6 one
    in URL brackets ``[::1]``, an IPv4-mapped ``::ffff:127.0.0.1``); False for anything else,
    the wildcard binds ``0.0.0.0`` and ``::`` and a name that would need a resolver included."""
    name = host.strip()
    if name.startswith("[") and name.endswith("]"):
        name = name[1:-1]
    if name.lower() == "localhost":
        return True
    try:
        addr = ipaddress.ip_address(name)
    except ValueError:
        return False
    mapped = getattr(addr, "ipv4_mapped", None)
    return bool(addr.is_loopback or (mapped is not None and mapped.is_loopback))
