from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class SonarModel(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ARIS1800: _ClassVar[SonarModel]
    ARIS3000: _ClassVar[SonarModel]
    ARIS1200: _ClassVar[SonarModel]
ARIS1800: SonarModel
ARIS3000: SonarModel
ARIS1200: SonarModel

class FramePart(_message.Message):
    __slots__ = ("frame_index", "total_data_size", "header", "data", "data_offset", "ack_port")
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    TOTAL_DATA_SIZE_FIELD_NUMBER: _ClassVar[int]
    HEADER_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    DATA_OFFSET_FIELD_NUMBER: _ClassVar[int]
    ACK_PORT_FIELD_NUMBER: _ClassVar[int]
    frame_index: int
    total_data_size: int
    header: bytes
    data: bytes
    data_offset: int
    ack_port: int
    def __init__(self, frame_index: _Optional[int] = ..., total_data_size: _Optional[int] = ..., header: _Optional[bytes] = ..., data: _Optional[bytes] = ..., data_offset: _Optional[int] = ..., ack_port: _Optional[int] = ...) -> None: ...

class FramePartAck(_message.Message):
    __slots__ = ("frame_index", "data_offset")
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    DATA_OFFSET_FIELD_NUMBER: _ClassVar[int]
    frame_index: int
    data_offset: int
    def __init__(self, frame_index: _Optional[int] = ..., data_offset: _Optional[int] = ...) -> None: ...
