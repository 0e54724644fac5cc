//! Back-pressure probe: `--role sub` counts messages (slowly), `--role pub` sends N with WaitWhenFull.
use std::time::{Duration, Instant};

use pipeline_runtime::{Delivery, Flow, IoxScope, Runtime, RuntimeOptions};
use shared_types::services::Qos;
use shared_types::{MsgHeader, OdometryInput};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let role = args[1].as_str();
    let n: u64 = args[2].parse().unwrap();
    let scope = IoxScope { prefix: "bpprobe_".into(), root: "/tmp/bpprobe".into(), base_config: None };
    let mut rt =
        Runtime::new(&format!("bp-{role}"), &scope, RuntimeOptions { publish_control: false, ..Default::default() })
            .unwrap();
    let qos = Qos::sensor(4, 16, 0);
    if role == "sub" {
        let input = rt.input_with_qos::<OdometryInput, MsgHeader>("test/bp", &qos).unwrap();
        let mut got = 0u64;
        let mut gaps = 0u64;
        let mut last: Option<u64> = None;
        let end = Instant::now() + Duration::from_secs(20);
        rt.run(&mut (), Some(Duration::from_millis(100)), |_, _, _| {
            while let Some(s) = input.receive()? {
                let seq = s.user_header().seq;
                if let Some(l) = last
                    && seq != l + 1
                {
                    gaps += seq - l - 1;
                }
                last = Some(seq);
                got += 1;
                std::thread::sleep(Duration::from_micros(200));
            }
            Ok::<_, anyhow::Error>(if got >= n || Instant::now() > end { Flow::Stop } else { Flow::Continue })
        })
        .unwrap();
        println!("sub: got {got}, gaps {gaps}");
    } else {
        let mut out = rt
            .output_with_qos::<OdometryInput, MsgHeader>(
                "test/bp",
                &qos,
                Delivery::WaitWhenFull { max_wait: Some(Duration::from_secs(2)) },
            )
            .unwrap();
        let mut zero = 0;
        for i in 0..n {
            let d =
                out.send_value(MsgHeader { stamp_ns: i + 1, ..Default::default() }, OdometryInput::default()).unwrap();
            if d == 0 {
                zero += 1;
            }
        }
        println!("pub: sent {n}, zero-delivery {zero}");
        std::thread::sleep(Duration::from_secs(3));
    }
}
