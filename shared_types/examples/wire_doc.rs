//! Prints docs/WIRE_FORMAT.md: `cargo run -p shared_types --example wire_doc > docs/WIRE_FORMAT.md`.
fn main() {
    print!("{}", shared_types::wire_format_markdown());
}
