//! `ros2_bench`: what the `ros2` gateway adds between a ROS 2 publisher and the pipeline, for the
//! targets of issue 33: a 1,081-beam `sensor_msgs/LaserScan` (with its `nav_msgs/Odometry`) into
//! grid SLAM, and a 300,000-point `sensor_msgs/PointCloud2` into a consumer of
//! `pipeline/sensors/cloud` (the sensor monitor).
//!
//! This process is the ROS 2 publisher (ros2-client over RustDDS, the gateway's own DDS stack, in
//! another process), the supervisor runs the gateway and the consumers. Per route it prints:
//! - **DDS**: the publisher's source timestamp → the gateway's reader received the sample (the
//!   transport, RustDDS to RustDDS over loopback);
//! - **gateway**: received → decoded and written into the loaned iceoryx2 sample and sent (what
//!   the gateway adds: its wake-up, the decode, the one copy into shared memory; RustDDS stamps
//!   a fragmented sample at its first fragment, so a cloud's reassembly is in it too);
//! - **take**: the take → sent (the decode, the one copy from the DDS buffer into the loaned
//!   sample, the send);
//! - **hop**: sent → the consumer took it (iceoryx2, from the run's latency.csv).
//!
//! A second gateway in the run publishes grid SLAM's `/map`, pose and `/tf` back on ROS 2; for
//! each it prints pipeline publish → DDS publish (the target: `/map` within 100 ms of the grid).
//!
//! All clocks are this machine's. Everything runs in a network namespace of its own (needs root):
//! DDS discovery never reaches the machine's interfaces.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use clap::Parser;
use ros2_client::{MessageTypeName, Name, NodeName, NodeOptions, QosProfile};
use ros2_interop::Message;
use ros2_interop::msgs::*;

#[derive(Parser)]
#[command(about = "Latency the ros2 gateway adds: LaserScan into grid SLAM, 300k-point PointCloud2 into the pipeline")]
struct Cli {
    /// Seconds of publishing.
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
    /// LaserScan (and Odometry) rate, Hz.
    #[arg(long, default_value_t = 40.0)]
    scan_hz: f64,
    /// Beams per scan.
    #[arg(long, default_value_t = 1081)]
    beams: usize,
    /// PointCloud2 rate, Hz (0: no clouds).
    #[arg(long, default_value_t = 2.0)]
    cloud_hz: f64,
    /// Points per cloud.
    #[arg(long, default_value_t = 300_000)]
    cloud_points: usize,
    /// Internal: already inside the benchmark's network namespace.
    #[arg(long, hide = true)]
    inside: bool,
}

fn ip(args: &[&str]) -> bool {
    Command::new("ip").args(args).stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok_and(|s| s.success())
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    if !cli.inside {
        // SAFETY: geteuid has no preconditions and cannot fail.
        if unsafe { libc::geteuid() } != 0 {
            bail!(
                "ros2_bench runs in a network namespace of its own (DDS discovery must not reach this machine's interfaces): run it as root"
            );
        }
        let ns = format!("r2bench{}", std::process::id());
        if !(ip(&["netns", "add", &ns])
            && ip(&["-n", &ns, "link", "set", "lo", "up"])
            && ip(&["-n", &ns, "link", "set", "lo", "multicast", "on"])
            && ip(&["-n", &ns, "route", "add", "224.0.0.0/4", "dev", "lo"]))
        {
            ip(&["netns", "del", &ns]);
            bail!("could not make the network namespace {ns} (`ip netns add`)");
        }
        let me = std::env::current_exe()?;
        let status = Command::new("ip")
            .args(["netns", "exec", &ns])
            .arg(me)
            .args(std::env::args().skip(1))
            .arg("--inside")
            .status();
        ip(&["netns", "del", &ns]);
        let status = status?;
        if !status.success() {
            bail!("the benchmark failed ({status})");
        }
        return Ok(());
    }
    run(&cli)
}

fn config(dir: &Path, cli: &Cli) -> String {
    let reliable = r#"qos = { reliability = "reliable", durability = "volatile", depth = 4 }"#;
    format!(
        r#"[run]
out_dir = "{out}"
iceoryx_prefix = "r2bench{pid}_"
iceoryx_root = "{out}/iox"
end = "end_of_stream"
end_of_stream_from = ["slam2d", "monitor", "ros_out"]
status_interval_s = 5.0

[processes.slam2d]
kind = "grid_slam"
[processes.slam2d.settings.filter]
particles = 30
threads = 1

[processes.monitor]
kind = "sensor_monitor"
[processes.monitor.settings]
max_cloud_points = {points}

[processes.ros_in]
kind = "ros2"
after = ["slam2d", "monitor"]
[processes.ros_in.settings]
insecure = true
end_when_idle_s = 2.0
in = [
  {{ topic = "/scan", service = "laser" }},
  {{ topic = "/odom", service = "planar_odometry" }},
  {{ topic = "/cloud", service = "cloud", {reliable} }},
]

# Grid SLAM's outputs back out on ROS 2, as config/ros2_laser.toml publishes them: the time from
# the grid (the pose) being published in the pipeline to the ROS 2 message being published.
[processes.ros_out]
kind = "ros2"
after = ["slam2d"]
[processes.ros_out.settings]
insecure = true
node_name = "slam_pipeline_out"
end_after = ["slam2d"]
linger_s = 0.2
out = [
  {{ what = "map" }},
  {{ what = "grid_slam_pose" }},
  {{ what = "tf", from = "grid_slam", odom = "planar_odometry" }},
]
"#,
        out = dir.join("out").display(),
        pid = std::process::id(),
        points = cli.cloud_points.max(1),
    )
}

fn unix_time(ns: u64) -> Time {
    Time::from_ns(ns)
}

fn now_ns() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

/// Removes what this run's iceoryx2 prefix left in /dev/shm (a run that failed and was killed).
fn clean_shm() {
    let prefix = format!("r2bench{}_", std::process::id());
    if let Ok(rd) = std::fs::read_dir("/dev/shm") {
        for e in rd.flatten() {
            if e.file_name().to_string_lossy().starts_with(&prefix) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
}

fn run(cli: &Cli) -> anyhow::Result<()> {
    let r = run_inner(cli);
    clean_shm();
    r
}

fn run_inner(cli: &Cli) -> anyhow::Result<()> {
    let dir = tempfile::Builder::new().prefix("ros2-bench-").tempdir()?;
    let cfg = dir.path().join("bench.toml");
    std::fs::write(&cfg, config(dir.path(), cli))?;
    let bin = std::env::current_exe()?.parent().context("target directory")?.to_path_buf();
    let log = std::fs::File::create(dir.path().join("supervisor.log"))?;
    let mut sup = Command::new(bin.join("supervisor"))
        .arg("--config")
        .arg(&cfg)
        .env("RUST_LOG", "warn")
        .stdout(log.try_clone()?)
        .stderr(log)
        .spawn()
        .context("starting the supervisor (build it: cargo build --release --workspace)")?;
    let peer = Peer::open(cli, &mut sup, dir.path())?;
    let (scans, clouds) = peer.publish(cli)?;
    eprintln!("published {scans} scans, {clouds} clouds; waiting for the run to end");
    let end = Instant::now() + Duration::from_secs(120);
    let status = loop {
        if let Some(s) = sup.try_wait()? {
            break s;
        }
        if Instant::now() > end {
            let _ = sup.kill();
            bail!("the run did not end");
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    if !status.success() {
        let log = std::fs::read_to_string(dir.path().join("supervisor.log")).unwrap_or_default();
        bail!("the supervisor failed ({status}):\n{log}");
    }
    if std::env::var_os("ROS2_BENCH_LOG").is_some() {
        eprintln!("{}", std::fs::read_to_string(dir.path().join("supervisor.log")).unwrap_or_default());
    }
    print_report(cli, &dir.path().join("out"))
}

/// The ROS 2 side, as a robot's drivers and RViz would be: publishers of scans, odometry and
/// clouds, subscribers of the map, the pose and the transforms (a route with no subscriber
/// publishes nothing).
struct Peer {
    scan_p: ros2_client::Publisher<LaserScan>,
    odom_p: ros2_client::Publisher<Odometry>,
    cloud_p: ros2_client::Publisher<PointCloud2<'static>>,
    _subscriptions: (
        ros2_client::Subscription<OccupancyGrid<'static>>,
        ros2_client::Subscription<PoseWithCovarianceStamped>,
        ros2_client::Subscription<TFMessage>,
    ),
    _node: ros2_client::Node,
}

impl Peer {
    /// Opens the node and waits until DDS discovery matched the gateways' readers and writers
    /// (60 s at most, or until the run ends).
    fn open(cli: &Cli, sup: &mut std::process::Child, dir: &Path) -> anyhow::Result<Self> {
        let ctx = ros2_client::Context::new().map_err(|e| anyhow::anyhow!("DDS participant: {e:?}"))?;
        let mut node = ctx
            .new_node(NodeName::new("/", "ros2_bench").map_err(|e| anyhow::anyhow!("{e:?}"))?, NodeOptions::new())
            .map_err(|e| anyhow::anyhow!("node: {e:?}"))?;
        let qos = QosProfile::publisher_default().history(ros2_client::qos::History::KeepLast { depth: 4 });
        let topic = |node: &mut ros2_client::Node, name: &str, ty: &str| {
            let (pkg, t) = ty.split_once("/msg/").unwrap_or_default();
            node.create_topic(&Name::parse(name).expect("topic name"), MessageTypeName::new(pkg, t), &qos)
                .map_err(|e| anyhow::anyhow!("topic {name}: {e:?}"))
        };
        let scan_t = topic(&mut node, "/scan", LaserScan::TYPE_NAME)?;
        let odom_t = topic(&mut node, "/odom", Odometry::TYPE_NAME)?;
        let cloud_t = topic(&mut node, "/cloud", PointCloud2::TYPE_NAME)?;
        let scan_p = node.create_publisher::<LaserScan>(&scan_t, None).map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let odom_p = node.create_publisher::<Odometry>(&odom_t, None).map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let cloud_p =
            node.create_publisher::<PointCloud2<'static>>(&cloud_t, None).map_err(|e| anyhow::anyhow!("{e:?}"))?;
        // Subscribers to the second gateway's outputs, as RViz would be: a route with no subscriber
        // publishes nothing.
        let map_t = topic(&mut node, "/map", OccupancyGrid::TYPE_NAME)?;
        let pose_t = topic(&mut node, "/slam/grid/pose", PoseWithCovarianceStamped::TYPE_NAME)?;
        let tf_t = topic(&mut node, "/tf", TFMessage::TYPE_NAME)?;
        let map_s =
            node.create_subscription::<OccupancyGrid<'static>>(&map_t, None).map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let pose_s = node
            .create_subscription::<PoseWithCovarianceStamped>(&pose_t, None)
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let tf_s = node.create_subscription::<TFMessage>(&tf_t, None).map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let t0 = Instant::now();
        // The gateways' readers and writers, as DDS discovery knows them (ros2-client's matched
        // counts need its spinner, which neither side runs).
        while node.subscription_count("/scan") == 0
            || node.subscription_count("/odom") == 0
            || (cli.cloud_hz > 0.0 && node.subscription_count("/cloud") == 0)
            || ["/map", "/slam/grid/pose", "/tf"].iter().any(|t| node.publisher_count(t) == 0)
        {
            if t0.elapsed() > Duration::from_secs(60) || sup.try_wait()?.is_some() {
                let _ = sup.kill();
                let log = std::fs::read_to_string(dir.join("supervisor.log")).unwrap_or_default();
                bail!("the gateway's readers did not match within 60 s (or the run ended); the run's log:\n{log}");
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        std::thread::sleep(Duration::from_millis(500));

        Ok(Self { scan_p, odom_p, cloud_p, _subscriptions: (map_s, pose_s, tf_s), _node: node })
    }

    /// Publishes scans with their odometry at `scan_hz` and clouds at `cloud_hz` for `seconds`.
    /// Returns how many of each.
    fn publish(&self, cli: &Cli) -> anyhow::Result<(u64, u64)> {
        let (scan_p, odom_p, cloud_p) = (&self.scan_p, &self.odom_p, &self.cloud_p);
        // A cloud of points on a 10 m sphere (x, y, z FLOAT32 and a padding float, as many drivers).
        let n = cli.cloud_points;
        let mut data = Vec::with_capacity(n * 16);
        for i in 0..n {
            let a = i as f32 * 0.001;
            for v in [10.0 * a.cos(), 10.0 * a.sin(), (i % 100) as f32 * 0.01, 0.0] {
                data.extend_from_slice(&v.to_le_bytes());
            }
        }
        let fields: Vec<PointField> = ["x", "y", "z", "intensity"]
            .iter()
            .enumerate()
            .map(|(k, f)| PointField {
                name: f.to_string(),
                offset: 4 * k as u32,
                datatype: POINT_FIELD_FLOAT32,
                count: 1,
            })
            .collect();
        let ranges: Vec<f32> = (0..cli.beams).map(|i| 2.0 + (i % 50) as f32 * 0.1).collect();
        let inc = std::f32::consts::PI * 1.5 / cli.beams as f32;

        let scan_period = Duration::from_secs_f64(1.0 / cli.scan_hz);
        let cloud_period = (cli.cloud_hz > 0.0).then(|| Duration::from_secs_f64(1.0 / cli.cloud_hz));
        let start = Instant::now();
        let (mut next_scan, mut next_cloud) = (start, start);
        let (mut scans, mut clouds, mut x) = (0u64, 0u64, 0.0f64);
        while start.elapsed().as_secs_f64() < cli.seconds {
            let now = Instant::now();
            if now >= next_scan {
                let t = now_ns();
                x += 0.01;
                let mut odom = Odometry { child_frame_id: "base_link".into(), ..Default::default() };
                odom.header = Header { stamp: unix_time(t), frame_id: "odom".into() };
                odom.pose.pose.position.x = x;
                odom_p.publish(odom).map_err(|e| anyhow::anyhow!("odometry: {e}"))?;
                let scan = LaserScan {
                    header: Header { stamp: unix_time(t), frame_id: "laser".into() },
                    angle_min: -0.75 * std::f32::consts::PI,
                    angle_max: -0.75 * std::f32::consts::PI + inc * (cli.beams - 1) as f32,
                    angle_increment: inc,
                    range_min: 0.05,
                    range_max: 30.0,
                    ranges: ranges.clone(),
                    ..Default::default()
                };
                scan_p.publish(scan).map_err(|e| anyhow::anyhow!("scan: {e}"))?;
                scans += 1;
                next_scan += scan_period;
            }
            if let Some(p) = cloud_period
                && now >= next_cloud
            {
                let cloud = PointCloud2 {
                    header: Header { stamp: unix_time(now_ns()), frame_id: "lidar".into() },
                    height: 1,
                    width: n as u32,
                    fields: fields.clone(),
                    is_bigendian: false,
                    point_step: 16,
                    row_step: 16 * n as u32,
                    data: Bytes::owned(data.clone()),
                    is_dense: true,
                };
                cloud_p.publish(cloud).map_err(|e| anyhow::anyhow!("cloud: {e}"))?;
                clouds += 1;
                next_cloud += p;
            }
            let wake = next_scan.min(if cloud_period.is_some() { next_cloud } else { next_scan });
            if let Some(d) = wake.checked_duration_since(Instant::now()) {
                std::thread::sleep(d);
            }
        }
        Ok((scans, clouds))
    }
}

/// The tables: ROS 2 → pipeline per route, pipeline → ROS 2 per topic.
fn print_report(cli: &Cli, out: &Path) -> anyhow::Result<()> {
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json"))?)?;
    let lat = std::fs::read_to_string(out.join("latency.csv"))?;
    let hop = |key: &str| -> (String, String) {
        lat.lines()
            .find(|l| l.starts_with("hops,") && l.contains(key))
            .map(|l| {
                let f: Vec<&str> = l.rsplit(',').collect();
                (f[3].to_string(), f[2].to_string())
            })
            .unwrap_or_default()
    };
    let r = &summary["ros2"]["ros_in"]["in"];
    println!("ROS 2 → pipeline through the `ros2` gateway ({} s; ms)", cli.seconds);
    println!(
        "{:<8} {:>6} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>5} {:>7}",
        "route",
        "sent",
        "DDS p50",
        "DDS p99",
        "gw p50",
        "gw p99",
        "take p50",
        "take p99",
        "hop p50",
        "hop p99",
        "lost",
        "dropped"
    );
    for (route, key, what) in [
        ("/scan", "pipeline/sensors/laser -> slam2d", format!("LaserScan {} beams", cli.beams)),
        ("/odom", "pipeline/sensors/planar_odometry -> slam2d", "Odometry".to_string()),
        ("/cloud", "pipeline/sensors/cloud -> monitor", format!("PointCloud2 {} points", cli.cloud_points)),
    ] {
        let c = &r[route];
        let l = &c["latency_ms"];
        let (h50, h99) = hop(key);
        let lost = c["counts"]["undecodable"].as_u64().unwrap_or(0)
            + c["counts"]["invalid"].as_u64().unwrap_or(0)
            + c["counts"]["lost_in_dds"].as_u64().unwrap_or(0);
        let ms = |v: &serde_json::Value| format!("{:.3}", v.as_f64().unwrap_or(f64::NAN));
        let hop = |v: &str| format!("{:.3}", v.parse::<f64>().unwrap_or(f64::NAN));
        println!(
            "{route:<8} {:>6} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>5} {:>7}   {what}",
            c["counts"]["published"],
            ms(&l["dds_transport"]["p50"]),
            ms(&l["dds_transport"]["p99"]),
            ms(&l["gateway"]["p50"]),
            ms(&l["gateway"]["p99"]),
            ms(&l["take_to_sent"]["p50"]),
            ms(&l["take_to_sent"]["p99"]),
            hop(&h50),
            hop(&h99),
            lost,
            c["counts"]["port_failed"],
        );
    }
    println!("\npipeline → ROS 2 (grid SLAM's outputs; pipeline publish → DDS publish, ms)");
    println!("{:<16} {:>9} {:>8} {:>8} {:>8} {:>6}", "topic", "published", "p50", "p99", "max", "lost");
    for (topic, c) in summary["ros2"]["ros_out"]["out"].as_object().into_iter().flatten() {
        let l = &c["latency_ms"];
        let ms = |v: &serde_json::Value| format!("{:.3}", v.as_f64().unwrap_or(f64::NAN));
        println!(
            "{topic:<16} {:>9} {:>8} {:>8} {:>8} {:>6}",
            c["published"],
            ms(&l["p50"]),
            ms(&l["p99"]),
            ms(&l["max"]),
            c["failed"].as_u64().unwrap_or(0) + c["not_recorded"].as_u64().unwrap_or(0)
        );
    }
    println!("grids grid SLAM published: {}", summary["grid_slam"]["grids_published"]);
    let p = &summary["processes"]["ros_in"];
    println!(
        "pipeline inputs the gateway could not deliver to a consumer (full queue / not yet connected): {}",
        p["undelivered"]
    );
    Ok(())
}
