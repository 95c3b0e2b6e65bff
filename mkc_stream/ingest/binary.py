"""The mkc binary frame: sync word, header, payload, CRC; encoder and resynchronising decoder.

Every field is little-endian::

    offset size  field
    0      1     0xA5            sync, first byte
    1      1     0x5A            sync, second byte
    2      1     version << 4 | type   (version 1; types below)
    3      1     payload length L (bytes); fixed by the type
    4      2     seq, uint16, +1 per frame generated (wraps), so the host counts frames lost
    6      4     device time, uint32 microseconds (wraps every 71.6 minutes; the host unwraps)
    10     L     payload
    10+L   2     CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor)
                 over bytes 2 .. 9+L (header after the sync word, and the payload)

    type 1  MAG_F32  L = 12: mx, my, mz float32 [uT]
    type 2  IMU_F32  L = 40: mx, my, mz [uT], ax, ay, az [m/s^2], gx, gy, gz [rad/s], temp [degC], float32
    type 3  MAG_I16  L = 6:  mx, my, mz int16 [0.01 uT] (the CAN frame's scaling)

Decoding: find the sync word; check version, type and length; wait for the whole frame; check
the CRC. On any failure advance ONE byte and search again, so a damaged frame (even a damaged
length byte) never hides the good frame after it. Frames of an unknown type with a good CRC
are skipped and counted as ignored (a newer firmware). Missing sequence numbers between two
good frames are bad frames when bytes were discarded between them, else drops.
"""
from __future__ import annotations

import binascii
import math
import struct

from .counters import SeqTracker
from .decoder import Decoder, SampleList
from .sample import Sample

SYNC = b"\xa5\x5a"
VERSION = 1
HEADER = struct.Struct("<BBHI")        # ver_type, length, seq, t_us (after the sync word)
HEADER_LEN = 2 + HEADER.size           # 10
CRC_LEN = 2
MAG_F32, IMU_F32, MAG_I16 = 1, 2, 3
PAYLOAD = {MAG_F32: struct.Struct("<3f"), IMU_F32: struct.Struct("<10f"), MAG_I16: struct.Struct("<3h")}
MAX_PAYLOAD = 64
I16_SCALE = 0.01                       # uT per LSB of MAG_I16


def crc16_ccitt_false(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (check value 0x29B1 for b"123456789"); binascii does it in C."""
    return binascii.crc_hqx(data, crc)


def encode_frame(seq: int, t_us: int, mag, acc=None, gyro=None, temp=None, ftype: int | None = None) -> bytes:
    """One frame. ``ftype`` defaults to IMU_F32 when acc is given, else MAG_F32."""
    if ftype is None:
        ftype = IMU_F32 if acc is not None else MAG_F32
    if ftype == MAG_F32:
        payload = PAYLOAD[MAG_F32].pack(*mag)
    elif ftype == IMU_F32:
        nan3 = (math.nan,) * 3
        payload = PAYLOAD[IMU_F32].pack(*mag, *(acc or nan3), *(gyro or nan3),
                                        math.nan if temp is None else temp)
    elif ftype == MAG_I16:
        q = [round(m / I16_SCALE) for m in mag]
        if any(abs(v) > 32767 for v in q):
            raise ValueError(f"MAG_I16 holds +-327.67 uT; got {mag}")
        payload = PAYLOAD[MAG_I16].pack(*q)
    else:
        raise ValueError(f"unknown frame type {ftype}")
    head = HEADER.pack(VERSION << 4 | ftype, len(payload), seq & 0xFFFF, t_us & 0xFFFFFFFF)
    body = head + payload
    return SYNC + body + struct.pack("<H", crc16_ccitt_false(body))


class BinaryDecoder(Decoder):
    name = "binary"
    time_source = "device"

    def __init__(self):
        super().__init__()
        self._buf = bytearray()
        self._seq = SeqTracker(1 << 16)
        self._synced = False              # a good frame was seen (bytes skipped before are lead-in)
        self._skipped_since_good = 0
        self._t_last: int | None = None   # last raw uint32 time
        self._t_wraps = 0
        self._t_offset = 0.0              # added after a device restart, so time never goes back
        self._t_out: float | None = None  # last time given out, and the host time then
        self._th_out = math.nan
        self._dt = 0.0
        self._restart = False
        self.crc_errors = 0
        self.time_resets = 0

    def feed(self, data: bytes, t_host: float = math.nan) -> list[Sample]:
        self._buf += data
        return self._decode(False, t_host)

    def _decode(self, final: bool, t_host: float = math.nan) -> list[Sample]:
        """Decode complete frames; ``final``: no more bytes will come, so a frame that cannot
        complete is a false sync (skip a byte and go on) rather than one to wait for."""
        buf = self._buf
        out = SampleList(self.counts)
        pos, n = 0, len(buf)
        while True:
            p = buf.find(SYNC, pos)
            if p < 0:
                # keep a last 0xA5: it may be the first half of a sync word
                keep = 1 if n > pos and buf[n - 1] == 0xA5 else 0
                self._skip(n - keep - pos)
                pos = n - keep
                break
            self._skip(p - pos)
            pos = p
            if n - pos < HEADER_LEN:
                if final and n - pos > 2:
                    self._skip(1)
                    pos += 1
                    continue
                break
            vt, length, seq, t_us = HEADER.unpack_from(buf, pos + 2)
            ftype = vt & 0x0F
            known = PAYLOAD.get(ftype)
            if vt >> 4 != VERSION or length > MAX_PAYLOAD or (known is not None and known.size != length):
                self._skip(1)
                pos += 1
                continue
            end = pos + HEADER_LEN + length + CRC_LEN
            if end > n:
                if final:
                    self._skip(1)
                    pos += 1
                    continue
                break                                         # wait for the rest of the frame
            crc = buf[end - 2] | buf[end - 1] << 8
            if crc16_ccitt_false(buf[pos + 2:end - 2]) != crc:
                self.crc_errors += 1
                self._skip(1)
                pos += 1
                continue
            if known is None:
                self.counts.ignored += 1
            else:
                out.append(self._sample(ftype, known.unpack_from(buf, pos + HEADER_LEN), seq, t_us, t_host))
            pos = end
        del buf[:pos]
        return out

    def _skip(self, k: int):
        if k <= 0:
            return
        if self._synced:
            if self._skipped_since_good == 0:
                self.counts.resyncs += 1
            self.counts.skipped_bytes += k
            self._skipped_since_good += k
        else:
            self.counts.lead_in_bytes += k

    def _sample(self, ftype, v, seq, t_us, t_host) -> Sample:
        self.counts.frames += 1
        missing = self._seq.missing(seq)
        if missing is None:
            self.counts.seq_resets += 1
        elif self._skipped_since_good:
            self.count_bad(f"{missing} frame(s) lost to damaged bytes before seq {seq}", missing)
        else:
            self.counts.drops += missing
        self._synced = True
        self._skipped_since_good = 0
        t = self._time(t_us, self._restart or missing is None, t_host)
        self._restart = False
        if ftype == MAG_F32:
            return Sample(t, (v[0], v[1], v[2]), seq=seq)
        if ftype == MAG_I16:
            return Sample(t, (v[0] * I16_SCALE, v[1] * I16_SCALE, v[2] * I16_SCALE), seq=seq)
        acc = None if math.isnan(v[3]) else (v[3], v[4], v[5])
        gyro = None if math.isnan(v[6]) else (v[6], v[7], v[8])
        temp = None if math.isnan(v[9]) else v[9]
        return Sample(t, (v[0], v[1], v[2]), acc, gyro, temp, seq)

    def _time(self, t_us: int, restarted: bool, t_host: float) -> float:
        """Device seconds: the 32-bit microsecond clock unwrapped; after a device restart (its
        counter and clock start again) time goes on from the last time given out, plus the time
        the host heard nothing (counted in ``time_resets``), so a recording stays in order."""
        if (not restarted and self._t_last is not None and t_us < self._t_last
                and self._t_last - t_us > 1 << 31):
            self._t_wraps += 1                                  # the 71.6-minute wrap
        self._t_last = t_us
        t = ((self._t_wraps << 32) + t_us) * 1e-6 + self._t_offset
        if self._t_out is not None and t < self._t_out:
            waited = t_host - self._th_out
            gap = waited if math.isfinite(waited) and waited > self._dt else self._dt
            self._t_offset += self._t_out + gap - t
            t = self._t_out + gap
            self.time_resets += 1
        if self._t_out is not None and t > self._t_out:
            self._dt = t - self._t_out
        self._t_out, self._th_out = t, t_host
        return t

    def flush(self) -> list[Sample]:
        # a false sync word near the end may claim more bytes than will ever come: the good
        # frames behind it are still decoded
        out = self._decode(final=True)
        if self._buf:
            self.counts.truncated += 1
            self._skip(len(self._buf))
            self._buf.clear()
        return out

    def reset_stream(self):
        self._skip(len(self._buf))
        self._buf.clear()
        self._seq.reset()
        self._synced = False
        self._skipped_since_good = 0
        self._restart = True              # the device may have restarted meanwhile
