"""The Ping360 messages of Blue Robotics' ping-protocol (sans-I/O).

One codec, two devices: the framing, the message table and the decoder are
:mod:`hilsim.protocols.ping_protocol` (shared with the Ping1D altimeter; its table holds the
Ping360 rows too, so one decoder knows every message as the protocol's own parsers do); this
module names the Ping360's ids and units, from bluerobotics/ping-protocol
``src/definitions/ping360.json``:

====  ======================  ==================================================================
id    name                    payload (little-endian)
====  ======================  ==================================================================
2000  ping360_set_device_id   u8 id, u8 reserved
2300  device_data             u8 mode, u8 gain_setting, u16 angle [grad], u16 transmit_duration [us],
                              u16 sample_period [25 ns], u16 transmit_frequency [kHz],
                              u16 number_of_samples, u16 data_length, u8[] data
2301  auto_device_data        device_data's head + u16 start_angle, u16 stop_angle, u8 num_steps,
                              u8 delay [ms], then u16 number_of_samples, u16 data_length, u8[] data
2600  reset                   u8 bootloader, u8 reserved
2601  transducer              u8 mode, u8 gain_setting, u16 angle, u16 transmit_duration,
                              u16 sample_period, u16 transmit_frequency, u16 number_of_samples,
                              u8 transmit, u8 reserved
2602  auto_transmit           u8 mode, u8 gain_setting, u16 transmit_duration, u16 sample_period,
                              u16 transmit_frequency, u16 number_of_samples, u16 start_angle,
                              u16 stop_angle, u8 num_steps, u8 delay
2903  motor_off               (empty)
====  ======================  ==================================================================

Angles are gradians 0-399 (400 per turn); ``sample_period`` is in ticks of 25 ns, so a sample
covers ``sample_period x 25 ns x c / 2`` of range. (The common ``set_device_id`` is id 100, so the
Ping360's own id 2000 is named ``ping360_set_device_id`` here.)
"""

from __future__ import annotations

from typing import Final


DEVICE_TYPE: Final = 2          # device_information.device_type of a Ping360 (common.json)
GRADIANS: Final = 400           # head positions per turn
TICK_S: Final = 25e-9           # [s] one sample_period unit
SAMPLES_MIN: Final = 200
SAMPLES_MAX: Final = 1200
SAMPLE_PERIOD_MIN: Final = 80
SAMPLE_PERIOD_MAX: Final = 40000

DEVICE_DATA: Final = 2300
AUTO_DEVICE_DATA: Final = 2301
RESET: Final = 2600
TRANSDUCER: Final = 2601
AUTO_TRANSMIT: Final = 2602
MOTOR_OFF: Final = 2903
SET_DEVICE_ID: Final = 2000

#: the ids a Ping360 answers as "get" messages (a general_request for them)
PING360_GET_IDS: Final = frozenset({4, 5, DEVICE_DATA})


def sample_spacing(sample_period: int, sound_speed: float) -> float:
    """[m] of range per sample for ``sample_period`` ticks of 25 ns at ``sound_speed`` [m/s]."""
    return sample_period * TICK_S * sound_speed / 2.0


def sample_period_for(range_m: float, samples: int, sound_speed: float) -> int:
    """The sample_period [ticks] that puts ``samples`` samples over ``range_m`` [m] (clamped to the
    device's 80..40000)."""
    ticks = round(2.0 * range_m / (samples * sound_speed * TICK_S))
    return int(min(max(ticks, SAMPLE_PERIOD_MIN), SAMPLE_PERIOD_MAX))
