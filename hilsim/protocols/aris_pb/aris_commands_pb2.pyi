from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Command(_message.Message):
    __slots__ = ("type", "dateTime", "frameStreamReceiver", "frameStreamSettings", "settings", "salinity", "telephoto", "focusPosition", "focusForce", "focusHome", "mount", "rotatorVelocity", "rotatorAcceleration", "rotatorPosition", "rotatorStop", "ping", "syslogReceiver", "powerDown", "reserved1")
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
        RESERVED_1: _ClassVar[Command.CommandType]
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
    RESERVED_1: Command.CommandType
    class Axis(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        PAN: _ClassVar[Command.Axis]
        ROLL: _ClassVar[Command.Axis]
        TILT: _ClassVar[Command.Axis]
    PAN: Command.Axis
    ROLL: Command.Axis
    TILT: Command.Axis
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
    class SetFrameStreamSettings(_message.Message):
        __slots__ = ("interpacketDelay", "packetLossMitigation")
        class PacketLossMitigation(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
            __slots__ = ()
            DROP_PARTIAL_FRAMES: _ClassVar[Command.SetFrameStreamSettings.PacketLossMitigation]
            PESSIMISTIC_RETRY: _ClassVar[Command.SetFrameStreamSettings.PacketLossMitigation]
        DROP_PARTIAL_FRAMES: Command.SetFrameStreamSettings.PacketLossMitigation
        PESSIMISTIC_RETRY: Command.SetFrameStreamSettings.PacketLossMitigation
        INTERPACKETDELAY_FIELD_NUMBER: _ClassVar[int]
        PACKETLOSSMITIGATION_FIELD_NUMBER: _ClassVar[int]
        interpacketDelay: Command.SetInterpacketDelay
        packetLossMitigation: Command.SetFrameStreamSettings.PacketLossMitigation
        def __init__(self, interpacketDelay: _Optional[_Union[Command.SetInterpacketDelay, _Mapping]] = ..., packetLossMitigation: _Optional[_Union[Command.SetFrameStreamSettings.PacketLossMitigation, str]] = ...) -> None: ...
    class SetInterpacketDelay(_message.Message):
        __slots__ = ("enable", "delayPeriod")
        ENABLE_FIELD_NUMBER: _ClassVar[int]
        DELAYPERIOD_FIELD_NUMBER: _ClassVar[int]
        enable: bool
        delayPeriod: int
        def __init__(self, enable: _Optional[bool] = ..., delayPeriod: _Optional[int] = ...) -> None: ...
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
    class SetTelephotoLens(_message.Message):
        __slots__ = ("telephoto",)
        TELEPHOTO_FIELD_NUMBER: _ClassVar[int]
        telephoto: bool
        def __init__(self, telephoto: _Optional[bool] = ...) -> None: ...
    class SetFocusPosition(_message.Message):
        __slots__ = ("position", "focusRange")
        POSITION_FIELD_NUMBER: _ClassVar[int]
        FOCUSRANGE_FIELD_NUMBER: _ClassVar[int]
        position: int
        focusRange: float
        def __init__(self, position: _Optional[int] = ..., focusRange: _Optional[float] = ...) -> None: ...
    class ForceFocus(_message.Message):
        __slots__ = ("direction",)
        class Direction(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
            __slots__ = ()
            INVALID0: _ClassVar[Command.ForceFocus.Direction]
            FORWARD: _ClassVar[Command.ForceFocus.Direction]
            REVERSE: _ClassVar[Command.ForceFocus.Direction]
        INVALID0: Command.ForceFocus.Direction
        FORWARD: Command.ForceFocus.Direction
        REVERSE: Command.ForceFocus.Direction
        DIRECTION_FIELD_NUMBER: _ClassVar[int]
        direction: Command.ForceFocus.Direction
        def __init__(self, direction: _Optional[_Union[Command.ForceFocus.Direction, str]] = ...) -> None: ...
    class HomeFocus(_message.Message):
        __slots__ = ()
        def __init__(self) -> None: ...
    class SetRotatorMount(_message.Message):
        __slots__ = ("mount",)
        class Mount(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
            __slots__ = ()
            POLE: _ClassVar[Command.SetRotatorMount.Mount]
            TRIPOD: _ClassVar[Command.SetRotatorMount.Mount]
            ROV: _ClassVar[Command.SetRotatorMount.Mount]
        POLE: Command.SetRotatorMount.Mount
        TRIPOD: Command.SetRotatorMount.Mount
        ROV: Command.SetRotatorMount.Mount
        MOUNT_FIELD_NUMBER: _ClassVar[int]
        mount: Command.SetRotatorMount.Mount
        def __init__(self, mount: _Optional[_Union[Command.SetRotatorMount.Mount, str]] = ...) -> None: ...
    class SetRotatorVelocity(_message.Message):
        __slots__ = ("axis", "velocity")
        AXIS_FIELD_NUMBER: _ClassVar[int]
        VELOCITY_FIELD_NUMBER: _ClassVar[int]
        axis: Command.Axis
        velocity: float
        def __init__(self, axis: _Optional[_Union[Command.Axis, str]] = ..., velocity: _Optional[float] = ...) -> None: ...
    class SetRotatorAcceleration(_message.Message):
        __slots__ = ("axis", "acceleration")
        AXIS_FIELD_NUMBER: _ClassVar[int]
        ACCELERATION_FIELD_NUMBER: _ClassVar[int]
        axis: Command.Axis
        acceleration: float
        def __init__(self, axis: _Optional[_Union[Command.Axis, str]] = ..., acceleration: _Optional[float] = ...) -> None: ...
    class SetRotatorPosition(_message.Message):
        __slots__ = ("axis", "position")
        AXIS_FIELD_NUMBER: _ClassVar[int]
        POSITION_FIELD_NUMBER: _ClassVar[int]
        axis: Command.Axis
        position: float
        def __init__(self, axis: _Optional[_Union[Command.Axis, str]] = ..., position: _Optional[float] = ...) -> None: ...
    class StopRotator(_message.Message):
        __slots__ = ("axis",)
        AXIS_FIELD_NUMBER: _ClassVar[int]
        axis: Command.Axis
        def __init__(self, axis: _Optional[_Union[Command.Axis, str]] = ...) -> None: ...
    class Ping(_message.Message):
        __slots__ = ()
        def __init__(self) -> None: ...
    class SetSyslogReceiver(_message.Message):
        __slots__ = ("ip",)
        IP_FIELD_NUMBER: _ClassVar[int]
        ip: str
        def __init__(self, ip: _Optional[str] = ...) -> None: ...
    class PowerDown(_message.Message):
        __slots__ = ()
        def __init__(self) -> None: ...
    class Reserved1(_message.Message):
        __slots__ = ()
        def __init__(self) -> None: ...
    TYPE_FIELD_NUMBER: _ClassVar[int]
    DATETIME_FIELD_NUMBER: _ClassVar[int]
    FRAMESTREAMRECEIVER_FIELD_NUMBER: _ClassVar[int]
    FRAMESTREAMSETTINGS_FIELD_NUMBER: _ClassVar[int]
    SETTINGS_FIELD_NUMBER: _ClassVar[int]
    SALINITY_FIELD_NUMBER: _ClassVar[int]
    TELEPHOTO_FIELD_NUMBER: _ClassVar[int]
    FOCUSPOSITION_FIELD_NUMBER: _ClassVar[int]
    FOCUSFORCE_FIELD_NUMBER: _ClassVar[int]
    FOCUSHOME_FIELD_NUMBER: _ClassVar[int]
    MOUNT_FIELD_NUMBER: _ClassVar[int]
    ROTATORVELOCITY_FIELD_NUMBER: _ClassVar[int]
    ROTATORACCELERATION_FIELD_NUMBER: _ClassVar[int]
    ROTATORPOSITION_FIELD_NUMBER: _ClassVar[int]
    ROTATORSTOP_FIELD_NUMBER: _ClassVar[int]
    PING_FIELD_NUMBER: _ClassVar[int]
    SYSLOGRECEIVER_FIELD_NUMBER: _ClassVar[int]
    POWERDOWN_FIELD_NUMBER: _ClassVar[int]
    RESERVED1_FIELD_NUMBER: _ClassVar[int]
    type: Command.CommandType
    dateTime: Command.SetDateTime
    frameStreamReceiver: Command.SetFrameStreamReceiver
    frameStreamSettings: Command.SetFrameStreamSettings
    settings: Command.SetAcousticSettings
    salinity: Command.SetSalinity
    telephoto: Command.SetTelephotoLens
    focusPosition: Command.SetFocusPosition
    focusForce: Command.ForceFocus
    focusHome: Command.HomeFocus
    mount: Command.SetRotatorMount
    rotatorVelocity: Command.SetRotatorVelocity
    rotatorAcceleration: Command.SetRotatorAcceleration
    rotatorPosition: Command.SetRotatorPosition
    rotatorStop: Command.StopRotator
    ping: Command.Ping
    syslogReceiver: Command.SetSyslogReceiver
    powerDown: Command.PowerDown
    reserved1: Command.Reserved1
    def __init__(self, type: _Optional[_Union[Command.CommandType, str]] = ..., dateTime: _Optional[_Union[Command.SetDateTime, _Mapping]] = ..., frameStreamReceiver: _Optional[_Union[Command.SetFrameStreamReceiver, _Mapping]] = ..., frameStreamSettings: _Optional[_Union[Command.SetFrameStreamSettings, _Mapping]] = ..., settings: _Optional[_Union[Command.SetAcousticSettings, _Mapping]] = ..., salinity: _Optional[_Union[Command.SetSalinity, _Mapping]] = ..., telephoto: _Optional[_Union[Command.SetTelephotoLens, _Mapping]] = ..., focusPosition: _Optional[_Union[Command.SetFocusPosition, _Mapping]] = ..., focusForce: _Optional[_Union[Command.ForceFocus, _Mapping]] = ..., focusHome: _Optional[_Union[Command.HomeFocus, _Mapping]] = ..., mount: _Optional[_Union[Command.SetRotatorMount, _Mapping]] = ..., rotatorVelocity: _Optional[_Union[Command.SetRotatorVelocity, _Mapping]] = ..., rotatorAcceleration: _Optional[_Union[Command.SetRotatorAcceleration, _Mapping]] = ..., rotatorPosition: _Optional[_Union[Command.SetRotatorPosition, _Mapping]] = ..., rotatorStop: _Optional[_Union[Command.StopRotator, _Mapping]] = ..., ping: _Optional[_Union[Command.Ping, _Mapping]] = ..., syslogReceiver: _Optional[_Union[Command.SetSyslogReceiver, _Mapping]] = ..., powerDown: _Optional[_Union[Command.PowerDown, _Mapping]] = ..., reserved1: _Optional[_Union[Command.Reserved1, _Mapping]] = ...) -> None: ...
