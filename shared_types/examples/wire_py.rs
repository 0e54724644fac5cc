//! Prints python/slam_pipeline_wire.py: `cargo run -p shared_types --example wire_py > python/slam_pipeline_wire.py`.
fn main() {
    print!("{}", shared_types::wire_format_python());
}
