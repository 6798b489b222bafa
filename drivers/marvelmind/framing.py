"""Marvelmind stream framing: bytes in, CRC-checked (code, payload) frames out, no I/O.

Theory of operation: a frame is `ff 47`, a little-endian u16 code, a u8 payload size N, N payload bytes and a
CRC-16/MODBUS (low byte first) over everything before it. The scanner looks for the header with `bytes.find`, then
rejects a candidate as early as its bytes allow: a code outside the whitelist, a size the code never has (exact for
fixed-size codes, 1 + 8n or 1 + 14n for the beacon lists, at least 26 for 0x0081), then a bad CRC. After any
rejection it rescans from the byte after the rejected header, so a real frame that starts inside a bad one is found
(the vendor's C library and ArduPilot restart after the whole bad frame and lose it).

A frame is returned by the very `feed` that brings its last byte, even when an earlier candidate header is still
waiting for bytes: a candidate whose claimed extent wholly holds a complete CRC-valid frame is a false header and is
rejected at once, whether or not its own bytes are all there. Every decision depends on the bytes only, never on how
they were split into reads, so any chunking gives the same frames and counters. Between calls the scanner holds only
the tail that could still start a frame: at most one incomplete candidate (< 262 bytes), so its buffer is capped by
construction. `finish()` counts that tail as junk at the end of a stream.
"""

from __future__ import annotations

from drivers.marvelmind.crc import crc16_modbus
from drivers.marvelmind.events import Counters

HEADER = b"\xff\x47"  # destination 0xFF (device to host), packet type 0x47 (streaming)
OVERHEAD = 7  # header 2, code 2, size 1, CRC 2
MAX_FRAME = 255 + OVERHEAD
SHORTEST_FRAME = 1 + OVERHEAD  # an empty stationary-beacon list

# The streaming codes robotd decodes, with the payload size each one always has.
FIXED_SIZES: dict[int, int] = {
    0x0001: 16,  # position, cm
    0x0011: 22,  # position, mm
    0x0003: 32,  # raw IMU
    0x0083: 36,  # raw IMU, 64-bit timestamp
    0x0004: 32,  # raw distances
    0x0084: 36,  # raw distances, 64-bit timestamp
    0x0005: 42,  # IMU fusion
    0x0085: 46,  # IMU fusion, 64-bit timestamp
    0x0006: 16,  # telemetry
    0x0007: 16,  # quality
}
MIN_SIZES: dict[int, int] = {0x0081: 26}  # position, mm, 64-bit timestamp, then optional extension records
BEACON_ITEM_SIZES: dict[int, int] = {0x0002: 8, 0x0012: 14}  # stationary beacons: u8 n, then n items
CODES = frozenset(FIXED_SIZES) | frozenset(MIN_SIZES) | frozenset(BEACON_ITEM_SIZES)

Frame = tuple[int, bytes]
"""A CRC-checked frame: its code and its payload."""


class FrameScanner:
    """Finds CRC-valid frames of the whitelisted codes in a byte stream delivered in arbitrary pieces."""

    def __init__(self, counters: Counters | None = None) -> None:
        self.counters = counters if counters is not None else Counters()
        self._buffer = bytearray()  # the undecided tail of the stream: < MAX_FRAME bytes between calls

    @property
    def pending(self) -> int:
        """Bytes held for a frame that may still complete."""
        return len(self._buffer)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """The frames completed by `data`, in stream order."""
        buffer = self._buffer
        if buffer:
            buffer += data
            return self._scan(buffer)
        return self._scan(bytes(data))

    def finish(self) -> None:
        """End of stream: the held bytes (an incomplete header, or a lone 0xFF) are junk.

        They hold no frame: a complete valid frame inside a waiting candidate's extent rejects the candidate at once.
        """
        if len(self._buffer) >= len(HEADER):
            self.counters.truncated += 1
        self.counters.junk_bytes += len(self._buffer)
        self._buffer.clear()

    def _scan(self, stream: bytes | bytearray) -> list[Frame]:
        counters = self.counters
        end = len(stream)
        find = stream.find
        frames: list[Frame] = []
        consumed = 0  # every byte before this is in a returned frame or counted as junk
        position = 0  # where the next header search starts
        while True:
            start = find(HEADER, position)
            if start < 0:
                # A last 0xFF may be the first half of a header split across reads.
                start = end - 1 if end > consumed and stream[end - 1] == 0xFF else end
                break
            claimed = _claimed_length(stream, start, end)
            if claimed == _UNKNOWN_CODE:
                counters.unknown_codes += 1
            elif claimed == _BAD_SIZE:
                counters.size_rejections += 1
            elif claimed == _NEED_MORE:
                break  # wait for the code and size
            elif find(HEADER, start + 1, start + claimed) >= 0 and _holds_frame(
                stream, start, min(start + claimed, end)
            ):
                counters.false_headers += 1
            elif start + claimed > end:
                break  # wait for the rest of the frame
            elif crc16_modbus(stream, start, start + claimed):  # over the whole frame, CRC included, a good CRC gives 0
                counters.crc_failures += 1
            else:
                frame_end = start + claimed
                counters.junk_bytes += start - consumed
                frames.append((stream[start + 2] | stream[start + 3] << 8, bytes(stream[start + 5 : frame_end - 2])))
                consumed = position = frame_end
                continue
            position = start + 1  # rejected: rescan from the byte after its header
        # `start` is where the undecided tail begins; everything before it that is not in a frame is junk.
        counters.junk_bytes += start - consumed
        if stream is self._buffer:
            del self._buffer[:start]
        else:
            self._buffer = bytearray(stream[start:])
        return frames


_UNKNOWN_CODE, _BAD_SIZE, _NEED_MORE = -1, -2, -3


def _claimed_length(stream: bytes | bytearray, start: int, end: int) -> int:
    """The frame length the header at `start` claims, or why it claims none (a negative marker)."""
    if end - start < 5:
        return _NEED_MORE
    code = stream[start + 2] | stream[start + 3] << 8
    size = stream[start + 4]
    expected = FIXED_SIZES.get(code)
    if expected is not None:
        return size + OVERHEAD if size == expected else _BAD_SIZE
    item_size = BEACON_ITEM_SIZES.get(code)
    if item_size is not None:
        if end - start < 6:
            return _NEED_MORE
        return size + OVERHEAD if size == 1 + item_size * stream[start + 5] else _BAD_SIZE
    minimum = MIN_SIZES.get(code)
    if minimum is not None:
        return size + OVERHEAD if size >= minimum else _BAD_SIZE
    return _UNKNOWN_CODE


def _holds_frame(stream: bytes | bytearray, start: int, limit: int) -> bool:
    """True when a complete CRC-valid frame starts after `start` and ends by `limit`."""
    last = limit - SHORTEST_FRAME + len(HEADER)  # the header of the shortest frame must end by here
    inner = stream.find(HEADER, start + 1, last)
    while inner >= 0:
        claimed = _claimed_length(stream, inner, limit)
        if claimed > 0 and inner + claimed <= limit and not crc16_modbus(stream, inner, inner + claimed):
            return True
        inner = stream.find(HEADER, inner + 1, last)
    return False
