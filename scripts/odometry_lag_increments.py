#!/usr/bin/env python3
"""How much the robustness suite's `lag` variant changes the odometry a recording's scans see.

For every pair of consecutive scans, the odometry's heading change between their stamps (odometry headings
interpolated at the stamps), with the odometry as recorded and with every reading stamped LAG seconds late
(the `lag` variant). Also counts the scan intervals under a fifth of the median: stamps in bursts.

    bash scripts/ros2_venv.sh
    target/ros2-venv/bin/python scripts/odometry_lag_increments.py ../shared/datasets/rosbag1/intel.orig.bag
"""

import argparse
import sys

import numpy as np
from rosbags.rosbag1 import Reader
from rosbags.typesys import Stores, get_typestore


def stamps_and_headings(path, scan_topic, odom_topic):
    typestore = get_typestore(Stores.ROS1_NOETIC)
    scans, odom_t, odom_heading = [], [], []
    with Reader(path) as reader:
        for connection, _, raw in reader.messages():
            if connection.topic not in (scan_topic, odom_topic):
                continue
            message = typestore.deserialize_ros1(raw, connection.msgtype)
            stamp = message.header.stamp.sec + message.header.stamp.nanosec * 1e-9
            if connection.topic == scan_topic:
                scans.append(stamp)
            else:
                q = message.pose.pose.orientation
                odom_t.append(stamp)
                odom_heading.append(2.0 * np.arctan2(q.z, q.w))
    if len(scans) < 2 or len(odom_t) < 2:
        sys.exit(f"{path}: needs at least two messages on {scan_topic} and on {odom_topic}")
    return np.array(scans), np.array(odom_t), np.unwrap(np.array(odom_heading))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", help="a ROS 1 bag with LaserScan and Odometry")
    parser.add_argument("--lag-s", type=float, default=0.1, help="the odometry's delay (s), as `lag`")
    parser.add_argument("--scan-topic", default="/scan")
    parser.add_argument("--odom-topic", default="/odom")
    args = parser.parse_args()

    scans, odom_t, heading = stamps_and_headings(args.bag, args.scan_topic, args.odom_topic)
    intervals = np.diff(scans)
    median = np.median(intervals)
    print(
        f"scans {len(scans)}, median interval {median:.4f} s, "
        f"intervals under a fifth of it {int(np.sum(intervals < 0.2 * median))}; "
        f"odometry {len(odom_t)}, median interval {np.median(np.diff(odom_t)):.4f} s"
    )
    as_recorded = np.degrees(np.diff(np.interp(scans, odom_t, heading)))
    lagged = np.degrees(np.diff(np.interp(scans, odom_t + args.lag_s, heading)))
    change = np.abs(lagged - as_recorded)
    counts = " / ".join(str(int(np.sum(change > limit))) for limit in (2, 5, 10))
    print(f"scan increments changed by more than 2 / 5 / 10 deg: {counts} of {len(change)}")
    worst = int(np.argmax(change))
    print(
        f"largest change {change[worst]:.1f} deg at {scans[worst + 1] - scans[0]:.3f} s "
        f"({intervals[worst]:.3f} s after the scan before): "
        f"{as_recorded[worst]:.1f} -> {lagged[worst]:.1f} deg"
    )


if __name__ == "__main__":
    main()
