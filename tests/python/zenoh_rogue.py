"""A rogue Zenoh peer, written with Eclipse Zenoh's own Python API (PyPI `eclipse-zenoh`, not our
code): it connects to an endpoint, with or without a client certificate, and puts messages that
carry the pipeline's wire signature (public in docs/WIRE_FORMAT.md) under a key of its choice, as
an attacker on the base station's network would. Prints one JSON line: how many peers it was
linked to, and how many messages it put.

Used by tests/tests/security.rs.
"""

import argparse
import hashlib
import json
import time

import zenoh



def zid_of(name):
    """The Zenoh id a bridge expects of the holder of the certificate named `name` (docs/security.md)."""
    d = hashlib.sha256(b"slam-bridge zid\0" + name.encode()).digest()
    return format(int.from_bytes(d[:16], "big") | 1 << 127, "x")

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--endpoint", required=True, help="e.g. tls/127.0.0.1:7447")
    ap.add_argument("--key", required=True, help="e.g. slam/auv1/pipeline/sensors/odometry")
    ap.add_argument("--attachment", required=True, help="the wire signature to attach")
    ap.add_argument("--size", type=int, default=200, help="bytes per message")
    ap.add_argument("--count", type=int, default=200)
    ap.add_argument("--seconds", type=float, default=4.0, help="spread the puts over this long")
    ap.add_argument("--ca", help="CA certificate to trust (TLS)")
    ap.add_argument("--cert", help="client certificate (mutual TLS)")
    ap.add_argument("--key-file", help="client private key (mutual TLS)")
    ap.add_argument("--id", help="Zenoh id to use (a bridge lets a certificate's holder in only with the id of its name)")
    ap.add_argument("--id-of", help="use the Zenoh id of this certificate name (docs/security.md's recipe)")
    a = ap.parse_args()

    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("connect/endpoints", json.dumps([a.endpoint]))
    c.insert_json5("connect/exit_on_failure", "false")
    c.insert_json5("scouting/multicast/enabled", "false")
    # The wheel is built with shared memory, which leaves a segment in /dev/shm: not wanted here.
    c.insert_json5("transport/shared_memory/enabled", "false")
    if a.id_of:
        a.id = zid_of(a.id_of)
    if a.id:
        c.insert_json5("id", json.dumps(a.id))
    if a.ca:
        tls = {"root_ca_certificate": a.ca, "verify_name_on_connect": False}
        if a.cert:
            tls.update(enable_mtls=True, connect_certificate=a.cert, connect_private_key=a.key_file)
        c.insert_json5("transport/link/tls", json.dumps(tls))
    s = zenoh.open(c)
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline and not list(s.info.peers_zid()):
        time.sleep(0.05)
    peers_max = 0
    pub = s.declare_publisher(a.key)
    payload = bytes(a.size)
    for _ in range(a.count):
        pub.put(payload, attachment=a.attachment.encode())
        peers_max = max(peers_max, len(list(s.info.peers_zid())))
        time.sleep(a.seconds / a.count)
    s.close()
    print(json.dumps({"peers": peers_max, "put": a.count}), flush=True)


if __name__ == "__main__":
    main()
