"""A compromised robot, written with Eclipse Zenoh's own Python API (PyPI `eclipse-zenoh`, not our
code): it holds robot `auv1`'s valid certificate, so the base station's access control lets it
publish under `auv1`'s keys, and it sends what a broken or hijacked robot might, built with the
generated wire mirrors (python/slam_pipeline_wire.py): good odometry, odometry with NaN, repeated
sequence numbers, `origin_ns` far in the future and far in the past, and a flood; then an end
marker with the number it sent. Prints one JSON line with what it sent, per kind.

Used by tests/tests/security.rs.
"""

import argparse
import hashlib
import ctypes
import json
import os
import sys
import time

import zenoh

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "python"))
from slam_pipeline_wire import MsgHeader, OdometryInput  # noqa: E402

ODOMETRY = "pipeline/sensors/odometry"


def message(seq: int, stamp_ns: int, origin_ns: int, v_mps: float = 0.5) -> bytes:
    h = MsgHeader(stamp_ns=stamp_ns, seq=seq, origin_ns=origin_ns, publish_ns=0)
    u = OdometryInput(v_mps=v_mps, dt_s=0.1)
    for i in range(4):
        u.input_covariance[i * 5] = 0.01
    return bytes(h) + bytes(u)



def zid_of(name):
    """The Zenoh id a bridge expects of the holder of the certificate named `name` (docs/security.md)."""
    d = hashlib.sha256(b"slam-bridge zid\0" + name.encode()).digest()
    return format(int.from_bytes(d[:16], "big") | 1 << 127, "x")

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--endpoint", required=True)
    ap.add_argument("--ca", required=True)
    ap.add_argument("--cert", required=True)
    ap.add_argument("--key-file", required=True)
    ap.add_argument("--id", help="Zenoh id to use (a bridge lets a certificate's holder in only with the id of its name)")
    ap.add_argument("--id-of", help="use the Zenoh id of this certificate name (docs/security.md's recipe)")
    ap.add_argument("--attachment", required=True, help="the wire signature")
    ap.add_argument("--flood", type=int, default=3000, help="messages sent back to back at the end")
    a = ap.parse_args()

    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("connect/endpoints", json.dumps([a.endpoint]))
    c.insert_json5("connect/exit_on_failure", "false")
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("transport/shared_memory/enabled", "false")
    if a.id_of:
        a.id = zid_of(a.id_of)
    if a.id:
        c.insert_json5("id", json.dumps(a.id))
    tls = {
        "root_ca_certificate": a.ca,
        "verify_name_on_connect": False,
        "enable_mtls": True,
        "connect_certificate": a.cert,
        "connect_private_key": a.key_file,
    }
    c.insert_json5("transport/link/tls", json.dumps(tls))
    s = zenoh.open(c)
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and not list(s.info.peers_zid()):
        time.sleep(0.05)
    if not list(s.info.peers_zid()):
        print(json.dumps({"error": "never linked to the base station"}), flush=True)
        sys.exit(1)
    # Let the base station's subscription arrive before the first put.
    time.sleep(1.0)
    pub = s.declare_publisher(f"slam/auv1/{ODOMETRY}", congestion_control=zenoh.CongestionControl.BLOCK)
    att = a.attachment.encode()
    sent = {"good": 0, "nan": 0, "repeated": 0, "future": 0, "past": 0, "flood": 0}
    seq, stamp = 100, 1_000_000_000

    def put(kind: str, data: bytes) -> None:
        pub.put(data, attachment=att)
        sent[kind] += 1

    def now() -> int:
        return time.clock_gettime_ns(time.CLOCK_MONOTONIC)

    for _ in range(10):
        put("good", message(seq, stamp, now()))
        seq, stamp = seq + 1, stamp + 100_000_000
        time.sleep(0.01)
    for _ in range(5):
        put("nan", message(seq, stamp, now(), v_mps=float("nan")))
        seq, stamp = seq + 1, stamp + 100_000_000
    for _ in range(5):
        put("repeated", message(seq - 1, stamp, now()))
    for _ in range(5):
        put("future", message(seq, stamp, now() + 10_000_000_000))
        seq, stamp = seq + 1, stamp + 100_000_000
    for _ in range(5):
        put("past", message(seq, stamp, max(1, now() - 1_000_000_000_000)))
        seq, stamp = seq + 1, stamp + 100_000_000
    for _ in range(a.flood):
        put("flood", message(seq, stamp, now()))
        seq, stamp = seq + 1, stamp + 1_000_000
    total = sum(sent.values())
    s.put(f"slam/auv1/_bridge/end", json.dumps({"sent": {ODOMETRY: total}}))
    time.sleep(1.0)
    s.close()
    print(json.dumps({"sent": sent, "total": total}), flush=True)


if __name__ == "__main__":
    main()
