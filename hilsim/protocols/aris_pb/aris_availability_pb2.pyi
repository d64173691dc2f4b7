from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Availability(_message.Message):
    __slots__ = ("serialNumber", "systemType", "softwareVersion", "connectionState", "capabilities", "reserved6", "commLinkPreference", "cpuTemp", "powerDownReason", "overTempLimitDegreesC", "overTempLimitSeconds", "isDiverHeld", "systemVariants")
    class SystemType(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        ARIS_1800: _ClassVar[Availability.SystemType]
        ARIS_3000: _ClassVar[Availability.SystemType]
        ARIS_1200: _ClassVar[Availability.SystemType]
    ARIS_1800: Availability.SystemType
    ARIS_3000: Availability.SystemType
    ARIS_1200: Availability.SystemType
    class ConnectionState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        AVAILABLE: _ClassVar[Availability.ConnectionState]
        BUSY: _ClassVar[Availability.ConnectionState]
    AVAILABLE: Availability.ConnectionState
    BUSY: Availability.ConnectionState
    class CommLinkPreference(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        HomePlug: _ClassVar[Availability.CommLinkPreference]
        Ethernet: _ClassVar[Availability.CommLinkPreference]
    HomePlug: Availability.CommLinkPreference
    Ethernet: Availability.CommLinkPreference
    class PowerDownReason(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        OverTemp: _ClassVar[Availability.PowerDownReason]
    OverTemp: Availability.PowerDownReason
    class SoftwareVersion(_message.Message):
        __slots__ = ("major", "minor", "buildnumber")
        MAJOR_FIELD_NUMBER: _ClassVar[int]
        MINOR_FIELD_NUMBER: _ClassVar[int]
        BUILDNUMBER_FIELD_NUMBER: _ClassVar[int]
        major: int
        minor: int
        buildnumber: int
        def __init__(self, major: _Optional[int] = ..., minor: _Optional[int] = ..., buildnumber: _Optional[int] = ...) -> None: ...
    class Capabilities(_message.Message):
        __slots__ = ("enabled",)
        ENABLED_FIELD_NUMBER: _ClassVar[int]
        enabled: _containers.RepeatedScalarFieldContainer[str]
        def __init__(self, enabled: _Optional[_Iterable[str]] = ...) -> None: ...
    class SystemVariants(_message.Message):
        __slots__ = ("enabled",)
        ENABLED_FIELD_NUMBER: _ClassVar[int]
        enabled: _containers.RepeatedScalarFieldContainer[str]
        def __init__(self, enabled: _Optional[_Iterable[str]] = ...) -> None: ...
    SERIALNUMBER_FIELD_NUMBER: _ClassVar[int]
    SYSTEMTYPE_FIELD_NUMBER: _ClassVar[int]
    SOFTWAREVERSION_FIELD_NUMBER: _ClassVar[int]
    CONNECTIONSTATE_FIELD_NUMBER: _ClassVar[int]
    CAPABILITIES_FIELD_NUMBER: _ClassVar[int]
    RESERVED6_FIELD_NUMBER: _ClassVar[int]
    COMMLINKPREFERENCE_FIELD_NUMBER: _ClassVar[int]
    CPUTEMP_FIELD_NUMBER: _ClassVar[int]
    POWERDOWNREASON_FIELD_NUMBER: _ClassVar[int]
    OVERTEMPLIMITDEGREESC_FIELD_NUMBER: _ClassVar[int]
    OVERTEMPLIMITSECONDS_FIELD_NUMBER: _ClassVar[int]
    ISDIVERHELD_FIELD_NUMBER: _ClassVar[int]
    SYSTEMVARIANTS_FIELD_NUMBER: _ClassVar[int]
    serialNumber: int
    systemType: Availability.SystemType
    softwareVersion: Availability.SoftwareVersion
    connectionState: Availability.ConnectionState
    capabilities: Availability.Capabilities
    reserved6: int
    commLinkPreference: Availability.CommLinkPreference
    cpuTemp: float
    powerDownReason: Availability.PowerDownReason
    overTempLimitDegreesC: float
    overTempLimitSeconds: int
    isDiverHeld: bool
    systemVariants: Availability.SystemVariants
    def __init__(self, serialNumber: _Optional[int] = ..., systemType: _Optional[_Union[Availability.SystemType, str]] = ..., softwareVersion: _Optional[_Union[Availability.SoftwareVersion, _Mapping]] = ..., connectionState: _Optional[_Union[Availability.ConnectionState, str]] = ..., capabilities: _Optional[_Union[Availability.Capabilities, _Mapping]] = ..., reserved6: _Optional[int] = ..., commLinkPreference: _Optional[_Union[Availability.CommLinkPreference, str]] = ..., cpuTemp: _Optional[float] = ..., powerDownReason: _Optional[_Union[Availability.PowerDownReason, str]] = ..., overTempLimitDegreesC: _Optional[float] = ..., overTempLimitSeconds: _Optional[int] = ..., isDiverHeld: _Optional[bool] = ..., systemVariants: _Optional[_Union[Availability.SystemVariants, _Mapping]] = ...) -> None: ...
