"""Modbus PDUs and ADUs, device side (sans-I/O): the request PDUs the emulated devices serve,
their normal and exception responses, the MBAP (TCP) and RTU frames around them, and the
CRC-16/MODBUS. No I/O, and nothing beyond ``struct`` and ``dataclasses``.

Written from the Modbus Application Protocol Specification V1.1b3 (function codes and PDU
layouts, section 6; exception responses, section 7), the Modbus Messaging on TCP/IP
Implementation Guide V1.0b (the MBAP header, section 3.1.3) and Modbus over Serial Line
V1.02 (the RTU frame, section 2.5.1; its CRC, section 2.5.1.2 and appendix B).

Requests served (everything else is :data:`~hilsim.protocols.registers.ILLEGAL_FUNCTION`):

======  =========================  ==========================================================
code    function                   request PDU after the code
======  =========================  ==========================================================
0x03    read holding registers     address (2), quantity (2): 1..125
0x04    read input registers       address (2), quantity (2): 1..125
0x06    write single register      address (2), value (2)
0x10    write multiple registers   address (2), quantity (2): 1..123, byte count (1) = 2 x
                                   quantity, that many bytes of values
======  =========================  ==========================================================

A request of a served function that breaks its layout (a wrong length, a quantity out of
range, a byte count that disagrees) is :data:`~hilsim.protocols.registers.ILLEGAL_VALUE`,
as the spec's server state diagrams have it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Final, Sequence, Union

from hilsim.protocols.registers import ILLEGAL_FUNCTION, ILLEGAL_VALUE, ModbusError

READ_HOLDING_REGISTERS: Final = 0x03
READ_INPUT_REGISTERS: Final = 0x04
WRITE_SINGLE_REGISTER: Final = 0x06
WRITE_MULTIPLE_REGISTERS: Final = 0x10
MAX_READ_COUNT: Final = 125   # 0x7D: 250 data bytes in the response
MAX_WRITE_COUNT: Final = 123  # 0x7B: 246 data bytes in the request
EXCEPTION_FLAG: Final = 0x80  # an exception response's function code: the request's + 0x80

RTU_MIN_SIZE: Final = 4  # address, function code, CRC (2)
MBAP: Final = struct.Struct(">HHHB")  # transaction id, protocol id (0), length (unit id + PDU), unit id


# ------------------------------------------------------------------ CRC-16/MODBUS


def _crc_table() -> tuple[int, ...]:
    """The CRC of each byte value alone from a zero register: the serial line spec's shift
    register (appendix B), eight shifts right, XOR 0xA001 when the bit shifted out is 1."""
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


CRC_TABLE: Final = _crc_table()


def crc16(data: bytes | bytearray, start: int = 0, end: int | None = None) -> int:
    """CRC-16/MODBUS of ``data[start:end]`` (polynomial 0x8005 reflected as 0xA001, register
    preset 0xFFFF, no final XOR). On the wire it follows the bytes it covers low byte first."""
    crc, table = 0xFFFF, CRC_TABLE
    for i in range(start, len(data) if end is None else end):
        crc = (crc >> 8) ^ table[(crc ^ data[i]) & 0xFF]
    return crc


def crc_ok(buf: bytes | bytearray, start: int, end: int) -> bool:
    """``buf[start:end]`` ends with the CRC-16/MODBUS of the bytes before it (low byte first).
    In place, no slice: the RTU decoder calls it for every candidate start while it hunts."""
    return crc16(buf, start, end - 2) == buf[end - 2] | (buf[end - 1] << 8)


# ------------------------------------------------------------------ requests


@dataclass(frozen=True)
class ReadRegisters:
    """03 / 04: ``count`` registers from ``address``."""

    function: int
    address: int
    count: int


@dataclass(frozen=True)
class WriteRegisters:
    """06 (one value) / 16: ``values`` to the registers from ``address``."""

    function: int
    address: int
    values: tuple[int, ...]


RequestPdu = Union[ReadRegisters, WriteRegisters]

_ADDRESS_COUNT: Final = struct.Struct(">HH")
_WRITE_MULTIPLE_HEAD: Final = struct.Struct(">HHB")  # address, quantity, byte count


def decode_request(pdu: bytes | bytearray) -> RequestPdu:
    """A request PDU (function code + data) -> the request; raises :class:`ModbusError`:
    ILLEGAL_FUNCTION for a function code not in the table above, ILLEGAL_VALUE for a served
    function whose PDU breaks its layout."""
    fc = pdu[0] if pdu else 0
    if fc in (READ_HOLDING_REGISTERS, READ_INPUT_REGISTERS, WRITE_SINGLE_REGISTER):
        if len(pdu) != 5:
            raise ModbusError(ILLEGAL_VALUE, f"function {fc}: PDU of {len(pdu)} bytes")
        address, n = _ADDRESS_COUNT.unpack_from(pdu, 1)
        if fc == WRITE_SINGLE_REGISTER:
            return WriteRegisters(fc, address, (n,))
        if not 1 <= n <= MAX_READ_COUNT:
            raise ModbusError(ILLEGAL_VALUE, f"function {fc}: count {n} outside 1..{MAX_READ_COUNT}")
        return ReadRegisters(fc, address, n)
    if fc == WRITE_MULTIPLE_REGISTERS:
        if len(pdu) < 6:
            raise ModbusError(ILLEGAL_VALUE, "function 16: short PDU")
        address, count, nbytes = _WRITE_MULTIPLE_HEAD.unpack_from(pdu, 1)
        if not 1 <= count <= MAX_WRITE_COUNT or nbytes != 2 * count or len(pdu) != 6 + nbytes:
            raise ModbusError(ILLEGAL_VALUE, f"function 16: count {count}, byte count {nbytes}")
        return WriteRegisters(fc, address, struct.unpack_from(f">{count}H", pdu, 6))
    raise ModbusError(ILLEGAL_FUNCTION, f"function {fc:#04x} not implemented")


# ------------------------------------------------------------------ responses


def read_response(function: int, registers: Sequence[int]) -> bytes:
    """03 / 04 response PDU: function code, byte count, the registers (each high byte first)."""
    return struct.pack(f">BB{len(registers)}H", function, 2 * len(registers), *registers)


def write_response(request: WriteRegisters) -> bytes:
    """06 response PDU: the request echoed (address, value); 16: address and quantity written."""
    if request.function == WRITE_SINGLE_REGISTER:
        return struct.pack(">BHH", request.function, request.address, request.values[0])
    return struct.pack(">BHH", request.function, request.address, len(request.values))


def exception_response(function: int, code: int) -> bytes:
    """Exception response PDU: the request's function code with the top bit set, the exception code."""
    return bytes([(function & 0x7F) | EXCEPTION_FLAG, code])


@dataclass(frozen=True)
class Response:
    """A device's answer: to ``unit`` (the address the request came to), response ``pdu``."""

    unit: int
    pdu: bytes

    @property
    def is_exception(self) -> bool:
        return bool(self.pdu[0] & EXCEPTION_FLAG)

    @property
    def exception_code(self) -> int:
        """The exception code of an exception response, 0 for a normal one."""
        return self.pdu[1] if self.is_exception else 0


# ------------------------------------------------------------------ framing


def mbap_frame(transaction_id: int, unit: int, pdu: bytes) -> bytes:
    """Modbus TCP ADU: MBAP header (protocol id 0, length = unit id + PDU) + PDU."""
    return MBAP.pack(transaction_id, 0, len(pdu) + 1, unit) + pdu


def rtu_frame(unit: int, pdu: bytes) -> bytes:
    """Modbus RTU ADU: address + PDU + CRC-16/MODBUS, low byte first."""
    body = bytes([unit]) + pdu
    return body + crc16(body).to_bytes(2, "little")


__all__ = ["CRC_TABLE", "EXCEPTION_FLAG", "MAX_READ_COUNT", "MAX_WRITE_COUNT", "MBAP", "READ_HOLDING_REGISTERS",
           "READ_INPUT_REGISTERS", "RTU_MIN_SIZE", "WRITE_MULTIPLE_REGISTERS", "WRITE_SINGLE_REGISTER",
           "ReadRegisters", "RequestPdu", "Response", "WriteRegisters", "crc16", "crc_ok", "decode_request",
           "exception_response", "mbap_frame", "read_response", "rtu_frame", "write_response"]
