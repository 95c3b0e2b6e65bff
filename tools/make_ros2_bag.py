"""Write the small ROS 2 bag of tests/data/rosbag-ck-explorer-ros2/ from a real recording.

No real ROS 2 bag with a magnetometer was found under a usable licence, so this one is made with
rosbags' own writer (MCAP storage) from the CK-Explorer accelerometer + magnetometer log (Apache-2.0, in
tests/data/ck-explorer-accmag): every STEP-th row, stamped at a nominal RATE_HZ (the log has no
timestamps), as /imu/mag (sensor_msgs/MagneticField, its gauss-like values x1e-4 -> tesla) and
/imu/data (sensor_msgs/Imu, acceleration g x 9.80665 -> m/s^2, no orientation). Run once:

    python tools/make_ros2_bag.py [OUT_DIR]
"""
from __future__ import annotations

import pathlib
import shutil
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
SOURCE = ROOT / "tests/data/ck-explorer-accmag/acc_mag_log.csv"
OUT = ROOT / "tests/data/rosbag-ck-explorer-ros2/ck_explorer_bag"
STEP = 15          # every 15th of the log's 12,000 rows: 800 samples spanning the whole rotation
RATE_HZ = 50.0
GAUSS_TO_TESLA = 1e-4
G = 9.80665


def messages(ts, ros1=False):
    """(ns, MagneticField, Imu) per kept row of SOURCE, built with the typestore ts (ROS 1 headers
    carry a sequence number as well)."""
    data = np.loadtxt(SOURCE, delimiter=",", skiprows=1)[::STEP]
    acc, mag = data[:, 0:3], data[:, 3:6]
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    Vector3, Quaternion = ts.types["geometry_msgs/msg/Vector3"], ts.types["geometry_msgs/msg/Quaternion"]
    MagneticField, Imu = ts.types["sensor_msgs/msg/MagneticField"], ts.types["sensor_msgs/msg/Imu"]
    zeros9 = np.zeros(9)
    no_orientation = np.r_[-1.0, np.zeros(8)]          # REP 145: orientation unknown
    for i in range(len(data)):
        ns = 1_000_000_000 + int(round(i * 1e9 / RATE_HZ))
        stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        header = Header(seq=i, stamp=stamp, frame_id="imu") if ros1 else Header(stamp=stamp, frame_id="imu")
        m = MagneticField(header=header, magnetic_field=Vector3(*(mag[i] * GAUSS_TO_TESLA)),
                          magnetic_field_covariance=zeros9)
        imu = Imu(header=header, orientation=Quaternion(0.0, 0.0, 0.0, 0.0), orientation_covariance=no_orientation,
                  angular_velocity=Vector3(0.0, 0.0, 0.0), angular_velocity_covariance=zeros9,
                  linear_acceleration=Vector3(*(acc[i] * G)), linear_acceleration_covariance=zeros9)
        yield ns, m, imu


def main(out=OUT):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    out = pathlib.Path(out)
    if out.exists():
        shutil.rmtree(out)
    n = 0
    with Writer(out, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        cm = writer.add_connection("/imu/mag", "sensor_msgs/msg/MagneticField", typestore=ts)
        ci = writer.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=ts)
        for ns, m, imu in messages(ts):
            writer.write(cm, ns, ts.serialize_cdr(m, m.__msgtype__))
            writer.write(ci, ns, ts.serialize_cdr(imu, imu.__msgtype__))
            n += 1
    print(f"wrote {out} ({n} samples per topic)")


if __name__ == "__main__":
    main(*sys.argv[1:])
