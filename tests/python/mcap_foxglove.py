#!/usr/bin/env python3
"""Reads a recording with Python's `mcap` reader and decodes its Foxglove-schema channels with the
protobuf schemas the file holds (as Foxglove does): prints one JSON object, per channel with a
`protobuf` encoding, its schema name, message count and what the last message held.

Usage: mcap_foxglove.py FILE. Needs the PyPI packages `mcap` and `protobuf` (scripts/test.sh
installs them)."""

import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from foxglove_decode import message_class, summary  # noqa: E402
from mcap.reader import make_reader  # noqa: E402


def main():
    pools = []
    classes = {}
    seen = {}
    with open(sys.argv[1], "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.message_encoding != "protobuf":
                continue
            if schema is None or schema.encoding != "protobuf":
                raise ValueError(f"{channel.topic}: protobuf messages without a protobuf schema")
            if channel.id not in classes:
                classes[channel.id] = message_class(schema.data, schema.name, pools)
            m = classes[channel.id].FromString(message.data)
            s = seen.setdefault(channel.topic, {"schema": schema.name, "count": 0})
            s["count"] += 1
            s["last"] = summary(schema.name, m)
    print(json.dumps(seen))


if __name__ == "__main__":
    main()
