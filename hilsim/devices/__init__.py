"""Emulated devices: a profile + a codec + a link, bound to the simulation.

Device classes load lazily from :data:`REGISTRY` (protocol name -> "module:Class"),
as python-can loads its interfaces, so a scenario only imports what it uses.
"""

from __future__ import annotations

import importlib

from hilsim.devices.base import Device, OptionError

__all__ = ["Device", "OptionError", "REGISTRY", "device_class"]

REGISTRY: dict[str, str] = {
    "ddf-stream": "hilsim.devices.ddf_stream:DdfStreamDevice",
    "oculus": "hilsim.devices.oculus:OculusDevice",
    "aris": "hilsim.devices.aris:ArisDevice",
    "vesc-can": "hilsim.devices.vesc_can:VescCanDevice",
    "dronecan": "hilsim.devices.dronecan_esc:DroneCanEscDevice",
    "vesc-uart": "hilsim.devices.vesc_uart:VescUartDevice",
    "vrcsr": "hilsim.devices.vrcsr:VrcsrDevice",
    "modbus-keller": "hilsim.devices.modbus_sensor:KellerDevice",
    "modbus-witmotion": "hilsim.devices.modbus_sensor:WitMotionDevice",
    "ardupilot-json": "hilsim.devices.ardupilot_json:ArdupilotJsonDevice",
    "dvl-a50": "hilsim.devices.dvl:DvlDevice",
    "nmea-gnss": "hilsim.devices.gnss:GnssDevice",
    "ping1d": "hilsim.devices.ping1d:Ping1dDevice",
    "ping360": "hilsim.devices.ping360:Ping360Device",
}


def device_class(protocol: str) -> type[Device]:
    """The device class for a protocol name; KeyError lists the known ones."""
    if protocol not in REGISTRY:
        import difflib

        close = difflib.get_close_matches(protocol, list(REGISTRY), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise KeyError(f"unknown device protocol {protocol!r}{hint} (known: {', '.join(sorted(REGISTRY))})")
    module, _, cls = REGISTRY[protocol].partition(":")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        raise KeyError(f"device protocol {protocol!r} is not available in this build ({exc})") from None
    return getattr(mod, cls)  # type: ignore[no-any-return]
