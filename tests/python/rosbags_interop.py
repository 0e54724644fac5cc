#!/usr/bin/env python3
"""rosbag2 bags written and read by Python `rosbags` (PyPI; not ours), for the pipeline's ROS 2
tests (tests/tests/ros2_bags.rs).

  carmen LOG BAG [--max-scans N] [--range-max M]
      A CARMEN log's FLASER lines as a rosbag2 MCAP bag: /scan (sensor_msgs/LaserScan: 180°, first
      beam at -90°, as the log states) and /odom (nav_msgs/Odometry: the line's odometry pose), both
      stamped with the line's ipc_timestamp.
  samples BAG
      One bag with a message of each type the pipeline reads (values in the printed JSON) and bad
      ones: a topic whose messages are of another type than the route says, a LaserScan cut short,
      one with a NaN angle_increment, a PointCloud2 without z.
  read BAG
      Reads every message of a bag with rosbags' AnyReader and deserializes it; prints JSON: per
      topic the type, the count and the first and last message's main fields.
"""
import gzip
import json
import math
import sys
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)
M = TS.types


def stamp(t):
    sec = int(math.floor(t))
    return M["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)


def header(t, frame):
    return M["std_msgs/msg/Header"](stamp=stamp(t), frame_id=frame)


def quat_yaw(yaw):
    return M["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def odometry(t, x, y, yaw, frame="odom"):
    g = M
    pose = g["geometry_msgs/msg/Pose"](position=g["geometry_msgs/msg/Point"](x=x, y=y, z=0.0), orientation=quat_yaw(yaw))
    twist = g["geometry_msgs/msg/Twist"](
        linear=g["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular=g["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    return g["nav_msgs/msg/Odometry"](
        header=header(t, frame),
        child_frame_id="base_link",
        pose=g["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=g["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )


def laser_scan(t, ranges, range_max, angle_min=-math.pi / 2, angle_increment=None):
    n = len(ranges)
    # FLASER beams span 180° from -90° (as the pipeline's CARMEN reader takes them).
    inc = (math.pi / (n - 1) if n % 2 == 1 else math.pi / n) if angle_increment is None else angle_increment
    return M["sensor_msgs/msg/LaserScan"](
        header=header(t, "laser"),
        angle_min=angle_min,
        angle_max=angle_min + inc * (n - 1),
        angle_increment=inc,
        time_increment=0.0,
        scan_time=0.0,
        range_min=0.01,
        range_max=range_max,
        ranges=np.array(ranges, dtype=np.float32),
        intensities=np.array([], dtype=np.float32),
    )


def open_writer(path):
    w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    w.open()
    return w


def carmen(log, bag, max_scans, range_max):
    opener = gzip.open if log.endswith(".gz") else open
    w = open_writer(bag)
    scan_c = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
    odom_c = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=TS)
    n = 0
    with opener(log, "rt") as f:
        for line in f:
            p = line.split()
            if not p or p[0] != "FLASER":
                continue
            k = int(p[1])
            ranges = [float(r) for r in p[2 : 2 + k]]
            ox, oy, oth = (float(v) for v in p[5 + k : 8 + k])
            t = float(p[8 + k])
            ns = int(round(t * 1e9))
            w.write(odom_c, ns, TS.serialize_cdr(odometry(t, ox, oy, oth), "nav_msgs/msg/Odometry"))
            w.write(scan_c, ns, TS.serialize_cdr(laser_scan(t, ranges, range_max), "sensor_msgs/msg/LaserScan"))
            n += 1
            if max_scans and n >= max_scans:
                break
    w.close()
    print(json.dumps({"scans": n}))


def samples(bag):
    g = M
    w = open_writer(bag)
    out = {}

    def put(topic, typ, msg, t_ns, raw=None):
        c = conns.get(topic)
        if c is None:
            c = conns[topic] = w.add_connection(topic, typ, typestore=TS)
        data = raw if raw is not None else TS.serialize_cdr(msg, typ)
        w.write(c, t_ns, data)

    conns = {}
    t = 100.0
    put("/scan", "sensor_msgs/msg/LaserScan", laser_scan(t, [1.0, 2.0, float("inf"), float("nan")], 30.0), int(t * 1e9))
    out["scan"] = {"stamp_ns": int(t * 1e9), "beams": 4}
    put("/odom", "nav_msgs/msg/Odometry", odometry(t, 1.5, -2.0, 0.5), int(t * 1e9))
    out["odom"] = {"x": 1.5, "y": -2.0, "yaw": 0.5}
    # A cloud with x, y, z, intensity (FLOAT32) and a padded 20-byte point; the third point NaN.
    pts = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("pad", "<f4")])
    pts["x"] = [1, 2, np.nan]
    pts["y"] = [3, 4, 5]
    pts["z"] = [5, 6, 7]
    fields = [
        g["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=7, count=1)
        for n, o in (("x", 0), ("y", 4), ("z", 8), ("intensity", 12))
    ]
    cloud = g["sensor_msgs/msg/PointCloud2"](
        header=header(t, "sonar"), height=1, width=3, fields=fields, is_bigendian=False, point_step=20,
        row_step=60, data=np.frombuffer(pts.tobytes(), dtype=np.uint8), is_dense=False,
    )
    put("/cloud", "sensor_msgs/msg/PointCloud2", cloud, int(t * 1e9))
    out["cloud"] = {"finite_points": [[1, 3, 5], [2, 4, 6]]}
    imu = g["sensor_msgs/msg/Imu"](
        header=header(t, "imu"), orientation=quat_yaw(-0.25), orientation_covariance=np.array([0.0] * 8 + [0.0004]),
        angular_velocity=g["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0), angular_velocity_covariance=np.zeros(9),
        linear_acceleration=g["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.8), linear_acceleration_covariance=np.zeros(9),
    )
    put("/imu", "sensor_msgs/msg/Imu", imu, int(t * 1e9))
    out["imu"] = {"yaw": -0.25, "sigma": 0.02}
    put("/pressure", "sensor_msgs/msg/FluidPressure",
        g["sensor_msgs/msg/FluidPressure"](header=header(t, "p"), fluid_pressure=101325.0 + 1025.0 * 9.80665 * 12.0, variance=0.0),
        int(t * 1e9))
    out["pressure"] = {"depth_m": 12.0}
    rng = g["sensor_msgs/msg/Range"](header=header(t, "buoy_2"), radiation_type=0, field_of_view=0.1, min_range=0.5,
                                     max_range=500.0, range=42.5, variance=0.09)
    put("/ranges", "sensor_msgs/msg/Range", rng, int(t * 1e9))
    out["range"] = {"buoy_id": 2, "range_m": 42.5, "sigma_m": 0.3}
    # A 4×2 depth image (16UC1, mm) and its camera info: fx = fy = 100, cx = 2, cy = 1.
    info = g["sensor_msgs/msg/CameraInfo"](
        header=header(t, "depth_optical"), height=2, width=4, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([100.0, 0, 2.0, 0, 100.0, 1.0, 0, 0, 1.0]), r=np.eye(3).flatten(),
        p=np.array([100.0, 0, 2.0, 0, 0, 100.0, 1.0, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0,
        roi=g["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )
    put("/camera_info", "sensor_msgs/msg/CameraInfo", info, int(t * 1e9))
    depth = np.zeros(8, dtype="<u2")
    depth[0], depth[7] = 2000, 1000
    # Half a second after the cloud: both feed pipeline/sensors/cloud, whose stamps must increase.
    img = g["sensor_msgs/msg/Image"](header=header(t + 0.5, "depth_optical"), height=2, width=4, encoding="16UC1",
                                     is_bigendian=0, step=8, data=np.frombuffer(depth.tobytes(), dtype=np.uint8))
    put("/depth", "sensor_msgs/msg/Image", img, int((t + 0.5) * 1e9))
    out["depth"] = {"points": [[-0.04, -0.02, 2.0], [0.01, 0.0, 1.0]]}
    # Bad ones.
    put("/scan", "sensor_msgs/msg/LaserScan", laser_scan(t + 1, [1.0, 2.0], 30.0, angle_increment=float("nan")), int((t + 1) * 1e9))
    good = TS.serialize_cdr(laser_scan(t + 2, [1.0] * 50, 30.0), "sensor_msgs/msg/LaserScan")
    put("/scan", "sensor_msgs/msg/LaserScan", None, int((t + 2) * 1e9), raw=bytes(good[: len(good) // 2]))
    put("/odom_wrong", "sensor_msgs/msg/FluidPressure",
        g["sensor_msgs/msg/FluidPressure"](header=header(t, "p"), fluid_pressure=1.0, variance=0.0), int(t * 1e9))
    cloud_noz = g["sensor_msgs/msg/PointCloud2"](
        header=header(t, "sonar"), height=1, width=3, fields=fields[:2], is_bigendian=False, point_step=20,
        row_step=60, data=np.frombuffer(pts.tobytes(), dtype=np.uint8), is_dense=False,
    )
    put("/cloud", "sensor_msgs/msg/PointCloud2", cloud_noz, int((t + 1) * 1e9))
    out["bad"] = {"scan_nan_increment": 1, "scan_truncated": 1, "wrong_type_topic": "/odom_wrong", "cloud_without_z": 1}
    w.close()
    print(json.dumps(out))


def brief(msg):
    d = {}
    h = getattr(msg, "header", None)
    if h is not None:
        d["stamp_ns"] = h.stamp.sec * 1_000_000_000 + h.stamp.nanosec
        d["frame_id"] = h.frame_id
    for k in ("child_frame_id", "width", "height", "point_step"):
        if hasattr(msg, k):
            d[k] = getattr(msg, k)
    if hasattr(msg, "pose") and hasattr(msg.pose, "pose"):
        p = msg.pose.pose.position
        d["position"] = [p.x, p.y, p.z]
    if hasattr(msg, "info"):
        d["resolution"] = float(msg.info.resolution)
        d["width"], d["height"] = msg.info.width, msg.info.height
        d["cells"] = len(msg.data)
    if hasattr(msg, "fields"):
        d["fields"] = [(f.name, f.datatype) for f in msg.fields]
    if hasattr(msg, "poses"):
        d["poses"] = len(msg.poses)
    if hasattr(msg, "transforms"):
        d["transforms"] = [(t.header.frame_id, t.child_frame_id) for t in msg.transforms]
    if hasattr(msg, "markers"):
        d["markers"] = len(msg.markers)
    return d


def read(bag):
    topics = {}
    with AnyReader([Path(bag)]) as r:
        for conn, ts, raw in r.messages():
            msg = r.deserialize(raw, conn.msgtype)
            t = topics.setdefault(conn.topic, {"type": conn.msgtype, "count": 0})
            t["count"] += 1
            b = brief(msg)
            t.setdefault("first", b)
            t["last"] = b
            t["last_log_time_ns"] = ts
    print(json.dumps(topics, default=float))


def main(argv):
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    cmd = argv[1]
    if cmd == "carmen":
        args = argv[2:]
        max_scans = 0
        range_max = 80.0
        if "--max-scans" in args:
            i = args.index("--max-scans")
            max_scans = int(args[i + 1])
            del args[i : i + 2]
        if "--range-max" in args:
            i = args.index("--range-max")
            range_max = float(args[i + 1])
            del args[i : i + 2]
        carmen(args[0], args[1], max_scans, range_max)
    elif cmd == "samples":
        samples(argv[2])
    elif cmd == "read":
        read(argv[2])
    else:
        print(__doc__, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
