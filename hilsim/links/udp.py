"""UDP sockets for datagrams a device sends (status, beacons, frame parts) and receives."""

from __future__ import annotations

import asyncio


async def open_udp(bind: str) -> asyncio.DatagramTransport:
    """A UDP socket on ``bind`` (any port) for a device's outgoing datagrams (a sonar's status or
    beacon, frame parts). Broadcast is allowed on it, for a user who names a LAN broadcast address."""
    transport, _ = await asyncio.get_running_loop().create_datagram_endpoint(
        asyncio.DatagramProtocol, local_addr=(bind, 0), allow_broadcast=True)
    return transport
