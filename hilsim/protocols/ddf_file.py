"""Whole .ddf files on disk: the only DDF code that touches files.

Both helpers go through the sans-I/O codec in :mod:`hilsim.protocols.ddf`,
so a file and a TCP capture (``nc HOST PORT > capture.ddf``) read the same.
"""

from __future__ import annotations

import os
from dataclasses import replace
from typing import Iterable

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


def read_ddf_file(
    path: str | os.PathLike[str], strict: bool = False
) -> tuple[FileHeader, list[FrameEvent]]:
    """Read a DDF_04 file -> (file header, frames with samples in sim order).

    ``numframes`` in the header is not trusted (captures keep 0): frames are
    counted from the data. A capture cut in the middle of a frame loses that
    frame; with ``strict=True`` such a tail raises ProtocolError instead.
    """
    reader = DdfReader()
    frames: list[FrameEvent] = []
    header: FileHeader | None = None
    with open(path, "rb") as f:
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
                            f"{os.fspath(path)}: {event.trailing_bytes} bytes of an"
                            " incomplete last frame"
                        )
                    assert header is not None  # the reader raises before that
                    return header, frames


def write_ddf_file(
    path: str | os.PathLike[str], header: FileHeader, frames: Iterable[FrameEvent]
) -> int:
    """Write a DDF_04 file; ``numframes`` is set to the count written. Returns it."""
    writer = DdfWriter()
    count = 0
    with open(path, "wb") as f:
        f.write(writer.send(FileHeaderEvent(replace(header, numframes=0))))
        for frame in frames:
            f.write(writer.send(frame))
            count += 1
        f.seek(0)
        f.write(encode_file_header(replace(header, numframes=count)))
    return count
