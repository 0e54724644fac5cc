//! Times decoding a 300,000-point `sensor_msgs/PointCloud2` from CDR and reading its points into
//! a preallocated buffer (what the `ros2` gateway does per cloud, without DDS and shared memory):
//! `cargo run --release -p ros2_interop --example cloud_decode`. Twice: with the same buffers every
//! time (in cache), and rotating through 16 sources and 16 destinations (115 MB: out of cache, as
//! in the gateway, where RustDDS has just written the source on another core and the destination is
//! a shared-memory sample last touched several clouds ago).

use std::time::Instant;

use ros2_interop::convert::CloudLayout;
use ros2_interop::msgs::*;

fn main() {
    let n = 300_000usize;
    let mut data = Vec::with_capacity(n * 16);
    for i in 0..n {
        for v in [i as f32, 1.0, 2.0, 0.0] {
            data.extend_from_slice(&v.to_le_bytes());
        }
    }
    let fields = ["x", "y", "z", "intensity"]
        .iter()
        .enumerate()
        .map(|(k, f)| PointField { name: f.to_string(), offset: 4 * k as u32, datatype: POINT_FIELD_FLOAT32, count: 1 })
        .collect();
    let msg = PointCloud2 {
        height: 1,
        width: n as u32,
        fields,
        point_step: 16,
        row_step: 16 * n as u32,
        data: Bytes::owned(data),
        is_dense: true,
        ..Default::default()
    };
    let bytes = ros2_interop::encode(&msg).expect("encodes");
    let mut out = vec![[0f32; 3]; n];
    let mut best = [f64::MAX; 3];
    for _ in 0..20 {
        let t0 = Instant::now();
        let m: PointCloud2<'_> = ros2_interop::decode(&bytes, PointCloud2::TYPE_NAME).expect("decodes");
        let t1 = Instant::now();
        let layout = CloudLayout::of(&m).expect("x, y, z");
        assert_eq!(layout.read_into(m.data.as_slice(), &mut out), n);
        let t2 = Instant::now();
        let finite = layout.count_finite(m.data.as_slice());
        let t3 = Instant::now();
        assert_eq!(finite, n);
        for (k, d) in [t1 - t0, t2 - t1, t3 - t2].iter().enumerate() {
            best[k] = best[k].min(d.as_secs_f64() * 1e3);
        }
    }
    println!(
        "300,000 points, best of 20 (in cache): decode {:.3} ms, read into a buffer {:.3} ms, count finite {:.3} ms",
        best[0], best[1], best[2]
    );
    let sources: Vec<Vec<u8>> = (0..16).map(|_| bytes.clone()).collect();
    let mut outs: Vec<Vec<[f32; 3]>> = (0..16).map(|_| vec![[0f32; 3]; n]).collect();
    let mut cold = vec![];
    for round in 0..64 {
        let (src, out) = (&sources[round % 16], &mut outs[(round * 7) % 16]);
        let t0 = Instant::now();
        let m: PointCloud2<'_> = ros2_interop::decode(src, PointCloud2::TYPE_NAME).expect("decodes");
        let layout = CloudLayout::of(&m).expect("x, y, z");
        assert_eq!(layout.read_into(m.data.as_slice(), out), n);
        cold.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    cold.sort_by(f64::total_cmp);
    println!(
        "out of cache (16 sources, 16 destinations, 64 rounds): decode + read p50 {:.3} ms, p90 {:.3} ms",
        cold[cold.len() / 2],
        cold[cold.len() * 9 / 10]
    );
}
