"""The CAN bus a CAN device attaches to: its options checked, and one bus per (transport, channel,
port or pty path), shared by every device naming it."""

from __future__ import annotations

from typing import Any, Mapping

from hilsim.devices.context import DeviceContext, OptionError
from hilsim.links.can import CanBus, bus_class

CAN_TRANSPORTS = ("socketcand", "slcan", "socketcan", "virtual")


def check_can_options(device: Any) -> None:
    """OptionError for a CAN device's transport options that cannot work (at construction time)."""
    options = device.options
    transport = options["transport"]
    if transport not in CAN_TRANSPORTS:
        raise device.option_error("transport", f"transport {transport!r} is not one of {', '.join(CAN_TRANSPORTS)}")
    if not isinstance(options["channel"], str) or not options["channel"]:
        raise device.option_error("channel", "channel must be a bus name such as 'can0'")
    if transport == "socketcand":
        device.option_int("port", 0, 65535)
    bitrate = options.get("bitrate")
    if bitrate is not None and not (isinstance(bitrate, int) and not isinstance(bitrate, bool) and bitrate > 0):
        raise device.option_error("bitrate", f"bitrate must be a positive number of bit/s, got {bitrate!r}")
    device.option_int("max_clients", 1, 10_000)
    device.option_number("evict_grace_s", 0.0)


def bus_location(ctx: DeviceContext, options: Mapping[str, Any]) -> Any:
    """What tells one bus of a transport from another: the socketcand port, the slcan pty path
    (inside the run folder; OptionError "path" for one that leaves it), the interface name."""
    transport = str(options["transport"])
    channel = str(options["channel"])
    if transport == "socketcand":
        return int(options["port"])
    if transport == "slcan":
        try:
            return str(ctx.pty_path(options["path"], f"slcan-{channel}"))
        except (TypeError, ValueError) as exc:
            raise OptionError("path", str(exc)) from None
    return channel


async def acquire_bus(ctx: DeviceContext, device: str, options: Mapping[str, Any]) -> CanBus:
    """The CAN bus named by the device's options (checked by :func:`check_can_options` when the
    device was built), shared with every device naming the same (transport, channel, port or path)."""
    transport = str(options["transport"])
    channel = str(options["channel"])
    bitrate = int(options["bitrate"]) if options.get("bitrate") else None
    where = bus_location(ctx, options)
    kw: dict[str, Any] = {"channel": channel}
    if transport == "socketcand":
        kw.update(host=ctx.bind, port=where, bitrate=bitrate, max_clients=int(options["max_clients"]),
                  evict_grace=float(options["evict_grace_s"]))
    elif transport == "slcan":
        kw.update(path=where, bitrate=bitrate)
    cls = bus_class(transport)

    async def make() -> CanBus:
        bus = cls(f"{transport}:{channel}", **kw)
        await bus.start()
        return bus
    return await ctx.shared(("can", transport, channel, where), make)


