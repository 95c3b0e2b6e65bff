"""The built-in CAN frame layout: one classic CAN frame per magnetometer sample.

8 data bytes, little-endian: int16 mx, int16 my, int16 mz in units of 0.01 uT (+-327.67 uT),
then uint16 sequence counter (+1 per sample, wraps). Arbitration id configurable, default 0x110.
"""
from __future__ import annotations

import struct

DEFAULT_CAN_ID = 0x110
SCALE = 0.01                 # uT per LSB
LAYOUT = struct.Struct("<hhhH")


def encode_mag_frame(mag_ut, seq: int) -> bytes:
    q = [round(m / SCALE) for m in mag_ut]
    if any(abs(v) > 32767 for v in q):
        raise ValueError(f"the CAN frame holds +-327.67 uT per axis; got {tuple(mag_ut)}")
    return LAYOUT.pack(q[0], q[1], q[2], seq & 0xFFFF)


def decode_mag_frame(data: bytes) -> tuple[tuple[float, float, float], int]:
    if len(data) != LAYOUT.size:
        raise ValueError(f"expected {LAYOUT.size} data bytes, got {len(data)}")
    mx, my, mz, seq = LAYOUT.unpack(bytes(data))
    return (mx * SCALE, my * SCALE, mz * SCALE), seq
