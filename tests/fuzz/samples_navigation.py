"""Fuzz samples of the navigation sensors' codecs (Water Linked DVL JSON and serial commands,
NMEA 0183 sentences, ping-protocol packets), built from the vendors' documents and the codecs'
encoders; kept apart from ``samples.py`` so the entries stay one import."""

from __future__ import annotations

import struct

from hilsim.protocols import dvl_json as dj
from hilsim.protocols import dvl_serial as ds
from hilsim.protocols import nmea
from hilsim.protocols import ping_protocol as pp
from tests.fuzz.samples import Predicate, Sample, equals, filler


def _command(name: str, params: object = None) -> Predicate:
    return lambda ev: isinstance(ev, dj.Command) and ev.command == name and ev.parameters == params


def dvl_json_samples() -> list[Sample]:
    return [
        Sample(b'{"command": "get_config"}\n', _command("get_config"), "get_config (the document's line)"),
        Sample(b'{"command":"set_config","parameters":{"speed_of_sound":1480}}\n',
               _command("set_config", {"speed_of_sound": 1480}), "set_config speed of sound"),
        Sample(b'{"command":"trigger_ping"}\r\n', _command("trigger_ping"), "trigger_ping, CR LF"),
    ]


def dvl_serial_samples() -> list[Sample]:
    return [
        Sample(b"wcv\n", equals(ds.SerialCommand("v", ())), "wcv"),
        Sample(b"wcs,1450,,n,,,\r\n", equals(ds.SerialCommand("s", ("1450", "", "n", "", "", ""))),
               "wcs (the document's example)"),
        Sample(ds.packet("wcr"), equals(ds.SerialCommand("r", ())), "wcr with its CRC"),
    ]


def nmea_samples() -> list[Sample]:
    gga = nmea.gga("GP", 45296.78, 36.0106, 129.323, 1, 9, 0.9, 5.0, 40.0)
    return [
        Sample(gga, lambda ev: isinstance(ev, nmea.Sentence) and ev.kind == "GGA" and ev.fields[5] == "1", "GGA fix"),
        Sample(nmea.rmc("GN", None, None, False, None, None, 0.0, 0.0),
               lambda ev: isinstance(ev, nmea.Sentence) and ev.kind == "RMC" and ev.fields[1] == "V", "RMC void"),
        Sample(nmea.hdt("GN", 12.5), equals(nmea.Sentence("GN", "HDT", ("12.50", "T"))), "HDT"),
    ]


def ping_samples() -> list[Sample]:
    def msg(mid: int, fields: dict[str, object]) -> Predicate:
        return lambda ev: isinstance(ev, pp.Message) and ev.message_id == mid and ev.fields == fields

    return [
        Sample(pp.encode("general_request", {"requested_id": 1212}), msg(6, {"requested_id": 1212}),
               "general_request distance"),
        Sample(pp.encode("set_speed_of_sound", {"speed_of_sound": 1_482_000}), msg(1002, {"speed_of_sound": 1_482_000}),
               "set_speed_of_sound"),
        Sample(pp.encode(1211), msg(1211, {}), "legacy request of distance_simple (empty payload)"),
        Sample(pp.encode("continuous_start", {"id": 1300}), msg(1400, {"id": 1300}), "continuous_start profile"),
    ]


def ping_oversize() -> list[tuple[bytes, bytes]]:
    return [(b"BR" + struct.pack("<HHBB", 0xFFFF, 1300, 0, 0), filler()),
            (b"BR" + struct.pack("<HHBB", pp.MAX_PAYLOAD, 1300, 0, 0), filler())]
