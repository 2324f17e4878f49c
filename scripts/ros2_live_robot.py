#!/usr/bin/env python3
"""A stand-in ROS 2 robot on rmw_zenoh, written independently of evermap (Python, no ROS install).

It replays a ROS 2 recording live over zenoh under the key expressions rmw_zenoh uses, and listens to what
evermap's agent sends back (the map on /map, the pose, map -> odom on /tf), decoding it with `rosbags`.
Everything about the wire format is computed here from its own sources, not from evermap's code:

- key expression: `<domain>/<topic without leading '/'>/<pkg>::msg::dds_::<Type>_/<RIHS01 hash>`, the hash
  from rosbags' `Typestore.hash_rihs01` (REP 2011) over the Jazzy message definitions;
- payload: each recorded message deserialized and serialized again as CDR by rosbags;
- attachment (rmw_zenoh's, zenoh-ext serialization): int64 sequence number, int64 source timestamp (ns),
  then the 16-byte publisher GID as a byte sequence (varint length 16, the bytes).

Messages are sent in the recording's order, paced at `--speed` times real time from their log times.
At the end the script waits for the agent's final map (`--linger-s` at most), asks for the latest map with a
zenoh query (what a subscriber that joins late does), and writes a JSON summary (`--summary FILE`).

    python scripts/ros2_live_robot.py --bag ../shared/datasets/rosbag2-derived/mit-csail \
        --connect tcp/127.0.0.1:7447 --speed 5 --summary out/robot.json
"""

import argparse
import hashlib
import json
import os
import struct
import sys
import threading
import time
from pathlib import Path

import zenoh
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

READ_TYPES = {
    "sensor_msgs/msg/LaserScan",
    "nav_msgs/msg/Odometry",
    "tf2_msgs/msg/TFMessage",
    "sensor_msgs/msg/Imu",
}


def dds_name(ros_type):
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def key_for(domain, topic, ros_type, typestore):
    return f"{domain}/{topic.lstrip('/')}/{dds_name(ros_type)}/{typestore.hash_rihs01(ros_type)}"


def attachment(sequence, gid):
    return struct.pack("<qq", sequence, time.time_ns()) + bytes([len(gid)]) + gid


def decode_attachment(raw):
    if raw is None or len(raw) != 33 or raw[16] != 16:
        return None
    sequence, stamp = struct.unpack("<qq", raw[:16])
    return {"sequence": sequence, "source_timestamp_ns": stamp, "gid": raw[17:].hex()}


def stamp_s(header):
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bag", required=True, help="rosbag2 folder (or .mcap / .db3)")
    parser.add_argument("--connect", action="append", default=[], help="zenoh endpoint")
    parser.add_argument("--listen", action="append", default=[], help="zenoh endpoint")
    parser.add_argument("--domain-id", type=int, default=0)
    parser.add_argument("--speed", type=float, default=1.0, help="multiple of real time")
    parser.add_argument("--start-s", type=float, default=0.0, help="skip this much of the recording")
    parser.add_argument("--duration-s", type=float, default=None, help="replay only this much")
    parser.add_argument("--wait-s", type=float, default=10.0,
                        help="longest wait for a subscriber of every topic before the first message")
    parser.add_argument("--linger-s", type=float, default=30.0, help="longest wait for the final map")
    parser.add_argument("--quiet-s", type=float, default=4.0,
                        help="the final map is the last one after this long without a new one")
    parser.add_argument("--map-topic", default="/map")
    parser.add_argument("--pose-topic", default="/evermap/pose")
    parser.add_argument("--summary", help="write the JSON summary here (default: stdout)")
    args = parser.parse_args()

    typestore = get_typestore(Stores.ROS2_JAZZY)
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("peer"))
    config.insert_json5("connect/endpoints", json.dumps(args.connect))
    config.insert_json5("listen/endpoints", json.dumps(args.listen))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    session = zenoh.open(config)

    lock = threading.Lock()
    back = {"maps": [], "poses": 0, "last_pose": None, "map_odom": 0, "last_map_odom": None,
            "bad": [], "map_attachments": 0, "last_map_at": None, "last_map_digest": None,
            "map_publications": 0}

    map_type, pose_type, tf_type = ("nav_msgs/msg/OccupancyGrid",
                                    "geometry_msgs/msg/PoseWithCovarianceStamped",
                                    "tf2_msgs/msg/TFMessage")
    map_key = key_for(args.domain_id, args.map_topic, map_type, typestore)
    pose_key = key_for(args.domain_id, args.pose_topic, pose_type, typestore)
    tf_key = key_for(args.domain_id, "/tf", tf_type, typestore)

    def summarize_map(msg):
        data = msg.data
        return {
            "stamp_s": stamp_s(msg.header), "frame_id": msg.header.frame_id,
            "resolution": float(msg.info.resolution), "width": int(msg.info.width),
            "height": int(msg.info.height),
            "origin": [float(msg.info.origin.position.x), float(msg.info.origin.position.y)],
            "cells": int(len(data)), "unknown": int((data == -1).sum()),
            "free": int(((data >= 0) & (data <= 19)).sum()), "occupied": int((data >= 65).sum()),
        }

    def on_map(sample):
        payload = sample.payload.to_bytes()
        digest = hashlib.sha256(payload).hexdigest()
        with lock:
            back["map_publications"] += 1
            if digest == back["last_map_digest"]:
                return  # the same map published again (for late joiners): not a new version
            back["last_map_digest"] = digest
        try:
            msg = typestore.deserialize_cdr(payload, map_type)
            info = summarize_map(msg)
        except Exception as e:  # a message that does not decode is what the test looks for
            with lock:
                back["bad"].append(f"map: {e}")
            return
        with lock:
            back["maps"].append(info)
            back["last_map_at"] = time.monotonic()
            if decode_attachment(sample.attachment.to_bytes() if sample.attachment else None):
                back["map_attachments"] += 1

    def on_pose(sample):
        try:
            msg = typestore.deserialize_cdr(sample.payload.to_bytes(), pose_type)
        except Exception as e:
            with lock:
                back["bad"].append(f"pose: {e}")
            return
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        with lock:
            back["poses"] += 1
            back["last_pose"] = {"stamp_s": stamp_s(msg.header), "frame_id": msg.header.frame_id,
                                 "x": p.x, "y": p.y, "qz": q.z, "qw": q.w,
                                 "cov_xx": float(msg.pose.covariance[0])}

    def on_tf(sample):
        try:
            msg = typestore.deserialize_cdr(sample.payload.to_bytes(), tf_type)
        except Exception as e:
            with lock:
                back["bad"].append(f"tf: {e}")
            return
        for t in msg.transforms:
            if t.header.frame_id == "map" and t.child_frame_id == "odom":
                tr = t.transform.translation
                with lock:
                    back["map_odom"] += 1
                    back["last_map_odom"] = {"stamp_s": stamp_s(t.header), "x": tr.x, "y": tr.y}

    subscribers = [session.declare_subscriber(map_key, on_map),
                   session.declare_subscriber(pose_key, on_pose),
                   session.declare_subscriber(tf_key, on_tf)]

    publishers, sequences = {}, {}
    sent, first_log, started = {}, None, None
    with AnyReader([Path(args.bag)]) as reader:
        connections = [c for c in reader.connections if c.msgtype in READ_TYPES]
        for i, c in enumerate(connections):
            if c.topic not in publishers:
                key = key_for(args.domain_id, c.topic, c.msgtype, typestore)
                publishers[c.topic] = (session.declare_publisher(key), os.urandom(12) + struct.pack("<I", i))
                sequences[c.topic] = 0
        # Start once every topic has a subscriber (zenoh does not keep what nobody listens to), or after
        # --wait-s at most.
        deadline = time.monotonic() + args.wait_s
        while time.monotonic() < deadline and not all(
                p.matching_status.matching for p, _ in publishers.values()):
            time.sleep(0.05)
        time.sleep(0.2)
        t0 = reader.start_time + int(args.start_s * 1e9)
        t1 = None if args.duration_s is None else t0 + int(args.duration_s * 1e9)
        for connection, log_time, raw in reader.messages(connections=connections):
            if log_time < t0 and connection.topic != "/tf_static":
                continue
            if t1 is not None and log_time > t1:
                break
            if first_log is None:
                first_log, started = max(log_time, t0), time.monotonic()
            due = (max(log_time, t0) - first_log) * 1e-9 / args.speed
            wait = due - (time.monotonic() - started)
            if wait > 0:
                time.sleep(wait)
            message = typestore.deserialize_cdr(raw, connection.msgtype)
            payload = typestore.serialize_cdr(message, connection.msgtype)
            publisher, gid = publishers[connection.topic]
            sequences[connection.topic] += 1
            publisher.put(bytes(payload), attachment=attachment(sequences[connection.topic], gid))
            sent[connection.topic] = sent.get(connection.topic, 0) + 1
    replay_s = time.monotonic() - started if started else 0.0

    # The agent publishes its final map once it has been idle; wait until no new map (re-publications of
    # the same one do not count) has come for --quiet-s, and --quiet-s after the replay at least.
    replay_end = time.monotonic()
    deadline = replay_end + args.linger_s
    while time.monotonic() < deadline:
        with lock:
            last = back["last_map_at"]
        if last is not None and time.monotonic() - max(last, replay_end) > args.quiet_s:
            break
        time.sleep(0.1)

    # A late joiner's query for the latest map.
    queried = None
    for reply in session.get(map_key, timeout=5.0):
        if reply.ok is not None:
            try:
                queried = summarize_map(typestore.deserialize_cdr(reply.ok.payload.to_bytes(), map_type))
            except Exception as e:
                back["bad"].append(f"queried map: {e}")

    with lock:
        summary = {
            "sent": sent, "replay_s": replay_s, "speed": args.speed,
            "keys": {"map": map_key, "pose": pose_key, "tf": tf_key},
            "maps_received": len(back["maps"]), "map_publications": back["map_publications"],
            "last_map": back["maps"][-1] if back["maps"] else None,
            "map_attachments_valid": back["map_attachments"], "queried_map": queried,
            "poses_received": back["poses"], "last_pose": back["last_pose"],
            "map_odom_received": back["map_odom"], "last_map_odom": back["last_map_odom"],
            "undecodable": back["bad"][:10],
        }
    for s in subscribers:
        s.undeclare()
    session.close()
    text = json.dumps(summary, indent=1)
    if args.summary:
        Path(args.summary).write_text(text + "\n")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
