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

from make_ros2_bag import messages

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT = ROOT / "tests/data/rosbag-ck-explorer-ros1/ck_explorer.bag"


def main(out=OUT):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    out = pathlib.Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.unlink(missing_ok=True)
    writer = Writer(out)
    writer.set_compression(Writer.CompressionFormat.BZ2)
    writer.chunk_threshold = 64 * 1024                 # several chunks, so a cut loses one, not all
    n = 0
    with writer:
        cm = writer.add_connection("/imu/mag", "sensor_msgs/msg/MagneticField", typestore=ts)
        ci = writer.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=ts)
        for ns, m, imu in messages(ts, ros1=True):
            writer.write(cm, ns, ts.serialize_ros1(m, m.__msgtype__))
            writer.write(ci, ns, ts.serialize_ros1(imu, imu.__msgtype__))
            n += 1
    print(f"wrote {out} ({n} samples per topic)")


if __name__ == "__main__":
    main(*sys.argv[1:])
