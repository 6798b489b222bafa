"""CRC-16/MODBUS (reflected polynomial 0xA001, init 0xFFFF, no final xor), the checksum of Marvelmind frames.

Theory of operation: the textbook table-driven CRC takes one table look-up per byte. Because the register is 16 bits
wide, two bytes can be folded in at once: xor the little-endian 16-bit word into the register, then shift 16 zero bits
through it, which is a function of the register alone and so a 65536-entry table. That halves the Python-level work
of checking a frame, the hot path of the parser. The byte table finishes an odd-length message.
"""

from __future__ import annotations

import struct

POLYNOMIAL = 0xA001  # 0x8005 reflected
INIT = 0xFFFF


def _byte_table() -> tuple[int, ...]:
    """The register after shifting 8 zero bits through each possible low byte."""
    table = []
    for value in range(256):
        register = value
        for _ in range(8):
            register = (register >> 1) ^ POLYNOMIAL if register & 1 else register >> 1
        table.append(register)
    return tuple(table)


BYTE_TABLE = _byte_table()


def _word_table() -> tuple[int, ...]:
    """The register after shifting 16 zero bits through each possible register value (two byte steps)."""
    byte_table = BYTE_TABLE
    table = []
    for register in range(65536):
        once = (register >> 8) ^ byte_table[register & 0xFF]
        table.append((once >> 8) ^ byte_table[once & 0xFF])
    return tuple(table)


WORD_TABLE = _word_table()

_WORD_FORMATS = [struct.Struct(f"<{count}H") for count in range(140)]  # a frame is at most 262 bytes: 131 words


def crc16_modbus(data: bytes | bytearray | memoryview, start: int = 0, end: int | None = None) -> int:
    """CRC-16/MODBUS of data[start:end]; over a whole frame, its CRC included, it is 0."""
    if end is None:
        end = len(data)
    register = INIT
    words = (end - start) >> 1
    if words:
        word_table = WORD_TABLE
        word_format = _WORD_FORMATS[words] if words < len(_WORD_FORMATS) else struct.Struct(f"<{words}H")
        for word in word_format.unpack_from(data, start):
            register = word_table[register ^ word]
    if (end - start) & 1:
        register = (register >> 8) ^ BYTE_TABLE[(register ^ data[end - 1]) & 0xFF]
    return register


def crc16_modbus_bitwise(data: bytes) -> int:
    """Reference CRC-16/MODBUS, one bit at a time: the definition the tables are checked against."""
    register = INIT
    for byte in data:
        register ^= byte
        for _ in range(8):
            register = (register >> 1) ^ POLYNOMIAL if register & 1 else register >> 1
    return register
