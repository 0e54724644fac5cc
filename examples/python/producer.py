#!/usr/bin/env python3
"""External point-cloud producer for the SLAM pipeline, in Python (iceoryx2 0.10 + ctypes).

Publishes deterministic point clouds on ``pipeline/sensors/cloud`` exactly like the Rust
``test_producer`` (point ``i`` of cloud ``seq`` equals ``testkit::cloud_point(seq, i)``
bit for bit), so the ``test_consumer`` process verifies every point it receives. It is also a
template for writing your own producer in Python.

Wire contract (``docs/WIRE_FORMAT.md``, ``python/slam_pipeline_wire.py``):

* payload: a slice of ``CloudPoint`` (``slam_pipeline::v1::CloudPoint``, 12 bytes, align 4),
  user header ``CloudHeader`` (``slam_pipeline::v1::CloudHeader``, 96 bytes, align 8);
* the service is opened with exactly the QoS of ``slam_pipeline_wire.SERVICES`` (iceoryx2 refuses
  to open a service created with different settings);
* after every send the event service of the same name is notified (the subscribers block in a
  WaitSet on it);
* after ``--frames`` clouds one ``EndOfStream`` goes out on ``pipeline/control/end_of_stream``
  (and its event is notified); the process then stays alive, so the shared memory of its last
  samples stays valid, until SIGTERM or SIGINT, on which it exits 0.

Environment (set by the supervisor for ``kind = "external"`` processes):

* ``SLAM_PIPELINE_IOX_PREFIX``: iceoryx2 file prefix of the run (default ``slam_``);
* ``SLAM_PIPELINE_IOX_ROOT``: iceoryx2 root path (default ``/tmp/slam_pipeline/<prefix>/``);
* ``SLAM_PIPELINE_IOX_CONFIG``: optional iceoryx2 config file to start from;
* ``SLAM_PIPELINE_PROCESS``: this process's name (default ``python_producer``), used as the
  iceoryx2 node name and in the ``EndOfStream`` message.

Usage::

    python3 -m pip install iceoryx2==0.10.0
    python3 examples/python/producer.py --points 300000 --rate-hz 10 --frames 100

Exit codes: 0 done (stopped by SIGTERM/SIGINT), 1 iceoryx2 set-up or send failure, 2 bad
arguments or iceoryx2 missing.
"""

from __future__ import annotations

import argparse
import array
import ctypes
import os
import select
import signal
import sys
import time
from pathlib import Path

# The generated ctypes mirrors of the wire types live in <repo>/python/.
_REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(_REPO / "python"))
import slam_pipeline_wire as wire  # noqa: E402

ICEORYX2_VERSION = "0.10.0"
CLOUD = "pipeline/sensors/cloud"
END_OF_STREAM = "pipeline/control/end_of_stream"
FRAME_SENSOR = 0
# Rust computes the coordinates in f32: `(i % 1024) as f32 * 0.01f32`. The f32 value of 0.01
# times a small integer is exact in double precision, so rounding that product to f32 (which
# array('f') does on store) gives exactly Rust's f32 product.
F32_CENTI = ctypes.c_float(0.01).value

try:
    import iceoryx2 as iox
except ImportError as _e:  # pragma: no cover - depends on the machine
    sys.stderr.write(
        f"error: the Python package `iceoryx2` is missing ({_e}).\n"
        f"Install it with: python3 -m pip install iceoryx2=={ICEORYX2_VERSION}\n"
    )
    sys.exit(2)


class SetupError(Exception):
    """iceoryx2 could not be set up (config, node, service or port)."""


def log(name: str, msg: str) -> None:
    print(f"{name}: {msg}", file=sys.stderr, flush=True)


def check_iceoryx2_version() -> None:
    """Refuses another iceoryx2 version: shared-memory names and layouts differ between versions."""
    try:
        from importlib.metadata import version

        v = version("iceoryx2")
    except Exception:  # metadata missing: let the service open decide
        return
    if v.split(".")[:2] != ICEORYX2_VERSION.split(".")[:2]:
        sys.stderr.write(
            f"error: iceoryx2 {v} is installed, the pipeline uses {ICEORYX2_VERSION}.\n"
            f"Install the matching version with: python3 -m pip install iceoryx2=={ICEORYX2_VERSION}\n"
        )
        sys.exit(2)


# --------------------------------------------------------------------------------------------
# iceoryx2 set-up


def iox_config(prefix: str, root: str, base_file: str | None) -> "iox.config.Config":
    """The iceoryx2 config of the run: same prefix and root path as every Rust process."""
    try:
        if base_file:
            config = iox.config.from_file(iox.FilePath.new(base_file))
        else:
            config = iox.config.default()
        if not root.endswith("/"):
            root += "/"
        g = config.global_cfg  # a view: setting its fields changes `config`
        g.prefix = iox.FileName.new(prefix)
        g.root_path = iox.Path.new(root)
    except Exception as e:
        raise SetupError(
            f"invalid iceoryx2 config (prefix `{prefix}`, root `{root}`, base file {base_file!r}): "
            f"{type(e).__name__}: {e}"
        ) from e
    return config


def describe_qos(q: dict) -> str:
    keys = (
        "max_publishers",
        "max_subscribers",
        "max_nodes",
        "subscriber_max_buffer_size",
        "subscriber_max_borrowed_samples",
        "history_size",
        "enable_safe_overflow",
    )
    return ", ".join(f"{k}={q[k]}" for k in keys)


def open_pubsub(node, name: str, payload_type, header_type):
    """Opens (or creates) the publish-subscribe service `name` with the contract's exact QoS."""
    q = wire.SERVICES[name]
    try:
        return (
            node.service_builder(iox.ServiceName.new(name))
            .publish_subscribe(payload_type)
            .user_header(header_type)
            .max_publishers(q["max_publishers"])
            .max_subscribers(q["max_subscribers"])
            .max_nodes(q["max_nodes"])
            .subscriber_max_buffer_size(q["subscriber_max_buffer_size"])
            .subscriber_max_borrowed_samples(q["subscriber_max_borrowed_samples"])
            .history_size(q["history_size"])
            .enable_safe_overflow(q["enable_safe_overflow"])
            .open_or_create()
        )
    except Exception as e:
        raise SetupError(
            f"cannot open publish-subscribe service `{name}` (payload {q['payload']}, user header "
            f"{q['user_header']}) with QoS {describe_qos(q)}: {type(e).__name__}: {e}. "
            "Another process may have created it with a different type or QoS, or with another "
            "iceoryx2 version."
        ) from e


def open_event(node, name: str):
    """Opens (or creates) the event service `name`, as the Rust runtime does (ports.rs open_event)."""
    q = wire.SERVICES[name]
    try:
        return (
            node.service_builder(iox.ServiceName.new(name))
            .event()
            .max_notifiers(q["max_publishers"])
            .max_listeners(q["max_subscribers"])
            .max_nodes(q["max_nodes"])
            .open_or_create()
        )
    except Exception as e:
        raise SetupError(
            f"cannot open event service `{name}` with max_notifiers={q['max_publishers']}, "
            f"max_listeners={q['max_subscribers']}, max_nodes={q['max_nodes']}: "
            f"{type(e).__name__}: {e}"
        ) from e


def create_port(what: str, name: str, builder):
    try:
        return builder.create()
    except Exception as e:
        raise SetupError(f"cannot create a {what} on `{name}`: {type(e).__name__}: {e}") from e


# --------------------------------------------------------------------------------------------
# Cloud content (testkit::cloud_point)


class CloudWriter:
    """Writes cloud `seq` of `n` points into loaned shared memory without a per-point Python loop.

    x and y do not depend on `seq`: they are computed once into a template that is copied with
    one memmove; z = (seq % 4096) + (i % 7) is then written as a strided column (period 7).
    """

    def __init__(self, n: int) -> None:
        self.n = n
        self.nbytes = n * ctypes.sizeof(wire.CloudPoint)
        blocks = (n + 1023) // 1024
        xs = array.array("f", [k * F32_CENTI for k in range(1024)]) * blocks
        del xs[n:]
        ys = array.array("f")
        for b in range(blocks):
            ys.extend(array.array("f", [b * F32_CENTI]) * 1024)
        del ys[n:]
        self.template = array.array("f", bytes(self.nbytes))  # x, y, z per point
        self.template[0::3] = xs
        self.template[1::3] = ys
        self.template_addr, _ = self.template.buffer_info()
        self.periods = (n + 6) // 7

    def z_column(self, seq: int) -> array.array:
        base = seq % 4096  # base + (i % 7) < 4103: an integer, exact in f32
        z = array.array("f", [float(base + k) for k in range(7)]) * self.periods
        del z[self.n :]
        return z

    def write(self, ptr: int, seq: int) -> None:
        ctypes.memmove(ptr, self.template_addr, self.nbytes)
        floats = (ctypes.c_float * (3 * self.n)).from_address(ptr)
        with memoryview(floats) as raw, raw.cast("B") as b, b.cast("f") as f:
            f[2::3] = self.z_column(seq)


# --------------------------------------------------------------------------------------------
# Signals


class Stopper:
    """SIGTERM/SIGINT set a flag and wake `wait` at once (a self-pipe; no polling)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._r, self._w = os.pipe()
        os.set_blocking(self._r, False)
        os.set_blocking(self._w, False)
        signal.set_wakeup_fd(self._w, warn_on_full_buffer=False)
        for s in (signal.SIGTERM, signal.SIGINT):
            signal.signal(s, self._handle)

    def _handle(self, signum, _frame) -> None:
        self.signum = signum

    @property
    def stopped(self) -> bool:
        return self.signum is not None

    def wait(self, timeout: float | None) -> bool:
        """Sleeps up to `timeout` s (None = until a signal); returns True once a signal came."""
        if self.stopped:
            return True
        if timeout is not None and timeout <= 0:
            return False
        ready, _, _ = select.select([self._r], [], [], timeout)
        if ready:
            try:
                os.read(self._r, 512)
            except BlockingIOError:
                pass
        return self.stopped


# --------------------------------------------------------------------------------------------


def name32(name: str) -> ctypes.Array:
    raw = name.encode("utf-8")[:32]
    return (ctypes.c_uint8 * 32)(*raw)


def write_header(ptr: int, header: ctypes.Structure) -> None:
    ctypes.memmove(ptr, ctypes.addressof(header), ctypes.sizeof(header))


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description="Publish deterministic point clouds on pipeline/sensors/cloud (iceoryx2 0.10).",
        epilog="Environment: SLAM_PIPELINE_IOX_PREFIX, SLAM_PIPELINE_IOX_ROOT, "
        "SLAM_PIPELINE_IOX_CONFIG, SLAM_PIPELINE_PROCESS (see the module docstring).",
    )
    p.add_argument("--points", type=int, default=10_000, help="points per cloud (default 10000)")
    p.add_argument("--rate-hz", type=float, default=10.0, help="clouds per second (default 10)")
    p.add_argument(
        "--frames", type=int, default=0, help="clouds before end of stream (default 0 = until stopped)"
    )
    a = p.parse_args(argv)
    if not 1 <= a.points <= 4_000_000:
        p.error(f"--points must be 1..=4000000, got {a.points}")
    if not (a.rate_hz > 0 and a.rate_hz <= 10_000):
        p.error(f"--rate-hz must be in (0, 10000], got {a.rate_hz}")
    if a.frames < 0:
        p.error(f"--frames must be >= 0, got {a.frames}")
    return a


def run(args: argparse.Namespace) -> int:
    name = os.environ.get("SLAM_PIPELINE_PROCESS") or "python_producer"
    prefix = os.environ.get("SLAM_PIPELINE_IOX_PREFIX") or "slam_"
    root = os.environ.get("SLAM_PIPELINE_IOX_ROOT") or f"/tmp/slam_pipeline/{prefix}/"
    base_file = os.environ.get("SLAM_PIPELINE_IOX_CONFIG") or None

    config = iox_config(prefix, root, base_file)
    try:
        node = (
            iox.NodeBuilder.new()
            .name(iox.NodeName.new(name))
            .config(config)
            # Signals are ours (Stopper), not iceoryx2's.
            .signal_handling_mode(iox.SignalHandlingMode.Disabled)
            .create(iox.ServiceType.Ipc)
        )
    except Exception as e:
        raise SetupError(
            f"cannot create iceoryx2 node `{name}` (prefix `{prefix}`, root `{root}`): {type(e).__name__}: {e}"
        ) from e
    stopper = Stopper()

    # Services and ports. Everything is opened up front so a mismatch fails before sending.
    cloud_svc = open_pubsub(node, CLOUD, iox.Slice[wire.CloudPoint], wire.CloudHeader)
    cloud_pub = create_port(
        "publisher",
        CLOUD,
        cloud_svc.publisher_builder()
        .initial_max_slice_len(args.points)
        .allocation_strategy(iox.AllocationStrategy.PowerOfTwo)
        .max_loaned_samples(1)
        # A live source never blocks on a slow subscriber: a full queue drops the sample for
        # it (the cloud service does not overflow; the subscriber sees a sequence gap).
        .backpressure_strategy(iox.BackpressureStrategy.DiscardData),
    )
    cloud_notifier = create_port("notifier", CLOUD, open_event(node, CLOUD).notifier_builder())
    eos_svc = open_pubsub(node, END_OF_STREAM, wire.EndOfStream, wire.MsgHeader)
    eos_pub = create_port(
        "publisher",
        END_OF_STREAM,
        eos_svc.publisher_builder()
        .max_loaned_samples(1)
        .backpressure_strategy(iox.BackpressureStrategy.DiscardData),
    )
    eos_notifier = create_port("notifier", END_OF_STREAM, open_event(node, END_OF_STREAM).notifier_builder())

    writer = CloudWriter(args.points)
    period_ns = int(1e9 / args.rate_hz)
    log(
        name,
        f"publishing {args.points}-point clouds at {args.rate_hz} Hz on {CLOUD} "
        f"({'until stopped' if args.frames == 0 else f'{args.frames} frames'}; prefix `{prefix}`, root `{root}`)",
    )

    # A subscriber attaches to a new publisher when its loop runs; wake the subscribers
    # (notifications without data) for a moment so none misses the first clouds.
    for _ in range(20):
        cloud_notifier.notify()
        if stopper.wait(0.025):
            break

    sent = 0
    next_ns = time.monotonic_ns()
    try:
        while not stopper.stopped and (args.frames == 0 or sent < args.frames):
            if stopper.wait((next_ns - time.monotonic_ns()) / 1e9):
                break
            seq = sent
            stamp_ns = time.monotonic_ns()
            sample = cloud_pub.loan_slice_uninit(args.points)
            writer.write(sample.payload_ptr, seq)
            sample = sample.assume_init()
            now = time.monotonic_ns()
            header = wire.CloudHeader(
                msg=wire.MsgHeader(stamp_ns=stamp_ns, seq=seq, origin_ns=now, publish_ns=now),
                orientation_xyzw=(ctypes.c_double * 4)(0.0, 0.0, 0.0, 1.0),
                frame=FRAME_SENSOR,
            )
            write_header(sample.user_header_ptr, header)
            sample.send()
            cloud_notifier.notify()
            sent += 1
            # Fixed schedule; after a long stall, restart it rather than burst to catch up.
            next_ns += period_ns
            if time.monotonic_ns() - next_ns > 10 * period_ns:
                next_ns = time.monotonic_ns() + period_ns

        if not stopper.stopped and args.frames > 0:
            eos = eos_pub.loan_uninit().write_payload(
                wire.EndOfStream(process=name32(name), last_seq=sent - 1, messages_sent=sent)
            )
            now = time.monotonic_ns()
            write_header(eos.user_header_ptr, wire.MsgHeader(stamp_ns=now, seq=0, origin_ns=now, publish_ns=now))
            eos.send()
            eos_notifier.notify()
            log(name, f"sent end of stream after {sent} clouds (last_seq {sent - 1}); waiting for SIGTERM/SIGINT")

        # Stay alive (our samples' shared memory stays valid) until told to stop.
        while not stopper.wait(None):
            pass
    except Exception as e:
        log(name, f"error after {sent} clouds: {type(e).__name__}: {e}")
        return 1
    finally:
        # Release the ports before the node so the shared memory is removed cleanly.
        for port in (eos_notifier, eos_pub, cloud_notifier, cloud_pub):
            port.delete()
        del eos_svc, cloud_svc, node
    log(name, f"stopped by signal {stopper.signum} after {sent} clouds")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    check_iceoryx2_version()
    try:
        return run(args)
    except SetupError as e:
        sys.stderr.write(f"error: {e}\n")
        return 1


if __name__ == "__main__":
    sys.exit(main())
