"""One table of fuzz targets: every decoder of peer input, driven the same way.

Used by ``tests/test_decoders_robust.py`` (hypothesis, in CI) and by
``tests/fuzz/fuzz_decoders.py`` (atheris, by hand). Importing this module
needs neither atheris nor hypothesis. One :class:`Target` per decoder:

* ``make()``: a fresh decoder, in the state a peer finds it in (a new
  connection, a new serial line), behind its link (:func:`tests.fuzz.adapters.driven`:
  bytes, datagrams or CAN frames); ``feed(decoder, data) -> events``: by default
  the codec contract (:func:`tests.fuzz.adapters.feed`: ``receive_data`` and
  ``next_event`` until NEED_DATA, ``data_to_send`` as replies); only the Modbus
  sessions, which answer requests, have their own;
* ``samples()``: valid messages built with the codecs' own encoders and the
  reference's known vectors, each with a predicate recognising its event
  (``seeds()``: more valid input without an event to recognise, for atheris);
  ``oversize()``: heads claiming a huge length (4 GB where the field allows
  it, else its largest value), each with a filler that keeps coming
  (:mod:`tests.fuzz.samples`);
* ``buffered(decoder) -> int`` (by default the decoder's ``buffered_bytes`` plus a
  partial link unit) and ``bound``: the bytes the decoder retains once drained and
  the most it may ever retain (``measure`` says what counts);
* how it resynchronises: ``sync`` (what a peer sends to put a text protocol
  back in step: a line end), ``resync_after`` (how many bytes of valid traffic
  after garbage may still be lost, and ``resync_note`` why), ``gap`` (the
  line going idle: Modbus RTU), or why it cannot (``no_resync``,
  ``no_resync_after_truncation``); and where the events may depend on how the
  input is cut (``chunking_matters``, or only after a loss of sync:
  ``chunking_matters_after`` and ``chunking_note``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

from hilsim.protocols import aris, ddf, ddf_commands, dronecan, modbus, oculus, slcan, socketcand, vesc_can, vesc_uart, vrcsr
from hilsim.protocols import modbus_device as mb
from hilsim.protocols import keller_bus, witmotion_uart
from hilsim.protocols import dvl_json, dvl_serial, nmea, ping_protocol
from tests.fuzz import adapters as A
from tests.fuzz import links as L
from tests.fuzz import samples as S
from tests.fuzz import samples_ping360 as SP
from tests.fuzz import samples_serial_sensors as SS
from tests.fuzz import samples_navigation as SN
from tests.fuzz.adapters import Closed, Events, PeerError, Reply
from tests.fuzz.events import Canon, badly_typed
from tests.fuzz.samples import Sample

__all__ = ["Closed", "PeerError", "Reply", "Sample", "TARGETS", "Target", "names"]


@dataclass(frozen=True)
class Target:
    """One decoder under fuzzing; the fields are described in the module docstring."""

    name: str
    summary: str
    make: Callable[[], Any]
    bound: int
    measure: str
    samples: Callable[[], list[Sample]]
    oversize: Callable[[], list[tuple[bytes, bytes]]]  # (head from a fresh decoder, filler repeated after it)
    feed: Callable[[Any, bytes], Events] = A.feed     # the codec contract; Modbus sessions: their own
    buffered: Callable[[Any], int] = A.buffered      # decoder.buffered_bytes + a partial link unit
    prefix: bytes = b""          # what every valid stream starts with (a file header, an open command)
    sync: bytes = b""            # sent (then the prefix) before a valid message after garbage (a line end)
    resync_after: int = 0        # bytes of valid traffic after garbage that may still be lost ...
    resync_note: str = ""        # ... and why
    gap: Callable[[Any], Events] | None = None   # the line idle between bursts (Modbus RTU)
    end: Callable[[Any], Events] | None = None   # the end of the input (DDF: EOF)
    unit: int = 1                # record size of the byte adapter (CAN: 16); garbage comes in whole records
    whole: Callable[[bytes], bytes] | None = None   # arbitrary bytes -> whole link units (datagrams)
    truncate: Callable[[bytes, int], bytes] | None = None  # a message cut after about k bytes
    pipelined: bool = True       # False: the peer waits for each reply (one message per burst)
    no_resync: str | None = None                  # why a valid message after garbage may be lost
    no_resync_after_truncation: str | None = None
    chunk_dependent: tuple[type, ...] = ()   # events whose size depends on how the bytes were cut (Junk)
    chunking_matters: str | None = None       # why the events may depend on how the input is cut
    chunking_matters_after: tuple[type, ...] = ()  # ... only after one of these (loss of sync); why:
    chunking_note: str = ""
    random_size: int = 1024      # random inputs up to this size hold a few messages (hypothesis)
    seeds: Callable[[], list[bytes]] | None = None  # more valid input with no event to recognise (atheris)

    def garbage(self, data: bytes) -> bytes:
        """Arbitrary bytes as the link can deliver them (whole CAN records, whole datagrams)."""
        if self.whole is not None:
            return self.whole(data)
        return data[: len(data) // self.unit * self.unit]

    def cut(self, wire: bytes, k: int) -> bytes:
        """A valid message truncated after about ``k`` bytes (whole link units)."""
        if self.truncate is not None:
            return self.truncate(wire, k)
        k = min(k, len(wire) - 1)
        return wire[: k // self.unit * self.unit]

    def run(self, decoder: Any, data: bytes, chunks: Sequence[int] = ()) -> Events:
        """Feed ``data`` in chunks of the given sizes (cycled; none: whole), checking the bound and
        that every event's fields fit their annotations."""
        out: Events = []
        sizes = [c for c in chunks if c > 0] or [len(data) or 1]
        pos, i = 0, 0
        while pos < len(data):
            n = sizes[i % len(sizes)]
            events = self.feed(decoder, data[pos : pos + n])
            for e in events:
                if bad := badly_typed(e):
                    raise AssertionError(f"{self.name}: an event does not fit its annotation: {bad}")
            out += events
            held = self.buffered(decoder)
            if held > self.bound:
                raise AssertionError(f"{self.name}: {held} bytes retained, bound {self.bound}")
            pos += n
            i += 1
        return out

    def finish(self, decoder: Any) -> Events:
        """The line goes idle, then the input ends."""
        out: Events = []
        if self.gap is not None:
            out += self.gap(decoder)
        if self.end is not None:
            out += self.end(decoder)
        return out

    def normalize(self, events: Events) -> tuple[Events, bytes]:
        """What must not depend on how the input was cut: events and reply bytes apart (when a reply
        is asked for does), without skipped-bytes counts, up to a loss of sync where the table says
        so; a peer error's text may quote fewer bytes; NaN equals NaN."""
        others = [Canon(PeerError("") if isinstance(e, PeerError) else e) for e in events
                  if not isinstance(e, (Reply, *self.chunk_dependent))]
        lost = [i for i, e in enumerate(others) if isinstance(e.event, self.chunking_matters_after)]
        if lost:
            others = others[: lost[0] + 1]
        return others, b"".join(e.data for e in events if isinstance(e, Reply))

    def filler(self) -> bytes:
        """Valid traffic long enough for a length claim stalled in garbage to run out (resync_after)."""
        out, i = b"", 0
        samples = self.samples()
        while len(out) < self.resync_after:
            out += samples[i % len(samples)].wire
            i += 1
        return out

    def expect_resync(self, decoder: Any, sample_index: int, chunks: Sequence[int] = ()) -> None:
        """After whatever was fed: (idle,) sync, prefix, filler, then sample ``sample_index`` must be decoded."""
        if self.gap is not None:
            self.gap(decoder)
        self.run(decoder, self.sync + self.prefix + self.filler(), chunks)
        s = self.samples()[sample_index]
        events = self.run(decoder, s.wire, chunks) + self.finish(decoder)
        if not any(s.expect(e) for e in events):
            raise AssertionError(f"{self.name}: {s.label} not decoded after resync; got {events[:6]}")


TARGETS: dict[str, Target] = {t.name: t for t in [
    Target(
        "ddf-stream", "DDF_04 stream reader (client side): ddf.DdfReader",
        make=A.driven(ddf.DdfReader), end=A.end,
        bound=ddf.FRAME_HEADER_SIZE + ddf.MAX_NUMBEAMS * ddf.MAX_SAMPLES_PER_CHANNEL,
        measure="DdfReader.buffered_bytes (one frame at most)",
        samples=S.ddf_samples, oversize=S.ddf_oversize, prefix=S.ddf_prefix(),
        random_size=3 * (ddf.FRAME_HEADER_SIZE + S.DDF_BEAMS * S.DDF_SAMPLES),
        no_resync="a DDF stream has no frame marker: a bad signature or an absurd frame size raises "
                  "ProtocolError and the reader stays dead by design (the client reconnects)",
        no_resync_after_truncation="frames are found by counting bytes from the file header: a short frame "
                                   "shifts every later one (the bytes still decode, as the wrong frames)"),
    Target(
        "ddf-commands", "DDF command lines (server side): ddf_commands.CommandDecoder",
        make=A.driven(ddf_commands.CommandDecoder), bound=ddf_commands.MAX_LINE_BYTES,
        measure="CommandDecoder.buffered_bytes",
        samples=S.ddf_command_samples, oversize=S.text_oversize(b"RATE ", b"9"), sync=b"\n"),
    Target(
        "oculus", "Oculus TCP stream, sonar side (client messages): oculus.OculusReader",
        make=A.driven(oculus.OculusReader), bound=oculus.HEADER_SIZE + oculus.MAX_SERVER_PAYLOAD,
        measure="OculusReader.buffered_bytes",
        samples=S.oculus_samples, oversize=S.oculus_oversize,
        resync_after=oculus.HEADER_SIZE + oculus.MAX_SERVER_PAYLOAD, chunk_dependent=(oculus.Junk,),
        resync_note="no checksum: a '53 4F' in garbage (or a cut message) announces up to max_payload bytes; "
                    "the reader waits for them and, if they frame a message it accepts (a dummy, or a fire "
                    "whose fields happen to be finite), the valid messages inside are lost"),
    Target(
        "aris-commands", "ARIS command channel (sonar side): aris.CommandReader",
        make=A.driven(aris.CommandReader), bound=aris.MAX_COMMAND_LENGTH + 4,
        measure="CommandReader.buffered_bytes",
        samples=S.aris_samples, oversize=S.aris_oversize, resync_after=aris.MAX_COMMAND_LENGTH + 4,
        chunk_dependent=(aris.Junk,), chunking_matters_after=(aris.BadCommand, aris.Oversize),
        chunking_note="out of sync, a complete command that parses is taken at once, even if an earlier "
                      "offset still waits for bytes that would make it a command too (a live reader over one "
                      "that waits up to max_length bytes for garbage)",
        resync_note="no checksum or marker: a length prefix in garbage (or a cut command) claims up to "
                    "max_length bytes; the reader waits for them before it can tell they are not a command"),
    Target(
        "aris-frames", "ARIS FramePart datagrams (client side): aris.FrameAssembler",
        make=A.driven(aris.FrameAssembler, L.Datagrams), bound=2 * aris.FrameAssembler().max_data + 2 + 0xFFFF,
        measure="FrameAssembler.buffered_bytes (the frame in progress and its map of received bytes) "
                "+ a partial datagram record",
        samples=S.assembler_samples, oversize=S.assembler_oversize,
        whole=lambda data: L.datagram(data[:0xFFFF]), truncate=S.assembler_cut,
        no_resync="a part with a higher frame_index makes every older index stale (by design: UDP reorders), "
                  "so a frame after garbage is assembled only if its index is higher than the garbage's"),
    Target(
        "socketcand", "socketcand text protocol (server side): socketcand.SocketcandServer",
        make=A.driven(socketcand.SocketcandServer), bound=socketcand.MAX_MESSAGE,
        measure="SocketcandServer.buffered_bytes (the unfinished message)",
        samples=S.socketcand_samples, oversize=S.text_oversize(b"< open can0 >< rawmode >< send ", b"0"),
        prefix=b"< open can0 >< rawmode >", sync=b">"),
    Target(
        "slcan", "slcan (adapter side): slcan.SlcanAdapter",
        make=A.driven(slcan.SlcanAdapter), bound=slcan.MAX_LINE,
        measure="SlcanAdapter.buffered_bytes (the unfinished line)",
        samples=S.slcan_samples, oversize=S.text_oversize(b"O\rt", b"0"), prefix=b"O\r", sync=b"\r"),
    Target(
        "vesc-uart", "VESC UART packets (ESC side): vesc_uart.PacketDecoder + decode_command",
        make=A.driven(vesc_uart.PacketDecoder, then=vesc_uart.decode_command),
        bound=3 + vesc_uart.MAX_PAYLOAD + 3 - 1, measure="PacketDecoder.buffered_bytes",
        samples=S.vesc_uart_samples, seeds=S.vesc_uart_seeds, resync_after=3 + vesc_uart.MAX_PAYLOAD + 3,
        resync_note="the end byte 0x03 is also the long-form start byte: a packet cut just before its end "
                    "byte is completed by the next packet's start (its CRC is good, so the bytes cannot tell) "
                    "and that packet is lost",
        oversize=lambda: [(b"\x03\xff\xff", S.filler()), (b"\x03\x02\x00", S.filler()), (b"\x02\xff", S.filler())]),
    Target(
        "vrcsr", "VideoRay VRCSR packets (thruster side): vrcsr.PacketDecoder",
        make=A.driven(vrcsr.PacketDecoder, then=lambda p: vrcsr.PropulsionCommand.decode(p.payload)),
        bound=vrcsr.HEADER_SIZE + 2 * vrcsr.CRC_SIZE + 255 - 1, measure="PacketDecoder.buffered_bytes",
        samples=S.vrcsr_samples, oversize=S.vrcsr_oversize),
    Target(
        "vesc-can", "VESC CAN frames (ESC side): vesc_can.decode, frames from SocketCAN records",
        make=A.driven(lambda: A.PerFrame(vesc_can.decode), L.CanRecords), bound=L.CAN_RECORD_SIZE - 1,
        measure="a partial CAN record (decode keeps nothing)",
        samples=S.vesc_can_samples, oversize=S.vesc_can_oversize, unit=L.CAN_RECORD_SIZE),
    Target(
        "dronecan", "DroneCAN transfers (ESC side): dronecan.TransferReceiver, frames from SocketCAN records",
        make=A.driven(dronecan.TransferReceiver, L.CanRecords,
                      then=lambda t: dronecan.decode_message(t.dtid, t.payload)),
        bound=dronecan.TransferReceiver.max_sessions * (dronecan.TransferReceiver.max_payload + 2)
        + L.CAN_RECORD_SIZE - 1,
        measure="TransferReceiver.buffered_bytes (payload bytes of the open sessions) + a partial CAN record",
        samples=S.dronecan_samples, seeds=S.dronecan_seeds, oversize=S.dronecan_oversize, unit=L.CAN_RECORD_SIZE),
    Target(
        "modbus-tcp", "Modbus TCP requests (device side): modbus_device.TcpSession (modbus.TcpRequestDecoder)",
        make=lambda: mb.TcpSession(A.keller_target()), feed=A.tcp_feed, buffered=lambda s: len(s.buffer),
        bound=6 + modbus.MAX_TCP_LENGTH - 1, measure="TcpSession.buffer (an unfinished ADU)",
        samples=S.tcp_samples, oversize=S.tcp_oversize,
        no_resync="a header that is not Modbus TCP closes the connection, as real devices do (the client "
                  "reconnects); MBAP has no marker to resynchronise on",
        no_resync_after_truncation="TCP does not lose bytes: a cut ADU swallows the start of the next one "
                                   "and the misread header closes the connection"),
    Target(
        "modbus-rtu", "Modbus RTU requests (device side): modbus_device.RtuSession (modbus.RtuRequestDecoder)",
        make=lambda: mb.RtuSession([A.keller_target()]), feed=A.rtu_feed, gap=A.rtu_silence,
        buffered=lambda s: len(s.buffer), bound=modbus.MAX_RTU_ADU, measure="RtuSession.buffer",
        samples=S.rtu_samples, seeds=S.rtu_seeds, oversize=S.rtu_oversize),
    Target(
        "keller-bus", "KELLER bus requests (transmitter side): keller_bus.KellerRequestDecoder",
        make=A.driven(keller_bus.KellerRequestDecoder), gap=lambda d: list(d.decoder.silence()),
        bound=keller_bus.MAX_FRAME, measure="KellerRequestDecoder.buffered_bytes",
        samples=SS.keller_samples, oversize=SS.keller_oversize, chunk_dependent=(keller_bus.Junk,)),
    Target(
        "witmotion-commands", "WitMotion UART commands FF AA (IMU side): witmotion_uart.CommandDecoder",
        make=A.driven(witmotion_uart.CommandDecoder), gap=lambda d: list(d.decoder.silence()),
        bound=witmotion_uart.COMMAND_SIZE - 1, measure="CommandDecoder.buffered_bytes",
        samples=SS.witmotion_command_samples, oversize=lambda: SS.head_oversize(b"\xff\xaa"),
        chunk_dependent=(witmotion_uart.Junk,)),
    Target(
        "witmotion-packets", "WitMotion UART 0x55 packets (host side): witmotion_uart.PacketDecoder",
        make=A.driven(witmotion_uart.PacketDecoder), bound=witmotion_uart.PACKET_SIZE - 1,
        measure="PacketDecoder.buffered_bytes", samples=SS.witmotion_packet_samples,
        oversize=lambda: SS.head_oversize(b"\x55\x53"), chunk_dependent=(witmotion_uart.Junk,)),
    Target(
        "dvl-json", "Water Linked DVL JSON command lines (DVL side): dvl_json.CommandDecoder",
        make=A.driven(dvl_json.CommandDecoder), bound=dvl_json.MAX_LINE,
        measure="CommandDecoder.buffered_bytes (the unfinished line)",
        samples=SN.dvl_json_samples, oversize=S.text_oversize(b'{"command": "', b"x"), sync=b"\n"),
    Target(
        "dvl-serial", "Water Linked DVL serial commands (DVL side): dvl_serial.SerialCommandDecoder",
        make=A.driven(dvl_serial.SerialCommandDecoder), bound=dvl_serial.MAX_LINE,
        measure="SerialCommandDecoder.buffered_bytes (the unfinished line)",
        samples=SN.dvl_serial_samples, oversize=S.text_oversize(b"wcs,", b"1"), sync=b"\n"),
    Target(
        "nmea", "NMEA 0183 sentences (host side): nmea.NmeaDecoder",
        make=A.driven(nmea.NmeaDecoder), bound=2 * nmea.MAX_SENTENCE,
        measure="NmeaDecoder.buffered_bytes (the unfinished line)",
        samples=SN.nmea_samples, oversize=S.text_oversize(b"$GPGGA,", b"1"), sync=b"\r\n"),
    Target(
        "ping-protocol", "Blue Robotics ping-protocol packets (device side): ping_protocol.PingDecoder",
        make=A.driven(ping_protocol.PingDecoder),
        bound=ping_protocol.HEADER_LEN + ping_protocol.MAX_PAYLOAD + ping_protocol.CHECKSUM_LEN - 1,
        measure="PingDecoder.buffered_bytes (one packet at most)",
        samples=SN.ping_samples, oversize=SN.ping_oversize, chunk_dependent=(ping_protocol.Junk,),
        resync_after=ping_protocol.HEADER_LEN + ping_protocol.MAX_PAYLOAD + ping_protocol.CHECKSUM_LEN,
        resync_note="a 'BR' in garbage (or a cut packet) announces up to max_payload bytes; the decoder waits "
                    "for them (as the device's byte-by-byte parser does) and drops them with a bad checksum"),
    Target(
        "ping360", "Blue Robotics Ping360 commands (device side): ping_protocol.PingDecoder, Ping360 messages",
        make=A.driven(ping_protocol.PingDecoder),
        bound=ping_protocol.HEADER_LEN + ping_protocol.MAX_PAYLOAD + ping_protocol.CHECKSUM_LEN - 1,
        measure="PingDecoder.buffered_bytes (one packet at most)",
        samples=SP.ping360_samples, oversize=SN.ping_oversize, chunk_dependent=(ping_protocol.Junk,),
        resync_after=ping_protocol.HEADER_LEN + ping_protocol.MAX_PAYLOAD + ping_protocol.CHECKSUM_LEN,
        resync_note="as ping-protocol: the same framing and decoder"),
]}


def names() -> list[str]:
    return list(TARGETS)
