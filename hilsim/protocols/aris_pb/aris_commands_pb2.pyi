from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Command(_message.Message):
    __slots__ = ("type", "dateTime", "frameStreamReceiver", "settings", "salinity", "focusPosition", "ping")
    class CommandType(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        SET_DATETIME: _ClassVar[Command.CommandType]
        SET_FRAMESTREAM_RECEIVER: _ClassVar[Command.CommandType]
        SET_FRAMESTREAM_SETTINGS: _ClassVar[Command.CommandType]
        SET_ACOUSTICS: _ClassVar[Command.CommandType]
        SET_SALINITY: _ClassVar[Command.CommandType]
        SET_TELEPHOTO: _ClassVar[Command.CommandType]
        SET_FOCUS: _ClassVar[Command.CommandType]
        FORCE_FOCUS: _ClassVar[Command.CommandType]
        HOME_FOCUS: _ClassVar[Command.CommandType]
        SET_ROTATOR_MOUNT: _ClassVar[Command.CommandType]
        SET_ROTATOR_VELOCITY: _ClassVar[Command.CommandType]
        SET_ROTATOR_ACCELERATION: _ClassVar[Command.CommandType]
        SET_ROTATOR_POSITION: _ClassVar[Command.CommandType]
        STOP_ROTATOR: _ClassVar[Command.CommandType]
        PING: _ClassVar[Command.CommandType]
        SET_SYSLOG_RECEIVER: _ClassVar[Command.CommandType]
        POWER_DOWN: _ClassVar[Command.CommandType]
    SET_DATETIME: Command.CommandType
    SET_FRAMESTREAM_RECEIVER: Command.CommandType
    SET_FRAMESTREAM_SETTINGS: Command.CommandType
    SET_ACOUSTICS: Command.CommandType
    SET_SALINITY: Command.CommandType
    SET_TELEPHOTO: Command.CommandType
    SET_FOCUS: Command.CommandType
    FORCE_FOCUS: Command.CommandType
    HOME_FOCUS: Command.CommandType
    SET_ROTATOR_MOUNT: Command.CommandType
    SET_ROTATOR_VELOCITY: Command.CommandType
    SET_ROTATOR_ACCELERATION: Command.CommandType
    SET_ROTATOR_POSITION: Command.CommandType
    STOP_ROTATOR: Command.CommandType
    PING: Command.CommandType
    SET_SYSLOG_RECEIVER: Command.CommandType
    POWER_DOWN: Command.CommandType
    class SetDateTime(_message.Message):
        __slots__ = ("dateTime",)
        DATETIME_FIELD_NUMBER: _ClassVar[int]
        dateTime: str
        def __init__(self, dateTime: _Optional[str] = ...) -> None: ...
    class SetFrameStreamReceiver(_message.Message):
        __slots__ = ("port", "ip")
        PORT_FIELD_NUMBER: _ClassVar[int]
        IP_FIELD_NUMBER: _ClassVar[int]
        port: int
        ip: str
        def __init__(self, port: _Optional[int] = ..., ip: _Optional[str] = ...) -> None: ...
    class SetAcousticSettings(_message.Message):
        __slots__ = ("cookie", "frameRate", "samplesPerBeam", "sampleStartDelay", "cyclePeriod", "samplePeriod", "pulseWidth", "pingMode", "enableTransmit", "frequency", "enable150Volts", "receiverGain")
        class Frequency(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
            __slots__ = ()
            LOW: _ClassVar[Command.SetAcousticSettings.Frequency]
            HIGH: _ClassVar[Command.SetAcousticSettings.Frequency]
        LOW: Command.SetAcousticSettings.Frequency
        HIGH: Command.SetAcousticSettings.Frequency
        COOKIE_FIELD_NUMBER: _ClassVar[int]
        FRAMERATE_FIELD_NUMBER: _ClassVar[int]
        SAMPLESPERBEAM_FIELD_NUMBER: _ClassVar[int]
        SAMPLESTARTDELAY_FIELD_NUMBER: _ClassVar[int]
        CYCLEPERIOD_FIELD_NUMBER: _ClassVar[int]
        SAMPLEPERIOD_FIELD_NUMBER: _ClassVar[int]
        PULSEWIDTH_FIELD_NUMBER: _ClassVar[int]
        PINGMODE_FIELD_NUMBER: _ClassVar[int]
        ENABLETRANSMIT_FIELD_NUMBER: _ClassVar[int]
        FREQUENCY_FIELD_NUMBER: _ClassVar[int]
        ENABLE150VOLTS_FIELD_NUMBER: _ClassVar[int]
        RECEIVERGAIN_FIELD_NUMBER: _ClassVar[int]
        cookie: int
        frameRate: float
        samplesPerBeam: int
        sampleStartDelay: int
        cyclePeriod: int
        samplePeriod: int
        pulseWidth: int
        pingMode: int
        enableTransmit: bool
        frequency: Command.SetAcousticSettings.Frequency
        enable150Volts: bool
        receiverGain: float
        def __init__(self, cookie: _Optional[int] = ..., frameRate: _Optional[float] = ..., samplesPerBeam: _Optional[int] = ..., sampleStartDelay: _Optional[int] = ..., cyclePeriod: _Optional[int] = ..., samplePeriod: _Optional[int] = ..., pulseWidth: _Optional[int] = ..., pingMode: _Optional[int] = ..., enableTransmit: _Optional[bool] = ..., frequency: _Optional[_Union[Command.SetAcousticSettings.Frequency, str]] = ..., enable150Volts: _Optional[bool] = ..., receiverGain: _Optional[float] = ...) -> None: ...
    class SetSalinity(_message.Message):
        __slots__ = ("salinity",)
        class Salinity(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
            __slots__ = ()
            FRESH: _ClassVar[Command.SetSalinity.Salinity]
            BRACKISH: _ClassVar[Command.SetSalinity.Salinity]
            SALTWATER: _ClassVar[Command.SetSalinity.Salinity]
        FRESH: Command.SetSalinity.Salinity
        BRACKISH: Command.SetSalinity.Salinity
        SALTWATER: Command.SetSalinity.Salinity
        SALINITY_FIELD_NUMBER: _ClassVar[int]
        salinity: Command.SetSalinity.Salinity
        def __init__(self, salinity: _Optional[_Union[Command.SetSalinity.Salinity, str]] = ...) -> None: ...
    class SetFocusPosition(_message.Message):
        __slots__ = ("position", "focusRange")
        POSITION_FIELD_NUMBER: _ClassVar[int]
        FOCUSRANGE_FIELD_NUMBER: _ClassVar[int]
        position: int
        focusRange: float
        def __init__(self, position: _Optional[int] = ..., focusRange: _Optional[float] = ...) -> None: ...
    class Ping(_message.Message):
        __slots__ = ()
        def __init__(self) -> None: ...
    TYPE_FIELD_NUMBER: _ClassVar[int]
    DATETIME_FIELD_NUMBER: _ClassVar[int]
    FRAMESTREAMRECEIVER_FIELD_NUMBER: _ClassVar[int]
    SETTINGS_FIELD_NUMBER: _ClassVar[int]
    SALINITY_FIELD_NUMBER: _ClassVar[int]
    FOCUSPOSITION_FIELD_NUMBER: _ClassVar[int]
    PING_FIELD_NUMBER: _ClassVar[int]
    type: Command.CommandType
    dateTime: Command.SetDateTime
    frameStreamReceiver: Command.SetFrameStreamReceiver
    settings: Command.SetAcousticSettings
    salinity: Command.SetSalinity
    focusPosition: Command.SetFocusPosition
    ping: Command.Ping
    def __init__(self, type: _Optional[_Union[Command.CommandType, str]] = ..., dateTime: _Optional[_Union[Command.SetDateTime, _Mapping]] = ..., frameStreamReceiver: _Optional[_Union[Command.SetFrameStreamReceiver, _Mapping]] = ..., settings: _Optional[_Union[Command.SetAcousticSettings, _Mapping]] = ..., salinity: _Optional[_Union[Command.SetSalinity, _Mapping]] = ..., focusPosition: _Optional[_Union[Command.SetFocusPosition, _Mapping]] = ..., ping: _Optional[_Union[Command.Ping, _Mapping]] = ...) -> None: ...
