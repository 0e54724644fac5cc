#!/usr/bin/env python3
"""A Foxglove WebSocket client that stops reading: it connects with a small receive buffer,
subscribes to every channel the server advertises, then reads nothing for --stall-s seconds
(a viewer on a slow link, or a frozen app). The server must drop for it, not block the pipeline.

Prints one JSON object: the channels it subscribed to. Needs the PyPI package `websockets`.
"""

import argparse
import json
import socket
import sys
import time
from urllib.parse import urlparse

from websockets.sync.client import connect

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", required=True)
    ap.add_argument("--stall-s", type=float, default=10.0)
    ap.add_argument("--timeout-s", type=float, default=60.0)
    args = ap.parse_args()
    u = urlparse(args.url)
    deadline = time.monotonic() + args.timeout_s
    ws = None
    while ws is None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        # Small, set before connecting so that the window the server sees stays small.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        try:
            sock.connect((u.hostname, u.port))
            ws = connect(args.url, sock=sock, subprotocols=SUBPROTOCOLS, max_size=None, open_timeout=5)
        except OSError:
            sock.close()
            if time.monotonic() > deadline:
                print(f"could not connect to {args.url}", file=sys.stderr)
                return 1
            time.sleep(0.2)
    topics = []
    while not topics and time.monotonic() < deadline:
        frame = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg.get("op") == "advertise":
                subs = [{"id": i + 1, "channelId": c["id"]} for i, c in enumerate(msg["channels"])]
                topics = [c["topic"] for c in msg["channels"]]
                ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
    time.sleep(args.stall_s)  # read nothing
    print(json.dumps({"subscribed": topics}))
    ws.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
