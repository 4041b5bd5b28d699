"""Who can reach a server of hil: this machine only, or any machine that reaches this one.

hil's servers (the live view, the emulators' Modbus TCP and socketcand) bind to 127.0.0.1
unless asked. One asked to listen beyond loopback says so in one line when it starts
(:func:`exposure`), and the live view keeps its parameters read-only there unless the run
allows otherwise (:mod:`hil.core.recording.live`).
"""

from __future__ import annotations

import ipaddress
import socket


def beyond_loopback(host: str) -> bool:
    """Whether a server listening on ``host`` can be reached from another machine: any host
    but a loopback address (all of 127.0.0.0/8, ``::1``) or a name that resolves to loopback
    addresses only (``localhost``). The wildcards ``0.0.0.0`` and ``::`` listen on every
    interface; a name that does not resolve counts as beyond."""
    try:
        return not _loopback(host)
    except ValueError:
        pass
    try:
        found = socket.getaddrinfo(host, None, proto=socket.IPPROTO_TCP)
    except (OSError, UnicodeError):
        return True
    return not found or not all(_loopback(str(info[4][0])) for info in found)


def _loopback(address: str) -> bool:
    """``address`` (an IPv4 or IPv6 literal, an IPv4-mapped one included) is on loopback."""
    ip = ipaddress.ip_address(address.partition("%")[0])
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        return ip.ipv4_mapped.is_loopback
    return ip.is_loopback


def exposure(server: str, host: str, reach: str) -> str | None:
    """The one-line warning of ``server`` (``"the live view on ws://0.0.0.0:8765"``) listening
    on ``host``: what any machine that reaches this one may do there (``reach``); None when
    ``host`` is on loopback."""
    if not beyond_loopback(host):
        return None
    return (f"{server} listens beyond loopback: any machine that reaches this one may "
            f"{reach} (a 127.0.0.1 address keeps it to this machine)")
