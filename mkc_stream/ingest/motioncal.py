"""PJRC MotionCal text lines, as printed by many Arduino/Teensy/Adafruit calibration sketches.

``Raw:ax,ay,az,gx,gy,gz,mx,my,mz`` integers: 8192 LSB/g, 16 LSB/(deg/s), 10 LSB/uT.
``Uni:ax,ay,az,gx,gy,gz,mx,my,mz`` floats: m/s^2, rad/s, uT (Adafruit unified sensor units).

Sketches often print both kinds for every reading; one reading must give one sample, so the
``motioncal`` decoder keeps the kind of the first sample line it decodes and counts lines of the
other kind as ignored (``motioncal-uni`` / ``motioncal-raw`` choose the kind; Uni has the finer
magnetometer resolution, 0.01 uT against 0.1 uT). Lines carry no time: samples get the host
receive time. Other lines (banners, ``Cal1:`` echoes) are ignored; an unknown line with nine
comma-separated fields is counted as a damaged sample line. The format has no checksum: a
damaged digit cannot be detected.
"""
from __future__ import annotations

import math

from .decoder import BadFrame, LineDecoder, ascii_line, parse_floats
from .sample import Sample

G = 9.80665                        # m/s^2 per g
RAW_ACC = G / 8192.0               # m/s^2 per LSB
RAW_GYRO = math.pi / 180.0 / 16.0  # rad/s per LSB
RAW_MAG = 0.1                      # uT per LSB


class MotionCalDecoder(LineDecoder):
    name = "motioncal"

    def __init__(self, kind: str | None = None):
        super().__init__()
        if kind not in (None, "Raw", "Uni"):
            raise ValueError(f"MotionCal line kind must be 'Raw' or 'Uni', not {kind!r}")
        self.kind = kind          # None: lock onto the first kind decoded
        self.fixed = kind is not None

    def parse_line(self, line: bytes, t_host: float) -> Sample | None:
        text = ascii_line(line).strip()
        head, sep, body = text.partition(":")
        if head not in ("Raw", "Uni"):
            if text.count(",") == 8:
                raise BadFrame(f"unknown MotionCal line prefix {head[:8]!r}")
            return None
        cells = body.split(",")
        if len(cells) == 10 and not cells[-1].strip():   # a trailing comma some sketches print
            cells.pop()
        if len(cells) != 9:
            raise BadFrame(f"{head}: expected 9 fields, got {len(cells)}")
        if head == "Raw":
            try:
                v = [int(c) for c in cells]
            except ValueError:
                raise BadFrame("Raw: a field is not an integer") from None
            acc = (v[0] * RAW_ACC, v[1] * RAW_ACC, v[2] * RAW_ACC)
            gyro = (v[3] * RAW_GYRO, v[4] * RAW_GYRO, v[5] * RAW_GYRO)
            mag = (v[6] * RAW_MAG, v[7] * RAW_MAG, v[8] * RAW_MAG)
        else:
            v = parse_floats(cells, "Uni")
            acc, gyro, mag = tuple(v[0:3]), tuple(v[3:6]), tuple(v[6:9])
        if self.kind is None:
            self.kind = head
        elif head != self.kind:
            return None                    # the other kind of the same reading
        return Sample(t_host, mag, acc, gyro, host_time=True)


def encode_motioncal(acc, gyro, mag, kind: str = "Raw") -> bytes:
    """One MotionCal line (as a sketch prints it) from m/s^2, rad/s, uT; for the emulator and tests."""
    if kind == "Raw":
        v = [round(a / RAW_ACC) for a in acc] + [round(g / RAW_GYRO) for g in gyro] + \
            [round(m / RAW_MAG) for m in mag]
        return ("Raw:" + ",".join(str(int(x)) for x in v) + "\r\n").encode()
    v = [f"{a:.2f}" for a in acc] + [f"{g:.4f}" for g in gyro] + [f"{m:.2f}" for m in mag]
    return ("Uni:" + ",".join(v) + "\r\n").encode()
