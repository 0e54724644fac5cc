"""Decoding Foxglove-schema messages (protobuf) with nothing but the schema that comes with them:
a live channel's advertisement or an MCAP file's schema record, as the Foxglove app does. Used by
foxglove_ws_client.py and mcap_foxglove.py. Needs the PyPI package `protobuf`."""

import math
import struct

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory


def message_class(schema_data, schema_name, pools):
    """The protobuf class of a schema: a FileDescriptorSet (as a Foxglove channel advertises it
    and as an MCAP schema record holds it) and the message's full name. `pools` keeps the
    descriptor pools alive."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    pools.append(pool)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def vec(v):
    return [v.x, v.y, v.z]


def summary(schema, m):
    """What a decoded message held, in a few numbers."""
    if schema == "foxglove.PointCloud":
        n = len(m.data) // m.point_stride if m.point_stride else 0
        names = [f.name for f in m.fields]
        first = list(struct.unpack_from(f"<{len(names)}f", m.data, 0)) if n else []
        return {
            "points": n,
            "fields": names,
            "frame_id": m.frame_id,
            "first": first,
            "finite": all(math.isfinite(x) for x in first),
        }
    if schema == "foxglove.PosesInFrame":
        last = vec(m.poses[-1].position) if m.poses else []
        return {"poses": len(m.poses), "frame_id": m.frame_id, "last": last,
                "finite": all(math.isfinite(x) for x in last)}
    if schema == "foxglove.PoseInFrame":
        p = vec(m.pose.position)
        return {"position": p, "frame_id": m.frame_id, "finite": all(math.isfinite(x) for x in p)}
    if schema == "foxglove.Log":
        return {"name": m.name, "message": m.message}
    if schema == "foxglove.Grid":
        stride = m.cell_stride or 1
        out = {"columns": m.column_count, "cells": len(m.data) // stride, "frame_id": m.frame_id,
               "cell_size": m.cell_size.x, "fields": [f.name for f in m.fields]}
        # A `class` field (uint8: the traversability grid's 0 unknown, 1 navigable, 2 obstacle)
        # is counted per value, and a `height` field (float32) checked finite, cell by cell
        # where the grid's own offsets say.
        by_name = {f.name: f for f in m.fields}
        if "class" in by_name:
            off = by_name["class"].offset
            counts = {}
            for i in range(out["cells"]):
                c = m.data[i * stride + off]
                counts[c] = counts.get(c, 0) + 1
            out["class_counts"] = {str(k): v for k, v in sorted(counts.items())}
        if "height" in by_name:
            off = by_name["height"].offset
            out["heights_finite"] = all(
                math.isfinite(struct.unpack_from("<f", m.data, i * stride + off)[0]) for i in range(out["cells"]))
        return out
    return {}
