"""Valid Ping360 packets for the fuzz table, from bluerobotics/ping-protocol's ping360.json."""

from __future__ import annotations

from hilsim.protocols import ping_protocol as pp
from tests.fuzz.samples import Sample


def ping360_samples() -> list[Sample]:
    def msg(mid: int, **fields: object):
        return lambda ev: isinstance(ev, pp.Message) and ev.message_id == mid and ev.fields == fields

    transducer = dict(mode=1, gain_setting=0, angle=100, transmit_duration=11, sample_period=88,
                      transmit_frequency=750, number_of_samples=1200, transmit=1, reserved=0)
    auto = dict(mode=1, gain_setting=1, transmit_duration=32, sample_period=200, transmit_frequency=740,
                number_of_samples=600, start_angle=0, stop_angle=399, num_steps=1, delay=0)
    return [
        Sample(pp.encode("transducer", transducer), msg(2601, **transducer), "transducer at 100 grad"),
        Sample(pp.encode("auto_transmit", auto), msg(2602, **auto), "auto_transmit, full turn"),
        Sample(pp.encode("motor_off", {}), msg(2903), "motor_off"),
        Sample(pp.encode("general_request", {"requested_id": 2300}), msg(6, requested_id=2300),
               "general_request device_data"),
    ]
