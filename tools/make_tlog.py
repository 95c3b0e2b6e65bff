"""Write the small MAVLink telemetry log of tests/data/flightlog-tlog-from-log171/ from a real log.

No real .tlog with a magnetometer was found under a usable licence, so this one is made with
pymavlink's own encoder (MAVLink 1 frames, each after the 8-byte big-endian receive time in us,
as ground stations write .tlog) from the ArduPilot DataFlash excerpt in
tests/data/flightlog-dronekit-log171 (CC BY-SA 3.0): HEARTBEAT (ArduPilot), PARAM_VALUE of every
COMPASS_* parameter, RAW_IMU (compass 0 = MAG, with IMU), SCALED_IMU2 (compass 1 = MAG2, with the same IMU),
ATTITUDE (ATT), SYS_STATUS (CURR), each as the autopilot would send it (the corrected field in
milligauss, time since boot). The receive time is boot time + RECEIVE_BASE_S. Run once:

    python tools/make_tlog.py [OUT_FILE]
"""
from __future__ import annotations

import math
import pathlib
import struct
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
SOURCE = ROOT / "tests/data/flightlog-dronekit-log171/log171_excerpt.bin"
OUT = ROOT / "tests/data/flightlog-tlog-from-log171/log171_excerpt.tlog"
RECEIVE_BASE_S = 1_430_000_000.0


class _Sink:
    def __init__(self):
        self.frames = []

    def write(self, buf):
        self.frames.append(bytes(buf))


def main(out=OUT):
    from pymavlink import DFReader
    from pymavlink.dialects.v10 import ardupilotmega as mavlink

    r = DFReader.DFReader_binary(str(SOURCE), zero_time_base=False)
    sink = _Sink()
    mav = mavlink.MAVLink(sink, srcSystem=1, srcComponent=1)
    records = []

    def emit(t_s, msg):
        records.append((t_s, msg.pack(mav)))

    compass = sorted(k for k in r.params if k.startswith("COMPASS_"))
    emit(0.0, mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0))
    for i, name in enumerate(compass):
        emit(0.0, mav.param_value_encode(name.encode(), float(r.params[name]), mavlink.MAV_PARAM_TYPE_REAL32,
                                         len(compass), i))
    imu = None
    while True:
        m = r.recv_msg()
        if m is None:
            break
        kind = m.get_type()
        if kind in ("IMU", "IMU2") or not hasattr(m, "TimeMS"):
            if kind == "IMU":
                imu = m
            continue
        t = m.TimeMS * 1e-3
        if kind == "MAG" and imu is not None:
            emit(t, mav.raw_imu_encode(m.TimeMS * 1000, *(int(round(v / 9.80665 * 1000)) for v in
                                                          (imu.AccX, imu.AccY, imu.AccZ)),
                                       *(int(round(v * 1000)) for v in (imu.GyrX, imu.GyrY, imu.GyrZ)),
                                       m.MagX, m.MagY, m.MagZ))
        elif kind == "MAG2" and imu is not None:
            emit(t, mav.scaled_imu2_encode(m.TimeMS, *(int(round(v / 9.80665 * 1000)) for v in
                                                       (imu.AccX, imu.AccY, imu.AccZ)),
                                           *(int(round(v * 1000)) for v in (imu.GyrX, imu.GyrY, imu.GyrZ)),
                                           m.MagX, m.MagY, m.MagZ))
        elif kind == "ATT":
            emit(t, mav.attitude_encode(m.TimeMS, *(math.radians(v) for v in (m.Roll, m.Pitch, m.Yaw)), 0, 0, 0))
        elif kind == "CURR":
            emit(t, mav.sys_status_encode(0, 0, 0, 0, int(m.Volt * 10), int(m.Curr), -1, 0, 0, 0, 0, 0, 0))
    out = pathlib.Path(out)
    with open(out, "wb") as f:
        for t, buf in records:
            f.write(struct.pack(">Q", int(round((RECEIVE_BASE_S + t) * 1e6))) + buf)
    print(f"wrote {out}: {len(records)} messages, {out.stat().st_size} bytes")


if __name__ == "__main__":
    main(*sys.argv[1:])
