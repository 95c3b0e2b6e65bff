"""Write the small ROS 1 bag of tests/data/rosbag-ck-explorer-ros1/ from a real recording.

The real ROS 1 bags found with a magnetometer are GPL or too large for the tests, so this one is
made with rosbags' own ROS 1 writer, bz2-compressed chunks, from the same rows and messages as the
ROS 2 bag of tools/make_ros2_bag.py (every 15th row of the Apache-2.0 CK-Explorer log, /imu/mag as
sensor_msgs/MagneticField in tesla, /imu/data as sensor_msgs/Imu). Run once:

    python tools/make_ros1_bag.py [OUT_FILE]
"""
from __future__ import annotations

import pathlib
import sys

import numpy as np

from make_ros2_bag import GAUSS_TO_TESLA, G, RATE_HZ, SOURCE, STEP

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT = ROOT / "tests/data/rosbag-ck-explorer-ros1/ck_explorer.bag"


def main(out=OUT):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    data = np.loadtxt(SOURCE, delimiter=",", skiprows=1)[::STEP]
    acc, mag = data[:, 0:3], data[:, 3:6]
    ts = get_typestore(Stores.ROS1_NOETIC)
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    Vector3, Quaternion = ts.types["geometry_msgs/msg/Vector3"], ts.types["geometry_msgs/msg/Quaternion"]
    MagneticField, Imu = ts.types["sensor_msgs/msg/MagneticField"], ts.types["sensor_msgs/msg/Imu"]
    out = pathlib.Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.unlink(missing_ok=True)
    zeros9 = np.zeros(9)
    no_orientation = np.r_[-1.0, np.zeros(8)]          # REP 145: orientation unknown
    writer = Writer(out)
    writer.set_compression(Writer.CompressionFormat.BZ2)
    writer.chunk_threshold = 64 * 1024                 # several chunks, so a cut loses one, not all
    with writer:
        cm = writer.add_connection("/imu/mag", MagneticField.__msgtype__, typestore=ts)
        ci = writer.add_connection("/imu/data", Imu.__msgtype__, typestore=ts)
        for i in range(len(data)):
            ns = 1_000_000_000 + int(round(i * 1e9 / RATE_HZ))
            header = Header(seq=i, stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id="imu")
            m = MagneticField(header=header, magnetic_field=Vector3(*(mag[i] * GAUSS_TO_TESLA)),
                              magnetic_field_covariance=zeros9)
            writer.write(cm, ns, ts.serialize_ros1(m, MagneticField.__msgtype__))
            imu = Imu(header=header, orientation=Quaternion(0.0, 0.0, 0.0, 0.0), orientation_covariance=no_orientation,
                      angular_velocity=Vector3(0.0, 0.0, 0.0), angular_velocity_covariance=zeros9,
                      linear_acceleration=Vector3(*(acc[i] * G)), linear_acceleration_covariance=zeros9)
            writer.write(ci, ns, ts.serialize_ros1(imu, Imu.__msgtype__))
    print(f"wrote {out} ({len(data)} samples per topic)")


if __name__ == "__main__":
    main(*sys.argv[1:])
