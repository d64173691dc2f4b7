"""Whole .ddf recordings: read from bytes or a binary stream, written to a binary stream.

Both helpers go through the sans-I/O codec in :mod:`hilsim.protocols.ddf`,
so a file and a TCP capture (``nc HOST PORT > capture.ddf``) read the same.
Opening files is the caller's (``with open(path, "rb") as f: read_ddf_file(f)``).
"""

from __future__ import annotations

import io
from dataclasses import replace
from typing import BinaryIO, Iterable

from hilsim.protocols.ddf import (
    NEED_DATA,
    DdfReader,
    DdfWriter,
    EndOfStream,
    FileHeader,
    FileHeaderEvent,
    FrameEvent,
    ProtocolError,
    encode_file_header,
)

_CHUNK = 1 << 20  # [bytes] read size


def read_ddf_file(source: bytes | BinaryIO, strict: bool = False) -> tuple[FileHeader, list[FrameEvent]]:
    """Read a DDF_04 recording (its bytes, or a binary stream read to its end) -> (file header,
    frames with samples in sim order).

    ``numframes`` in the header is not trusted (captures keep 0): frames are
    counted from the data. A capture cut in the middle of a frame loses that
    frame; with ``strict=True`` such a tail raises ProtocolError instead.
    """
    reader = DdfReader()
    frames: list[FrameEvent] = []
    header: FileHeader | None = None
    f: BinaryIO = io.BytesIO(source) if isinstance(source, (bytes, bytearray, memoryview)) else source
    name = str(getattr(source, "name", "") or "<DDF bytes>")
    while True:
        chunk = f.read(_CHUNK)
        reader.receive_data(chunk)
        while True:
            event = reader.next_event()
            if event is NEED_DATA:
                break
            if isinstance(event, FileHeaderEvent):
                header = event.header
            elif isinstance(event, FrameEvent):
                frames.append(event)
            elif isinstance(event, EndOfStream):
                if strict and event.trailing_bytes:
                    raise ProtocolError(
                        f"{name}: {event.trailing_bytes} bytes of an"
                        " incomplete last frame"
                    )
                assert header is not None  # the reader raises before that
                return header, frames


def write_ddf_file(sink: BinaryIO, header: FileHeader, frames: Iterable[FrameEvent]) -> int:
    """Write a DDF_04 recording to a seekable binary stream (from its current position, which
    must be the start of the recording); ``numframes`` is set to the count written. Returns it."""
    writer = DdfWriter()
    count = 0
    start = sink.tell()
    sink.write(writer.send(FileHeaderEvent(replace(header, numframes=0))))
    for frame in frames:
        sink.write(writer.send(frame))
        count += 1
    end = sink.tell()
    sink.seek(start)
    sink.write(encode_file_header(replace(header, numframes=count)))
    sink.seek(end)
    return count
