""".aris recordings (DDF_05): reader and writer.

Layout (``protocols/aris.md``; aris-file-sdk FileHeader.h / FrameHeader.h):
a 1024-byte file header (Version ``0x05464444`` = ``DDF\\x05``, FrameCount @4,
NumRawBeams @16, SamplesPerChannel @24, SN @44), then per frame a 1024-byte
frame header (:data:`hilsim.protocols.aris.FRAME_HEADER_LAYOUT`) followed by
``beams x samples`` uint8 samples.

Geometry comes from the first frame header (PingMode -> beams, SamplesPerBeam),
falling back to the file header; the frame count is computed from the file
size (the SDK tells readers to), FrameCount is only cross-checked. Samples are
returned as ``(n_samples, n_beams)`` with beam 0 = port, like the simulator's
frames; that needs ``ReorderedSamples = 1`` (every file hilsim writes; for a
file without it the SDK's permutation would be needed, which we do not ship:
:meth:`ArisReader.frame` then returns the samples in stored order and says so).

A file that is not DDF_05 or whose size does not fit its geometry raises
:class:`ArisFileError` (a ValueError). Sans-I/O as the rest of the package: the
reader takes the file's bytes or a binary stream, the writer a binary stream;
opening files is the caller's.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import BinaryIO, Iterator, Mapping

import numpy as np
import numpy.typing as npt

from hilsim.protocols.aris import (
    FILE_OFFSETS,
    FILE_VERSION,
    HEADER_SIZE,
    HeaderValue,
    beams_for_ping_mode,
    decode_file_header,
    decode_frame_header,
    encode_file_header,
    encode_frame_header,
    samples_from_wire,
    samples_to_wire,
)

MAX_BEAMS = 256
MAX_SAMPLES = 8192


class ArisFileError(ValueError):
    """Not a readable .aris file."""


@dataclass(frozen=True, eq=False)
class ArisFrame:
    """One frame: header fields and samples (n_samples, n_beams) uint8, beam 0 = port
    (stored order instead when ``reordered`` is False)."""

    index: int
    header: dict[str, HeaderValue]
    samples: npt.NDArray[np.uint8]
    reordered: bool = True


class ArisReader:
    """Random access to the frames of an .aris recording.

    source: the file's bytes, or a seekable binary stream (an open file: the caller
    opens it and closes it; :meth:`close` leaves a stream it was given open). Use as a
    context manager or call close().
    """

    def __init__(self, source: bytes | BinaryIO, name: str = "") -> None:
        self._f: BinaryIO = io.BytesIO(source) if isinstance(source, (bytes, bytearray, memoryview)) else source
        self.name = name or str(getattr(source, "name", "") or "<.aris bytes>")
        self._f.seek(0)
        self._open()

    def _open(self) -> None:
        raw = self._f.read(HEADER_SIZE)
        if len(raw) < HEADER_SIZE:
            raise ArisFileError(f"{self.name}: {len(raw)} bytes, shorter than the 1024-byte file header")
        self.file_header = decode_file_header(raw)
        if self.file_header["Version"] != FILE_VERSION:
            raise ArisFileError(f"{self.name}: not an ARIS file (starts {raw[:4].hex(' ')}, expected 44 44 46 05)")
        first = self._f.read(HEADER_SIZE)
        beams, samples = int(self.file_header["NumRawBeams"]), int(self.file_header["SamplesPerChannel"])  # type: ignore[arg-type]
        if len(first) == HEADER_SIZE:
            fh = decode_frame_header(first)
            beams = beams_for_ping_mode(int(fh["PingMode"])) or beams  # type: ignore[arg-type]
            samples = int(fh["SamplesPerBeam"]) or samples  # type: ignore[arg-type]
        if not (1 <= beams <= MAX_BEAMS and 1 <= samples <= MAX_SAMPLES):
            raise ArisFileError(f"{self.name}: implausible geometry {beams} beams x {samples} samples")
        self.n_beams, self.n_samples = beams, samples
        self.frame_size = HEADER_SIZE + beams * samples
        size = self._f.seek(0, io.SEEK_END)
        self.n_frames = (size - HEADER_SIZE) // self.frame_size
        self.trailing_bytes = (size - HEADER_SIZE) % self.frame_size

    @property
    def serial_number(self) -> int:
        return int(self.file_header["SN"])  # type: ignore[arg-type]

    def __len__(self) -> int:
        return self.n_frames

    def frame(self, i: int) -> ArisFrame:
        """Frame ``i`` (0-based, in file order)."""
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame {i} out of range 0..{self.n_frames - 1}")
        self._f.seek(HEADER_SIZE + i * self.frame_size)
        raw = self._f.read(self.frame_size)
        header = decode_frame_header(raw)
        data = raw[HEADER_SIZE:]
        if header["ReorderedSamples"] == 1:
            samples = samples_from_wire(data, self.n_beams, self.n_samples)
            return ArisFrame(i, header, samples, True)
        stored = np.frombuffer(data, np.uint8).reshape(self.n_samples, self.n_beams).copy()
        return ArisFrame(i, header, stored, False)

    def __iter__(self) -> Iterator[ArisFrame]:
        for i in range(self.n_frames):
            yield self.frame(i)

    def close(self) -> None:
        """Nothing to release: the stream is the caller's (kept for ``with`` blocks)."""

    def __enter__(self) -> "ArisReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ArisWriter:
    """Write an .aris recording frame by frame; FrameCount is patched on close().

    sink: a seekable binary stream opened for writing (``open(path, "wb")``: the
    caller opens it; :meth:`close` patches the header, flushes and leaves it open).
    file_fields: extra file-header fields (SN, strHeaderID ...). Every frame of
    one file must have the same geometry. Frames are written with
    ``ReorderedSamples = 1`` and ``Version = DDF_05``.
    """

    def __init__(self, sink: BinaryIO, file_fields: Mapping[str, HeaderValue] | None = None) -> None:
        self.file_fields: dict[str, HeaderValue] = dict(file_fields or {})
        encode_file_header(self.file_fields)  # validate early
        self._f: BinaryIO | None = sink
        self._f.write(encode_file_header(self.file_fields))
        self.n_frames = 0
        self.shape: tuple[int, int] | None = None

    def write_frame(self, header: Mapping[str, HeaderValue], samples: npt.NDArray[np.uint8]) -> None:
        """header: frame-header fields; samples (n_samples, n_beams) uint8, beam 0 = port."""
        if self._f is None:
            raise ValueError("write_frame on a closed ArisWriter")
        if self.shape is None:
            self.shape = (int(samples.shape[0]), int(samples.shape[1]))
            self.file_fields.update(NumRawBeams=self.shape[1], SamplesPerChannel=self.shape[0])
        elif samples.shape != self.shape:
            raise ValueError(f"frame shape {samples.shape} != the file's {self.shape}")
        fields = {**header, "Version": FILE_VERSION, "ReorderedSamples": 1,
                  "SamplesPerBeam": self.shape[0]}
        fields.setdefault("FrameIndex", self.n_frames)
        self._f.write(encode_frame_header(fields))
        self._f.write(samples_to_wire(samples))
        self.n_frames += 1

    def flush(self) -> None:
        """Write the file header with the current FrameCount and geometry."""
        if self._f is None:
            return
        pos = self._f.tell()
        self._f.seek(0)
        self._f.write(encode_file_header({**self.file_fields, "FrameCount": self.n_frames}))
        self._f.seek(pos)
        self._f.flush()

    def close(self) -> None:
        if self._f is None:
            return
        self.flush()
        self._f = None

    def __enter__(self) -> "ArisWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["ArisFileError", "ArisFrame", "ArisReader", "ArisWriter", "FILE_OFFSETS"]
