#!/usr/bin/env python3
"""A Foxglove WebSocket client, as the Foxglove app is one (protocol foxglove.websocket.v1; the
Foxglove SDK's server names it `foxglove.sdk.v1`, with inline schemas: both are offered).

Connects to a viewer (retrying until it listens), subscribes to every advertised channel,
decodes each message with the protobuf schema the server advertised for its channel (no
Foxglove package: the schema comes over the wire, as the app takes it) and prints one JSON
object: per topic, the schema name, how many messages were decoded and what the last one held.
Stops when every topic named with --want has had a message (and --min-messages of each) and
every --at-least condition holds on its topic's last message, or at --timeout-s (then exits 1
naming the topics that never came or whose condition never held).

Needs the PyPI packages `websockets` and `protobuf` (scripts/test.sh installs them).
"""

import argparse
import base64
import json
import os
import struct
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from foxglove_decode import message_class, summary  # noqa: E402
import ssl

from websockets.exceptions import ConnectionClosed, InvalidMessage, InvalidStatus
from websockets.sync.client import connect

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
OP_MESSAGE_DATA = 1


def refused(args, why):
    print(json.dumps({"refused": why}))
    if not args.expect_refused:
        print(f"refused: {why}", file=sys.stderr)
    return 0 if args.expect_refused else 1


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", required=True)
    ap.add_argument("--want", action="append", default=[], help="a topic that must deliver (repeatable)")
    ap.add_argument("--min-messages", type=int, default=1)
    ap.add_argument("--timeout-s", type=float, default=120.0)
    ap.add_argument(
        "--at-least",
        nargs=3,
        action="append",
        default=[],
        metavar=("TOPIC", "FIELD", "N"),
        help="wait until TOPIC's last message has FIELD (a number in its summary, e.g. points) >= N (repeatable)",
    )
    ap.add_argument("--ca", help="trust this CA certificate (wss:// URLs)")
    ap.add_argument(
        "--expect-refused",
        action="store_true",
        help="the server must refuse the connection (HTTP status or TLS failure): print why and exit 0",
    )
    args = ap.parse_args()
    at_least = [(t, f, float(n)) for t, f, n in args.at_least]

    def unmet(seen):
        missing = [t for t in args.want if seen.get(t, {}).get("count", 0) < args.min_messages]
        for t, f, n in at_least:
            v = seen.get(t, {}).get("last", {}).get(f)
            if not isinstance(v, (int, float)) or v < n:
                missing.append(f"{t} ({f} >= {n:g}; last: {v})")
        return missing

    deadline = time.monotonic() + args.timeout_s
    ws = None
    ssl_ctx = None
    if args.url.startswith("wss://"):
        ssl_ctx = ssl.create_default_context(cafile=args.ca)
    while ws is None:
        try:
            ws = connect(args.url, subprotocols=SUBPROTOCOLS, max_size=None, open_timeout=5, ssl=ssl_ctx)
        except InvalidStatus as e:
            return refused(args, f"http {e.response.status_code}")
        except ssl.SSLError as e:
            return refused(args, f"tls: {e.reason or e}")
        except (InvalidMessage, ConnectionClosed, EOFError) as e:
            # A TLS server answering a plain ws:// request closes it.
            print(f"closed before a response: {e!r} (cause: {e.__cause__!r})", file=sys.stderr)
            return refused(args, f"closed: {type(e).__name__}")
        except OSError as e:
            print(f"connecting to {args.url}: {e!r}; retrying", file=sys.stderr)
            if time.monotonic() > deadline:
                print(f"could not connect to {args.url}", file=sys.stderr)
                return 1
            time.sleep(0.2)
    if args.expect_refused:
        print(json.dumps({"refused": None}))
        print("connected, but the server should have refused", file=sys.stderr)
        return 1
    if ws.subprotocol not in SUBPROTOCOLS:
        print(f"server chose subprotocol {ws.subprotocol!r}", file=sys.stderr)
        return 1

    pools = []
    channels = {}  # channel id -> (topic, schema name, class)
    subs = {}  # subscription id -> channel id
    seen = {}  # topic -> {"schema", "count", "last"}
    server_name = None
    closed = False
    with ws:
        while time.monotonic() < deadline:
            if (args.want or at_least) and not unmet(seen):
                break
            try:
                frame = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
            except TimeoutError:
                break
            except ConnectionClosed:
                closed = True  # the run ended: report what came
                break
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg.get("op") == "serverInfo":
                    server_name = msg.get("name")
                elif msg.get("op") == "advertise":
                    new = []
                    for c in msg["channels"]:
                        if c.get("encoding") != "protobuf" or c.get("schemaEncoding") != "protobuf":
                            raise ValueError(f"{c['topic']}: not a protobuf channel: {c}")
                        cls = message_class(base64.b64decode(c["schema"]), c["schemaName"], pools)
                        channels[c["id"]] = (c["topic"], c["schemaName"], cls)
                        sub = len(subs) + 1
                        subs[sub] = c["id"]
                        new.append({"id": sub, "channelId": c["id"]})
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                continue
            if not frame or frame[0] != OP_MESSAGE_DATA:
                continue
            sub, _log_time = struct.unpack_from("<IQ", frame, 1)
            topic, schema, cls = channels[subs[sub]]
            m = cls.FromString(frame[13:])
            s = seen.setdefault(topic, {"schema": schema, "count": 0})
            s["count"] += 1
            s["last"] = summary(schema, m)

    out = {"server": server_name, "subprotocol": ws.subprotocol, "closed_by_server": closed, "advertised": sorted(t for t, _, _ in channels.values()), "topics": seen}
    print(json.dumps(out))
    missing = unmet(seen)
    if missing:
        print(f"no message on: {', '.join(missing)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
