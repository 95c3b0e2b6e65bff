"""VectorNav ASCII asynchronous outputs with checksum: ``$VNYMR`` and ``$VNIMU``.

``$VNYMR,yaw,pitch,roll,magX,magY,magZ,accX,accY,accZ,gyroX,gyroY,gyroZ*CS``
``$VNIMU,magX,magY,magZ,accX,accY,accZ,gyroX,gyroY,gyroZ,temp,pressure*CS``

Magnetometer in gauss (x100 -> uT), acceleration m/s^2, angular rate rad/s, temperature degC,
pressure kPa (kept as the auxiliary signal ``pressure``; yaw/pitch/roll are dropped). ``CS`` is
either the 8-bit XOR of the bytes between ``$`` and ``*`` (2 hex digits) or the 16-bit
CRC-CCITT (XMODEM: poly 0x1021, init 0) of the same bytes (4 hex digits); ``XX`` means the
sensor's checksum is switched off (accepted, counted as ``unchecked``). Other ``$VN`` messages
are ignored; a line that is not a ``$VN`` message is damage (a VectorNav sends nothing else).
The ASCII outputs carry no time: samples get the host receive time.
"""
from __future__ import annotations

import binascii
import functools
import operator

from .decoder import BadFrame, LineDecoder, ascii_line, parse_floats
from .sample import Sample

GAUSS_TO_UT = 100.0


def xor8(body: bytes) -> int:
    return functools.reduce(operator.xor, body, 0)


def crc16_xmodem(body: bytes) -> int:
    return binascii.crc_hqx(body, 0)


class VectorNavDecoder(LineDecoder):
    name = "vectornav"

    def __init__(self):
        super().__init__()
        self.unchecked = 0

    def parse_line(self, line: bytes, t_host: float) -> Sample | None:
        text = ascii_line(line).strip()
        if not text.startswith("$VN"):
            raise BadFrame("not a $VN message")
        body, star, cs = text[1:].rpartition("*")
        if not star:
            raise BadFrame("no '*' checksum field")
        raw = body.encode()
        if cs == "XX":
            self.unchecked += 1
        else:
            try:
                want = int(cs, 16)
            except ValueError:
                raise BadFrame(f"checksum field {cs[:6]!r} is not hex") from None
            if len(cs) == 2:
                ok = xor8(raw) == want
            elif len(cs) == 4:
                ok = crc16_xmodem(raw) == want
            else:
                raise BadFrame(f"checksum field has {len(cs)} digits")
            if not ok:
                raise BadFrame("checksum mismatch")
        cells = body.split(",")
        kind = cells[0]
        if kind == "VNYMR":
            if len(cells) != 13:
                raise BadFrame(f"VNYMR: expected 12 fields, got {len(cells) - 1}")
            v = parse_floats(cells[4:], "VNYMR")
            return Sample(t_host, (v[0] * GAUSS_TO_UT, v[1] * GAUSS_TO_UT, v[2] * GAUSS_TO_UT),
                          (v[3], v[4], v[5]), (v[6], v[7], v[8]), host_time=True)
        if kind == "VNIMU":
            if len(cells) != 12:
                raise BadFrame(f"VNIMU: expected 11 fields, got {len(cells) - 1}")
            v = parse_floats(cells[1:], "VNIMU")
            return Sample(t_host, (v[0] * GAUSS_TO_UT, v[1] * GAUSS_TO_UT, v[2] * GAUSS_TO_UT),
                          (v[3], v[4], v[5]), (v[6], v[7], v[8]), v[9], host_time=True,
                          aux={"pressure": v[10]})
        return None


def encode_vn(kind: str, mag_ut, acc, gyro, temp=20.0, pressure=101.3, ypr=(0.0, 0.0, 0.0),
              checksum: str = "xor") -> bytes:
    """One VectorNav line; for the emulator and tests. checksum: "xor", "crc" or "off"."""
    g = [m / GAUSS_TO_UT for m in mag_ut]
    if kind == "VNYMR":
        fields = [f"{a:+08.3f}" for a in ypr] + [f"{x:+08.4f}" for x in g] + \
                 [f"{a:+07.3f}" for a in acc] + [f"{w:+09.6f}" for w in gyro]
    elif kind == "VNIMU":
        fields = [f"{x:+08.4f}" for x in g] + [f"{a:+07.3f}" for a in acc] + \
                 [f"{w:+09.6f}" for w in gyro] + [f"{temp:+05.1f}", f"{pressure:+07.3f}"]
    else:
        raise ValueError(f"unknown VectorNav message {kind!r}")
    body = (kind + "," + ",".join(fields)).encode()
    cs = {"xor": lambda: f"{xor8(body):02X}", "crc": lambda: f"{crc16_xmodem(body):04X}",
          "off": lambda: "XX"}[checksum]()
    return b"$" + body + b"*" + cs.encode() + b"\r\n"
