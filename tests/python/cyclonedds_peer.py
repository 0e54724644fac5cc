#!/usr/bin/env python3
"""A ROS 2 peer from another DDS vendor for the pipeline's `ros2` gateway tests: Eclipse Cyclone
DDS (Python `cyclonedds`, PyPI), declaring the ROS 2 types with their DDS names
(`nav_msgs::msg::dds_::Odometry_`, topics `rt/<name>`) and plain CDR (XCDR1), as rmw_cyclonedds
does. Run it inside the test's network namespace (CYCLONEDDS_URI confines it to `lo`).

  listen SECONDS TOPIC:KIND [TOPIC:KIND ...] [--until TOPIC=N ...]
      Subscribes (reliable; transient local for /map, /tf_static and the marker and voxel topics)
      and prints, as JSON, per topic the count and the main fields of the first and last messages.
      KIND: odometry, pose, path, tf, map, cloud, markers, nodes (the DDS topic ros_discovery_info,
      what `ros2 node list` reads: every ROS node seen, with its readers and writers). Ends after SECONDS, once every
      --until topic has N messages, or on SIGINT / SIGTERM.
  carmen LOG [--max-scans N] [--rate-x K]
      Publishes a CARMEN log's FLASER lines as /scan (sensor_msgs/LaserScan) and /odom
      (nav_msgs/Odometry), reliable, waiting for a subscriber first; K times the log's own rate
      (0: as fast as the link takes them). Prints {"scans": N}.
  bad SECONDS
      Publishes what the gateway must refuse: a LaserScan with a NaN angle_increment, an
      Odometry whose quaternion is zero, a PointCloud2 without z; a best-effort writer on
      /scan_be and an Odometry writer on /scan_typed.
"""
import gzip
import json
import math
import os
import signal
import sys
import time
from dataclasses import dataclass, field

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float32, float64, int8, int32, sequence, uint8, uint32
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


def T(name):
    pkg, _, ty = name.partition("/msg/")
    return f"{pkg}::msg::dds_::{ty}_"


@dataclass
class Time(IdlStruct, typename=T("builtin_interfaces/msg/Time")):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Duration(IdlStruct, typename=T("builtin_interfaces/msg/Duration")):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename=T("std_msgs/msg/Header")):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class ColorRGBA(IdlStruct, typename=T("std_msgs/msg/ColorRGBA")):
    r: float32 = 0.0
    g: float32 = 0.0
    b: float32 = 0.0
    a: float32 = 0.0


@dataclass
class Vector3(IdlStruct, typename=T("geometry_msgs/msg/Vector3")):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Point(IdlStruct, typename=T("geometry_msgs/msg/Point")):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename=T("geometry_msgs/msg/Quaternion")):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose(IdlStruct, typename=T("geometry_msgs/msg/Pose")):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseWithCovariance(IdlStruct, typename=T("geometry_msgs/msg/PoseWithCovariance")):
    pose: Pose = field(default_factory=Pose)
    covariance: array[float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class Twist(IdlStruct, typename=T("geometry_msgs/msg/Twist")):
    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class TwistWithCovariance(IdlStruct, typename=T("geometry_msgs/msg/TwistWithCovariance")):
    twist: Twist = field(default_factory=Twist)
    covariance: array[float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class Odometry(IdlStruct, typename=T("nav_msgs/msg/Odometry")):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)
    twist: TwistWithCovariance = field(default_factory=TwistWithCovariance)


@dataclass
class PoseWithCovarianceStamped(IdlStruct, typename=T("geometry_msgs/msg/PoseWithCovarianceStamped")):
    header: Header = field(default_factory=Header)
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)


@dataclass
class PoseStamped(IdlStruct, typename=T("geometry_msgs/msg/PoseStamped")):
    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@dataclass
class Path(IdlStruct, typename=T("nav_msgs/msg/Path")):
    header: Header = field(default_factory=Header)
    poses: sequence[PoseStamped] = field(default_factory=list)


@dataclass
class Transform(IdlStruct, typename=T("geometry_msgs/msg/Transform")):
    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename=T("geometry_msgs/msg/TransformStamped")):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
class TFMessage(IdlStruct, typename=T("tf2_msgs/msg/TFMessage")):
    transforms: sequence[TransformStamped] = field(default_factory=list)


@dataclass
class MapMetaData(IdlStruct, typename=T("nav_msgs/msg/MapMetaData")):
    map_load_time: Time = field(default_factory=Time)
    resolution: float32 = 0.0
    width: uint32 = 0
    height: uint32 = 0
    origin: Pose = field(default_factory=Pose)


@dataclass
class OccupancyGrid(IdlStruct, typename=T("nav_msgs/msg/OccupancyGrid")):
    header: Header = field(default_factory=Header)
    info: MapMetaData = field(default_factory=MapMetaData)
    data: sequence[int8] = field(default_factory=list)


@dataclass
class LaserScan(IdlStruct, typename=T("sensor_msgs/msg/LaserScan")):
    header: Header = field(default_factory=Header)
    angle_min: float32 = 0.0
    angle_max: float32 = 0.0
    angle_increment: float32 = 0.0
    time_increment: float32 = 0.0
    scan_time: float32 = 0.0
    range_min: float32 = 0.0
    range_max: float32 = 0.0
    ranges: sequence[float32] = field(default_factory=list)
    intensities: sequence[float32] = field(default_factory=list)


@dataclass
class PointField(IdlStruct, typename=T("sensor_msgs/msg/PointField")):
    name: str = ""
    offset: uint32 = 0
    datatype: uint8 = 0
    count: uint32 = 0


@dataclass
class PointCloud2(IdlStruct, typename=T("sensor_msgs/msg/PointCloud2")):
    header: Header = field(default_factory=Header)
    height: uint32 = 0
    width: uint32 = 0
    fields: sequence[PointField] = field(default_factory=list)
    is_bigendian: bool = False
    point_step: uint32 = 0
    row_step: uint32 = 0
    data: sequence[uint8] = field(default_factory=list)
    is_dense: bool = False


@dataclass
class Image(IdlStruct, typename=T("sensor_msgs/msg/Image")):
    header: Header = field(default_factory=Header)
    height: uint32 = 0
    width: uint32 = 0
    encoding: str = ""
    is_bigendian: uint8 = 0
    step: uint32 = 0
    data: sequence[uint8] = field(default_factory=list)


@dataclass
class RegionOfInterest(IdlStruct, typename=T("sensor_msgs/msg/RegionOfInterest")):
    x_offset: uint32 = 0
    y_offset: uint32 = 0
    height: uint32 = 0
    width: uint32 = 0
    do_rectify: bool = False


@dataclass
class CameraInfo(IdlStruct, typename=T("sensor_msgs/msg/CameraInfo")):
    header: Header = field(default_factory=Header)
    height: uint32 = 0
    width: uint32 = 0
    distortion_model: str = ""
    d: sequence[float64] = field(default_factory=list)
    k: array[float64, 9] = field(default_factory=lambda: [0.0] * 9)
    r: array[float64, 9] = field(default_factory=lambda: [0.0] * 9)
    p: array[float64, 12] = field(default_factory=lambda: [0.0] * 12)
    binning_x: uint32 = 0
    binning_y: uint32 = 0
    roi: RegionOfInterest = field(default_factory=RegionOfInterest)


@dataclass
class CompressedImage(IdlStruct, typename=T("sensor_msgs/msg/CompressedImage")):
    header: Header = field(default_factory=Header)
    format: str = ""
    data: sequence[uint8] = field(default_factory=list)


@dataclass
class UVCoordinate(IdlStruct, typename=T("visualization_msgs/msg/UVCoordinate")):
    u: float32 = 0.0
    v: float32 = 0.0


@dataclass
class MeshFile(IdlStruct, typename=T("visualization_msgs/msg/MeshFile")):
    filename: str = ""
    data: sequence[uint8] = field(default_factory=list)


@dataclass
class Marker(IdlStruct, typename=T("visualization_msgs/msg/Marker")):
    header: Header = field(default_factory=Header)
    ns: str = ""
    id: int32 = 0
    type: int32 = 0
    action: int32 = 0
    pose: Pose = field(default_factory=Pose)
    scale: Vector3 = field(default_factory=Vector3)
    color: ColorRGBA = field(default_factory=ColorRGBA)
    lifetime: Duration = field(default_factory=Duration)
    frame_locked: bool = False
    points: sequence[Point] = field(default_factory=list)
    colors: sequence[ColorRGBA] = field(default_factory=list)
    texture_resource: str = ""
    texture: CompressedImage = field(default_factory=CompressedImage)
    uv_coordinates: sequence[UVCoordinate] = field(default_factory=list)
    text: str = ""
    mesh_resource: str = ""
    mesh_file: MeshFile = field(default_factory=MeshFile)
    mesh_use_embedded_materials: bool = False


@dataclass
class MarkerArray(IdlStruct, typename=T("visualization_msgs/msg/MarkerArray")):
    markers: sequence[Marker] = field(default_factory=list)


@dataclass
class Gid(IdlStruct, typename=T("rmw_dds_common/msg/Gid")):
    data: array[uint8, 16] = field(default_factory=lambda: [0] * 16)


@dataclass
class NodeEntitiesInfo(IdlStruct, typename=T("rmw_dds_common/msg/NodeEntitiesInfo")):
    node_namespace: str = ""
    node_name: str = ""
    reader_gid_seq: sequence[Gid] = field(default_factory=list)
    writer_gid_seq: sequence[Gid] = field(default_factory=list)


@dataclass
class ParticipantEntitiesInfo(IdlStruct, typename=T("rmw_dds_common/msg/ParticipantEntitiesInfo")):
    """What `ros2 node list` reads: each participant's ROS nodes (DDS topic `ros_discovery_info`)."""
    gid: Gid = field(default_factory=Gid)
    node_entities_info_seq: sequence[NodeEntitiesInfo] = field(default_factory=list)


KINDS = {
    "nodes": ParticipantEntitiesInfo,
    "odometry": Odometry,
    "pose": PoseWithCovarianceStamped,
    "path": Path,
    "tf": TFMessage,
    "map": OccupancyGrid,
    "cloud": PointCloud2,
    "markers": MarkerArray,
}
LATCHED = {"map", "cloud", "markers", "nodes"}


def qos(latched=False, depth=10, best_effort=False):
    rel = Policy.Reliability.BestEffort if best_effort else Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1))
    dur = Policy.Durability.TransientLocal if latched else Policy.Durability.Volatile
    return Qos(rel, dur, Policy.History.KeepLast(depth), Policy.DataRepresentation(use_cdrv0_representation=True))


def stamp_ns(h):
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec


def brief(kind, m):
    if kind == "odometry":
        p = m.pose.pose.position
        return {"stamp_ns": stamp_ns(m.header), "frame_id": m.header.frame_id, "child_frame_id": m.child_frame_id,
                "position": [p.x, p.y, p.z], "cov_diag": [m.pose.covariance[i * 7] for i in range(6)]}
    if kind == "pose":
        p = m.pose.pose.position
        return {"stamp_ns": stamp_ns(m.header), "frame_id": m.header.frame_id, "position": [p.x, p.y, p.z]}
    if kind == "path":
        last = m.poses[-1].pose.position if m.poses else None
        return {"frame_id": m.header.frame_id, "poses": len(m.poses), "last": [last.x, last.y, last.z] if last else None}
    if kind == "tf":
        return {"transforms": [[t.header.frame_id, t.child_frame_id, stamp_ns(t.header),
                                [t.transform.translation.x, t.transform.translation.y, t.transform.translation.z]]
                               for t in m.transforms]}
    if kind == "map":
        known = sum(1 for v in m.data if v >= 0)
        occupied = sum(1 for v in m.data if v >= 65)
        return {"frame_id": m.header.frame_id, "resolution": m.info.resolution, "width": m.info.width,
                "height": m.info.height, "cells": len(m.data), "known": known, "occupied": occupied,
                "origin": [m.info.origin.position.x, m.info.origin.position.y]}
    if kind == "cloud":
        return {"frame_id": m.header.frame_id, "width": m.width, "height": m.height, "point_step": m.point_step,
                "fields": [[f.name, f.offset, f.datatype] for f in m.fields], "bytes": len(m.data)}
    if kind == "markers":
        return {"markers": [[mk.ns, mk.type, len(mk.points), mk.header.frame_id] for mk in m.markers]}
    if kind == "nodes":
        return {"nodes": [[n.node_namespace, n.node_name, len(n.reader_gid_seq), len(n.writer_gid_seq)]
                          for n in m.node_entities_info_seq]}
    return {}


def listen(args):
    seconds = float(args[0])
    until = {}
    specs = []
    i = 1
    while i < len(args):
        if args[i] == "--until":
            t, n = args[i + 1].split("=")
            until[t] = int(n)
            i += 2
        else:
            specs.append(args[i].split(":"))
            i += 1
    dp = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID", "0")))
    readers = []
    for name, kind in specs:
        cls = KINDS[kind]
        latched = kind in LATCHED or name == "/tf_static"
        # ROS topics are `rt/<name>` on DDS; `ros_discovery_info` (kind nodes) is a DDS topic as is.
        dds_name = name if kind == "nodes" else "rt" + name
        # One participant per gateway publishes on the keyless ros_discovery_info: keep them all.
        # Deep enough that a loaded machine, where this loop falls behind a burst of the main
        # job's fused poses, loses nothing from the reader's history (100 lost 13 of 601 in CI).
        depth = 1 if latched and kind != "nodes" else 10000
        topic = Topic(dp, dds_name, cls, qos=qos(latched=latched, depth=depth))
        readers.append((name, kind, DataReader(dp, topic, qos=qos(latched=latched, depth=depth))))
    out = {name: {"count": 0} for name, _, _ in readers}
    end = time.monotonic() + seconds
    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    while time.monotonic() < end and not stop:
        got = False
        for name, kind, r in readers:
            for m in r.take(N=256):
                if not isinstance(m, KINDS[kind]):
                    continue  # a dispose / unregister notice (InvalidSample), not data
                got = True
                o = out[name]
                o["count"] += 1
                b = brief(kind, m)
                o.setdefault("first", b)
                o["last"] = b
                if kind == "nodes":  # every node seen, with its most readers and writers
                    seen = o.setdefault("nodes", {})
                    for ns, n, r, w in b["nodes"]:
                        k = ns.rstrip("/") + "/" + n
                        seen[k] = [max(r, seen.get(k, [0, 0])[0]), max(w, seen.get(k, [0, 0])[1])]
        if until and all(out[t]["count"] >= n for t, n in until.items()):
            break
        if not got:
            time.sleep(0.01)
    print(json.dumps(out))


def carmen(args):
    log = args[0]
    max_scans = int(args[args.index("--max-scans") + 1]) if "--max-scans" in args else 0
    rate_x = float(args[args.index("--rate-x") + 1]) if "--rate-x" in args else 0.0
    dp = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID", "0")))
    q = qos(depth=1000)
    scan_w = DataWriter(dp, Topic(dp, "rt/scan", LaserScan, qos=q), qos=q)
    odom_w = DataWriter(dp, Topic(dp, "rt/odom", Odometry, qos=q), qos=q)
    # Wait for the gateway's readers (reliable writers send only to matched readers).
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if scan_w.get_matched_subscriptions() and odom_w.get_matched_subscriptions():
            break
        time.sleep(0.05)
    else:
        print("no subscriber for /scan and /odom within 60 s", file=sys.stderr)
        return 1
    time.sleep(0.5)
    opener = gzip.open if log.endswith(".gz") else open
    n = 0
    t0 = None
    wall0 = time.monotonic()
    with opener(log, "rt") as f:
        for line in f:
            p = line.split()
            if not p or p[0] != "FLASER":
                continue
            k = int(p[1])
            ranges = [float(r) for r in p[2:2 + k]]
            ox, oy, oth = (float(v) for v in p[5 + k:8 + k])
            t = float(p[8 + k])
            if t0 is None:
                t0 = t
            if rate_x > 0:
                wait = (t - t0) / rate_x - (time.monotonic() - wall0)
                if wait > 0:
                    time.sleep(wait)
            sec = int(math.floor(t))
            h = Header(stamp=Time(sec=sec, nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000), frame_id="odom")
            pose = Pose(position=Point(x=ox, y=oy), orientation=Quaternion(z=math.sin(oth / 2), w=math.cos(oth / 2)))
            odom_w.write(Odometry(header=h, child_frame_id="base_link", pose=PoseWithCovariance(pose=pose)))
            inc = math.pi / (k - 1) if k % 2 == 1 else math.pi / k
            hs = Header(stamp=h.stamp, frame_id="laser")
            scan_w.write(LaserScan(header=hs, angle_min=-math.pi / 2, angle_max=-math.pi / 2 + inc * (k - 1),
                                   angle_increment=inc, range_min=0.01, range_max=80.0, ranges=ranges))
            n += 1
            if max_scans and n >= max_scans:
                break
    # Reliable: stay until the gateway has acknowledged everything.
    try:
        scan_w.wait_for_acknowledgments(10.0)
        odom_w.wait_for_acknowledgments(10.0)
    except Exception:
        time.sleep(3)
    print(json.dumps({"scans": n}))
    return 0


def bad(args):
    seconds = float(args[0])
    dp = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID", "0")))
    q = qos(depth=100)
    scan_w = DataWriter(dp, Topic(dp, "rt/scan", LaserScan, qos=q), qos=q)
    odom_w = DataWriter(dp, Topic(dp, "rt/odom", Odometry, qos=q), qos=q)
    cloud_w = DataWriter(dp, Topic(dp, "rt/cloud", PointCloud2, qos=q), qos=q)
    # A best-effort writer where the gateway's route asks for reliable; an Odometry writer on a
    # LaserScan route's topic. Discovery tells the gateway; nothing of theirs can arrive.
    be = qos(depth=10, best_effort=True)
    be_w = DataWriter(dp, Topic(dp, "rt/scan_be", LaserScan, qos=be), qos=be)
    typed_w = DataWriter(dp, Topic(dp, "rt/scan_typed", Odometry, qos=q), qos=q)
    info_w = DataWriter(dp, Topic(dp, "rt/camera_info", CameraInfo, qos=q), qos=q)
    depth_w = DataWriter(dp, Topic(dp, "rt/depth", Image, qos=q), qos=q)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (scan_w.get_matched_subscriptions() and cloud_w.get_matched_subscriptions()):
        time.sleep(0.05)
    time.sleep(0.5)
    h = Header(stamp=Time(sec=5), frame_id="laser")
    scan_w.write(LaserScan(header=h, angle_increment=float("nan"), range_min=0.1, range_max=30.0, ranges=[1.0, 2.0]))
    scan_w.write(LaserScan(header=h, angle_min=-1.0, angle_increment=0.5, range_min=0.1, range_max=30.0,
                           ranges=[1.0, 2.0, 3.0]))
    odom_w.write(Odometry(header=h, pose=PoseWithCovariance(pose=Pose(orientation=Quaternion(w=0.0)))))
    xy = [PointField(name="x", offset=0, datatype=7, count=1), PointField(name="y", offset=4, datatype=7, count=1)]
    cloud_w.write(PointCloud2(header=h, height=1, width=1, fields=xy, point_step=8, row_step=8, data=[0] * 8))
    be_w.write(LaserScan(header=h, angle_increment=0.5, range_min=0.1, range_max=30.0, ranges=[1.0]))
    # A good 4x2 depth image (16UC1, mm) after its camera info: two points.
    info_w.write(CameraInfo(header=h, height=2, width=4, k=[100.0, 0, 2.0, 0, 100.0, 1.0, 0, 0, 1.0]))
    time.sleep(0.3)
    depth = [0] * 16
    depth[0:2] = list((2000).to_bytes(2, "little"))
    depth[14:16] = list((1000).to_bytes(2, "little"))
    depth_w.write(Image(header=h, height=2, width=4, encoding="16UC1", step=8, data=depth))
    typed_w.write(Odometry(header=h))
    time.sleep(seconds)
    print(json.dumps({"sent": 8}))
    return 0


def main(argv):
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    cmd, args = argv[1], argv[2:]
    if cmd == "listen":
        listen(args)
        return 0
    if cmd == "carmen":
        return carmen(args)
    if cmd == "bad":
        return bad(args)
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv))
