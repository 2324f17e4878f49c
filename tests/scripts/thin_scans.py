"""Writes a copy of a ROS1 bag keeping /scan messages at least PERIOD s apart (header stamp), all else
unchanged: a recording at 1-2 scans per second made from a shared one (docs/BENCHMARK-HISTORY.md,
"low scan rate").

    pip install rosbags
    python3 tests/scripts/thin_scans.py IN.bag OUT.bag 0.7
"""
import sys
from rosbags.rosbag1 import Reader, Writer
from rosbags.typesys import Stores, get_typestore
src, dst, period = sys.argv[1], sys.argv[2], float(sys.argv[3])
ts = get_typestore(Stores.ROS1_NOETIC)
kept = total = 0
last = None
with Reader(src) as r, Writer(dst) as w:
    conns = {}
    for c in r.connections:
        conns[c.id] = w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest, callerid=c.ext.callerid, latching=c.ext.latching)
    for c, t, raw in r.messages():
        if c.topic == '/scan':
            total += 1
            msg = ts.deserialize_ros1(raw, c.msgtype)
            stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            if last is not None and stamp - last < period:
                continue
            last = stamp
            kept += 1
        w.write(conns[c.id], t, raw)
print(f"{dst}: kept {kept} of {total} scans")
