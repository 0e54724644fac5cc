//! `external_producer`: an example of a sensor driver outside the pipeline. It uses only the wire
//! contract (`shared_types`) and iceoryx2 — not the pipeline's runtime — the way a user's own
//! driver would: it opens the sensor services with the contract's QoS, writes samples in place,
//! fills the common header, sends, notifies the event service of the same name, and ends with
//! `EndOfStream`. `--hostile` interleaves invalid messages (NaN, zero δt, stamps going back,
//! unknown buoy ids, empty and oversized clouds; with `--stereo` also stereo observations with a
//! NaN point, behind the camera, a negative or an infinite variance) that the pipeline must reject
//! without harm;
//! `--wrong-layout` tries to publish another type under a contract service name, which iceoryx2
//! refuses.
//!
//! Run it under the supervisor as `kind = "external"` (it reads SLAM_PIPELINE_IOX_PREFIX,
//! SLAM_PIPELINE_IOX_ROOT and SLAM_PIPELINE_PROCESS), or next to a running pipeline with the same
//! prefix and root.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::*;
use shared_types::services::{self, BUOY_RANGES, CLOUD, END_OF_STREAM, ODOMETRY, Qos, STEREO};
use shared_types::{
    BuoyRange, CloudHeader, CloudPoint, EndOfStream, MsgHeader, OdometryInput, StereoObservation, name32,
};

#[derive(Debug, Parser)]
struct Args {
    /// Odometry messages to send (then end of stream).
    #[arg(long, default_value_t = 100)]
    frames: u64,
    /// Odometry rate, Hz (buoy ranges every 10th, a cloud every 5th).
    #[arg(long, default_value_t = 50.0)]
    rate_hz: f64,
    /// Points per cloud.
    #[arg(long, default_value_t = 1000)]
    points: usize,
    /// Also send invalid messages.
    #[arg(long)]
    hostile: bool,
    /// Points of the oversized cloud sent in hostile mode.
    #[arg(long, default_value_t = 20_000)]
    oversized_points: usize,
    /// Also publish stereo frames (every 3rd odometry message; 8 landmarks in front of the camera).
    #[arg(long)]
    stereo: bool,
    /// Try to publish a wrong type under the odometry service name, then exit.
    #[arg(long)]
    wrong_layout: bool,
}

fn now_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: valid pointer; CLOCK_MONOTONIC is the pipeline clock.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

fn node() -> anyhow::Result<Node<ipc::Service>> {
    let prefix = std::env::var("SLAM_PIPELINE_IOX_PREFIX").unwrap_or_else(|_| "slam_".into());
    let root = std::env::var("SLAM_PIPELINE_IOX_ROOT").unwrap_or_else(|_| format!("/tmp/slam_pipeline/{prefix}"));
    let name = std::env::var("SLAM_PIPELINE_PROCESS").unwrap_or_else(|_| "external_producer".into());
    let mut config = iceoryx2::config::Config::default();
    config.global.prefix = FileName::new(prefix.as_bytes()).context("prefix")?;
    config
        .global
        .set_root_path(&Path::new(format!("{}/", root.trim_end_matches('/')).as_bytes()).context("root path")?);
    Ok(NodeBuilder::new()
        .name(&NodeName::new(&name).context("node name")?)
        .config(&config)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()?)
}

fn qos(name: &str) -> Qos {
    services::service_spec(name).expect("contract service").qos
}

/// A publisher plus the notifier of the event service with the same name.
struct Port<P: Debug + ?Sized + IceoryxSend + 'static, H: Debug + ZeroCopySend> {
    publisher: Publisher<ipc::Service, P, H>,
    notifier: Notifier<ipc::Service>,
    seq: u64,
}

use core::fmt::Debug;

macro_rules! open {
    ($node:expr, $name:expr, $payload:ty, $header:ty) => {{
        let q = qos($name);
        let svc = $node
            .service_builder(&$name.try_into()?)
            .publish_subscribe::<$payload>()
            .user_header::<$header>()
            .max_publishers(q.max_publishers)
            .max_subscribers(q.max_subscribers)
            .max_nodes(q.max_nodes)
            .subscriber_max_buffer_size(q.subscriber_buffer)
            .subscriber_max_borrowed_samples(q.subscriber_borrowed)
            .history_size(q.history)
            .enable_safe_overflow(q.safe_overflow)
            .open_or_create()
            .map_err(|e| anyhow::anyhow!("cannot open `{}`: {e:?}", $name))?;
        let event = $node
            .service_builder(&$name.try_into()?)
            .event()
            .max_notifiers(q.max_publishers)
            .max_listeners(q.max_subscribers)
            .max_nodes(q.max_nodes)
            .open_or_create()
            .map_err(|e| anyhow::anyhow!("cannot open event `{}`: {e:?}", $name))?;
        (svc, event.notifier_builder().create().map_err(|e| anyhow::anyhow!("notifier: {e:?}"))?)
    }};
}

fn header(stamp_ns: u64, seq: u64) -> MsgHeader {
    let now = now_ns();
    MsgHeader { stamp_ns, seq, origin_ns: now, publish_ns: now }
}

impl<T: Debug + ZeroCopySend + Copy + 'static> Port<T, MsgHeader> {
    fn send(&mut self, stamp_ns: u64, value: T) -> anyhow::Result<()> {
        let mut s = self.publisher.loan_uninit()?.write_payload(value);
        *s.user_header_mut() = header(stamp_ns, self.seq);
        s.send()?;
        self.seq += 1;
        self.notifier.notify()?;
        Ok(())
    }
}

impl<T: Debug + ZeroCopySend + Copy + 'static, H: Debug + ZeroCopySend + Default> Port<[T], H> {
    fn send_slice(&mut self, h: H, n: usize, f: impl FnMut(usize) -> T) -> anyhow::Result<()> {
        let mut s = self.publisher.loan_slice_uninit(n)?.write_from_fn(f);
        *s.user_header_mut() = h;
        s.send()?;
        self.seq += 1;
        self.notifier.notify()?;
        Ok(())
    }
}

fn run(args: &Args) -> anyhow::Result<()> {
    let node = node()?;
    if args.wrong_layout {
        // A different payload type under a contract name: iceoryx2 compares type name, size and
        // alignment and refuses to open the service.
        let q = qos(ODOMETRY);
        let r = node
            .service_builder(&ODOMETRY.try_into()?)
            .publish_subscribe::<[u8; 10]>()
            .max_publishers(q.max_publishers)
            .max_subscribers(q.max_subscribers)
            .open_or_create();
        anyhow::ensure!(r.is_err(), "iceoryx2 accepted a wrong payload type on {ODOMETRY}");
        println!("REFUSED {ODOMETRY}: {:?}", r.err());
        return Ok(());
    }
    let stop = Arc::new(AtomicBool::new(false));
    signal_hook::flag::register(signal_hook::consts::SIGTERM, stop.clone())?;
    signal_hook::flag::register(signal_hook::consts::SIGINT, stop.clone())?;

    let (svc, notifier) = open!(node, ODOMETRY, OdometryInput, MsgHeader);
    let mut odo = Port {
        publisher: svc.publisher_builder().backpressure_strategy(BackpressureStrategy::DiscardData).create()?,
        notifier,
        seq: 0,
    };
    let (svc, notifier) = open!(node, BUOY_RANGES, [BuoyRange], MsgHeader);
    let mut buoys = Port {
        publisher: svc
            .publisher_builder()
            .initial_max_slice_len(8)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()?,
        notifier,
        seq: 0,
    };
    let (svc, notifier) = open!(node, CLOUD, [CloudPoint], CloudHeader);
    let mut cloud = Port {
        publisher: svc
            .publisher_builder()
            .initial_max_slice_len(args.points.max(1))
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(1)
            // A live source: a full subscriber queue drops the sample for that subscriber.
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()?,
        notifier,
        seq: 0,
    };
    let mut stereo = if args.stereo {
        let (svc, notifier) = open!(node, STEREO, [StereoObservation], MsgHeader);
        let publisher = svc
            .publisher_builder()
            .initial_max_slice_len(64)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(1)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()?;
        Some(Port { publisher, notifier, seq: 0 })
    } else {
        None
    };
    let (svc, notifier) = open!(node, END_OF_STREAM, EndOfStream, MsgHeader);
    let mut eos = Port { publisher: svc.publisher_builder().create()?, notifier, seq: 0 };

    // Give the pipeline's subscribers a moment to attach to the new publishers: a subscriber
    // attaches when its loop runs, so wake them (a notification without data) meanwhile.
    for _ in 0..40 {
        for n in [&odo.notifier, &buoys.notifier, &cloud.notifier] {
            n.notify()?;
        }
        if let Some(st) = &stereo {
            st.notifier.notify()?;
        }
        std::thread::sleep(Duration::from_millis(25));
    }
    let period = Duration::from_secs_f64(1.0 / args.rate_hz);
    let dt = 1.0 / args.rate_hz;
    let t0 = now_ns();
    let (mut good, mut bad) = ([0u64; 4], 0u64);
    for k in 0..args.frames {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        let stamp = t0 + (k as f64 * dt * 1e9) as u64;
        let input =
            OdometryInput { v_mps: 1.0, delta_theta_rad: [0.0, 0.0, 0.02], dt_s: dt, input_covariance: [0.0; 16] };
        odo.send(stamp, input)?;
        good[0] += 1;
        if k % 10 == 0 {
            let ranges = [BuoyRange {
                buoy_id: (k / 10 % 4) as u32,
                _reserved: 0,
                range_m: 20.0 + k as f64 * 0.01,
                sigma_m: 0.5,
            }];
            buoys.send_slice(header(stamp, buoys.seq), 1, |i| ranges[i])?;
            good[1] += 1;
        }
        if k % 5 == 0 {
            let h = CloudHeader { msg: header(stamp, cloud.seq), ..Default::default() };
            cloud.send_slice(h, args.points, |i| CloudPoint { x_m: i as f32 * 0.01, y_m: 1.0, z_m: 2.0 })?;
            good[2] += 1;
        }
        if let Some(st) = stereo.as_mut()
            && k % 3 == 0
        {
            st.send_slice(header(stamp, st.seq), 8, |i| observation(i, k))?;
            good[3] += 1;
            if args.hostile && k % 30 == 15 {
                let h = header(stamp + 7, st.seq);
                match (k / 30) % 4 {
                    0 => st.send_slice(h, 8, |i| StereoObservation {
                        point_cam_m: [f64::NAN, 0.0, 5.0],
                        ..observation(i, k)
                    })?,
                    1 => st.send_slice(h, 8, |i| StereoObservation {
                        point_cam_m: [0.0, 0.0, -3.0],
                        ..observation(i, k)
                    })?,
                    2 => st.send_slice(h, 8, |i| StereoObservation {
                        covariance_cam_m2: [-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                        ..observation(i, k)
                    })?,
                    _ => st.send_slice(h, 8, |i| StereoObservation {
                        covariance_cam_m2: [f64::INFINITY, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                        ..observation(i, k)
                    })?,
                }
                bad += 1;
            }
        }
        if args.hostile && k % 10 == 5 {
            match (k / 10) % 6 {
                0 => odo.send(stamp + 1, OdometryInput { v_mps: f64::NAN, dt_s: dt, ..input })?,
                1 => odo.send(stamp + 2, OdometryInput { dt_s: 0.0, ..input })?,
                2 => odo.send(stamp - 1_000_000, input)?, // a stamp going back in time
                3 => {
                    let r = [BuoyRange { buoy_id: 99, _reserved: 0, range_m: 5.0, sigma_m: 0.5 }];
                    buoys.send_slice(header(stamp + 3, buoys.seq), 1, |i| r[i])?
                }
                4 => {
                    let h = CloudHeader { msg: header(stamp + 4, cloud.seq), ..Default::default() };
                    cloud.send_slice(h, args.oversized_points, |_| CloudPoint { x_m: 1.0, y_m: 1.0, z_m: 1.0 })?
                }
                _ => {
                    let h = CloudHeader { msg: header(stamp + 5, cloud.seq), ..Default::default() };
                    cloud.send_slice(h, 10, |i| CloudPoint {
                        x_m: if i == 3 { f32::INFINITY } else { 0.0 },
                        y_m: 0.0,
                        z_m: 0.0,
                    })?
                }
            }
            bad += 1;
        }
        std::thread::sleep(period);
    }
    let sent = good.iter().sum::<u64>() + bad;
    eos.send(
        now_ns(),
        EndOfStream {
            process: name32(&std::env::var("SLAM_PIPELINE_PROCESS").unwrap_or_else(|_| "external_producer".into())),
            last_seq: odo.seq.saturating_sub(1),
            messages_sent: sent,
            status: shared_types::EOS_COMPLETE,
            // 0: the services it published are not said (every stage takes it for an upstream).
            outputs: 0,
        },
    )?;
    println!("SENT good odometry={} buoy_ranges={} clouds={} stereo={} bad={bad}", good[0], good[1], good[2], good[3]);
    // Stay up until stopped, so the pipeline can still read what we sent.
    while !stop.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(())
}

/// Landmark `i` of a valid stereo frame `k`: 2-6 m in front of the camera, 1 cm² variances.
fn observation(i: usize, k: u64) -> StereoObservation {
    let (x, y) = ((i % 4) as f64 - 1.5, (i / 4) as f64 - 0.5);
    StereoObservation {
        point_cam_m: [x, y, 4.0 + (k % 7) as f64 * 0.1 - (i % 3) as f64],
        covariance_cam_m2: [1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 4e-4],
        pixels_ul_ur_v: [0.0; 3],
        source_id: i as u64,
        descriptor: [i as u8; 32],
        flags: 1,
        _reserved: 0,
    }
}

fn main() -> std::process::ExitCode {
    match run(&Args::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("external_producer: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
