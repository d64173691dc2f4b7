"""The native serial dialects of the Modbus navigation sensors, on the same device state.

* :class:`KellerBus`: the KELLER bus protocol of the Keller Series 30
  (:mod:`hilsim.protocols.keller_bus`), served beside Modbus RTU on the device's RTU
  line (told by function code, as the transmitter does) and on the line's TCP port.
  It reads the device's one register image (P1, TOB1 ... as Modbus shows them, so
  faults and the zero point apply alike), moves the one device address, zeroes the
  one zero point; the power-up rule (exception 32 until F48) is the protocol's.
* :class:`WitUart`: the WitMotion UART stream (:mod:`hilsim.protocols.witmotion_uart`)
  on a pty of its own: packets at the configured rate with the configured content,
  built from the IMU's register image; ``FF AA`` commands taken as the device takes
  them, into the same image (RSW, RRATE, BAUD are Modbus registers too).

Devices import nothing from the runtime: both use the device context only.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

from hilsim.links.pty import PtyLink
from hilsim.protocols import keller_bus as kb
from hilsim.protocols import witmotion_uart as wu
from hilsim.protocols.codec import NEED_DATA
from hilsim.protocols.registers import ModbusError, RegisterImage

if TYPE_CHECKING:
    from hilsim.devices.context import DeviceContext, Periodic
    from hilsim.protocols.modbus_device import ModbusTarget

log = logging.getLogger(__name__)


class KellerBus:
    """The KELLER bus side of a Keller device.

    ``image``/``target``: the device's register image and Modbus target (address);
    ``zero(setpoint_pa | None)``: the device's zeroing of P1 (None: reset; raises
    ValueError when the channel cannot be zeroed); ``others``: the other targets on the
    line (an address they use is refused)."""

    def __init__(self, name: str, image: RegisterImage, target: "ModbusTarget",
                 zero: Any, line_targets: Optional[list["ModbusTarget"]] = None, *,
                 offset: Any = lambda: 0.0, set_offset: Any = None,
                 pressure_range: tuple[float, float] = (math.nan, math.nan)) -> None:
        self.name = name
        self.image = image
        self.target = target
        self.zero = zero
        self.offset = offset                  # () -> [Pa] the zero point subtracted from P1
        self.set_offset = set_offset          # ([Pa]) -> None
        self.pressure_range = pressure_range  # [Pa] absolute, of P1
        self.line_targets = line_targets if line_targets is not None else []
        self.responder = kb.KellerResponder(
            get_address=lambda: self.target.device_id, set_address=self._set_address,
            serial_number=lambda: int(self.image.values.get("serial_number", 0)),
            read_channel=self._channel, set_zero=self._set_zero,
            coefficient=self._coefficient, write_coefficient=self._write_coefficient)

    def handle_frame(self, frame: bytes) -> Optional[bytes]:
        """A KELLER frame from the line (CRC checked) -> the reply, or None (not ours, broadcast,
        or the sensor dead: a dropout that silences the device silences this side too)."""
        if self.target.silent:
            return None
        return self.responder.handle_frame(frame)

    def _channel(self, ch: int) -> float:
        value = float(self.image.values.get(kb.CHANNELS[ch][0], math.nan))
        return value * 1e5 if ch <= 2 else value + 273.15

    def _coefficient(self, nr: int) -> Optional[float]:
        """F30: 64 the P1 offset [bar] (P1 = raw - offset), 65 its gain, 80/81 P1's range [bar]."""
        if nr == kb.COEFF_OFFSET_P1:
            return float(self.offset()) / 1e5
        if nr == kb.COEFF_GAIN_P1:
            return 1.0
        if nr in (kb.COEFF_P1_MIN, kb.COEFF_P1_MAX):
            return self.pressure_range[nr - kb.COEFF_P1_MIN] / 1e5
        return None

    def _write_coefficient(self, nr: int, value: float) -> bool:
        if nr == kb.COEFF_OFFSET_P1 and self.set_offset is not None and math.isfinite(value):
            self.set_offset(value * 1e5)
            return True
        return False

    def _set_address(self, new: int) -> bool:
        if not 1 <= new <= 247 or any(t is not self.target and t.device_id == new for t in self.line_targets):
            return False  # a Modbus unicast address, and free on the line
        try:
            self.target.set_device_id(new)
        except ModbusError:
            return False
        return True

    def _set_zero(self, cmd: int, setpoint: Optional[float]) -> None:
        if cmd not in (0, 1):
            return  # P2 and CH0 are not fitted: accepted, nothing to zero
        try:
            self.zero(setpoint if cmd == 0 else None)
        except ValueError as exc:
            raise kb.KellerError(kb.EXC_PARAMETER, str(exc)) from None


class WitUart:
    """The WitMotion UART stream of an IMU device on its own pty.

    path: the pty symlink; baudrate [bit/s]: the line's initial speed (also the BAUD
    register's value); ``silent()``: whether the sensor is dead (dropout: no packets)."""

    IDLE = 0.05  # [s] a command still incomplete after this long is dropped

    def __init__(self, name: str, ctx: "DeviceContext", image: RegisterImage, path: Path, baudrate: int,
                 silent: Any = lambda: False) -> None:
        if baudrate not in wu.BAUD_CODES:
            raise ValueError(f"uart_baudrate must be one of {sorted(wu.BAUD_CODES)}, got {baudrate}")
        self.name = name
        self.ctx = ctx
        self.image = image
        self.silent = silent
        self.other: dict[int, int] = {}  # registers the map does not hold (offsets, ...)
        self.link = PtyLink(f"{name}-uart", path, baudrate=baudrate, on_data=self._on_data)
        self.decoder = wu.CommandDecoder()
        self.config = wu.WitConfig(self._read, self._write, defaults={wu.BAUD: wu.BAUD_CODES[baudrate]})
        self._periodic: Optional["Periodic"] = None
        self._rate = 0.0
        self._due = math.nan     # [s] simulation time of the next output cycle
        self._timer: Optional[asyncio.TimerHandle] = None
        self.packets = 0
        self.cycles = 0
        self.bad_input = 0

    @property
    def path(self) -> str:
        return self.link.path

    # -- registers (the image where the map has them) --

    def _read(self, reg: int) -> int:
        r = self.image.map.at(reg)
        if r is not None and r.address == reg and r.words == 1:
            return int(self.image.words(reg, 1)[0])
        return self.other.get(reg, 0)

    def _write(self, reg: int, value: int) -> None:
        r = self.image.map.at(reg)
        if r is not None and r.address == reg and r.words == 1:
            if r.on_write == "device_id":
                return  # the Modbus address is not the UART's to move
            self.image.store(r, r.decode([value]))
        else:
            self.other[reg] = value & 0xFFFF

    # -- the stream --

    async def start(self) -> str:
        path = await self.link.start()
        self._reschedule()
        return path

    async def close(self) -> None:
        if self._periodic is not None:
            self._periodic.cancel()
            self._periodic = None
        if self._timer is not None:
            self._timer.cancel()
        await self.link.close()

    def _reschedule(self) -> None:
        rate = self.config.rate
        code = self.config.rate_code
        if self._periodic is not None and rate == self._rate:
            return
        if self._periodic is not None:
            self._periodic.cancel()
            self._periodic = None
        self._rate = rate
        self._due = math.nan
        if rate > 0:
            self._periodic = self.ctx.every(f"{self.name}-uart", 1.0 / rate, self._tick, priority=21)
        elif code == wu.RRATE_SINGLE:
            self.ctx.at(self.ctx.now(), self._single, f"{self.name}-uart-single")

    def _single(self, t: float) -> None:
        self._send(t)
        self._write(wu.RRATE, wu.RRATE_NONE)  # one cycle, then none

    def _tick(self, t: float) -> None:
        if self.link.baudrate != self.config.baudrate:  # BAUD written through Modbus
            self.link.baudrate = self.config.baudrate
        if self.config.rate != self._rate:  # RRATE written through Modbus
            self._reschedule()
            return
        # the device's clock is its own: cycles the scheduler passed over (a loaded host) are
        # sent now, with the current values (at most a quarter of a second's worth at once)
        period = 1.0 / self._rate
        due = t if math.isnan(self._due) or t - self._due > 0.25 + period else self._due
        n = 0
        while due <= t + 1e-9 and n < 64:
            self._send(t)
            due += period
            n += 1
        self._due = max(due, t + period * 0.5)

    def _send(self, t: float) -> None:
        if self.silent():
            return
        self._set_time(t)
        out = b"".join(wu.encode_packet(k, [self._read(r) for r in wu.PACKET_REGISTERS[k]])
                       for k in wu.content_kinds(self.config.rsw))
        if out:
            self.link.write(out)
            self.packets += len(out) // wu.PACKET_SIZE
        self.cycles += 1

    def _set_time(self, t: float) -> None:
        if not self.config.rsw & 1:
            return
        stamp = dt.datetime.fromtimestamp(self.ctx.wall_time(t), tz=dt.timezone.utc)
        words = ((stamp.year - 2000) & 0xFF | stamp.month << 8, stamp.day | stamp.hour << 8,
                 stamp.minute | stamp.second << 8, stamp.microsecond // 1000)
        for reg, w in zip((wu.YYMM, wu.DDHH, wu.MMSS, wu.MS), words):
            self._write(reg, w)

    # -- commands --

    def _on_data(self, data: bytes) -> None:
        try:
            self.decoder.receive_data(data)
            self._handle(list(_drain(self.decoder)))
        except Exception:  # our bug: keep streaming
            log.exception("%s: error handling UART input", self.name)
        if self._timer is not None:
            self._timer.cancel()
        self._timer = asyncio.get_running_loop().call_later(self.IDLE, self._on_idle) \
            if self.decoder.buffered_bytes else None

    def _on_idle(self) -> None:
        self._timer = None
        self._handle(self.decoder.silence())

    def _handle(self, events: list[Any]) -> None:
        baud = self.config.baudrate
        for ev in events:
            if isinstance(ev, wu.Command):
                reply = self.config.handle(ev, self.ctx.now())
                if reply and not self.silent():
                    self.link.write(reply)
            else:
                self.bad_input += 1
        if self.config.baudrate != baud:
            log.info("%s: UART baud rate %d -> %d", self.name, baud, self.config.baudrate)
            self.link.baudrate = self.config.baudrate
        self._reschedule()


def _drain(decoder: wu.CommandDecoder) -> Any:
    for _ in range(4 * decoder.buffered_bytes + 4):
        ev = decoder.next_event()
        if ev is NEED_DATA:
            return
        yield ev


__all__ = ["KellerBus", "WitUart"]
