//! The PNG of `pipeline_bench latency`: end-to-end latency histograms, one panel per payload size
//! (for the shortest chain measured), one line per transport, on a logarithmic latency axis.

use std::path::Path;

use anyhow::{Context as _, anyhow};
use plotters::prelude::*;

use super::cli::size_label;
use super::report::CaseResult;

/// Histogram bins per panel.
const BINS: usize = 40;
/// Colours of the transports, in order of first appearance.
const COLORS: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
    RGBColor(127, 127, 127),
];

/// Fraction of `samples_us` in each of `BINS` equal bins of log10(µs) over `lo..hi`.
pub fn log_histogram(samples_ns: &[u64], lo: f64, hi: f64) -> Vec<(f64, f64)> {
    let mut counts = vec![0u64; BINS];
    let width = (hi - lo) / BINS as f64;
    for &s in samples_ns {
        let x = (s.max(1) as f64 / 1000.0).log10();
        let b = (((x - lo) / width).floor().max(0.0) as usize).min(BINS - 1);
        counts[b] += 1;
    }
    let n = samples_ns.len().max(1) as f64;
    counts.iter().enumerate().map(|(i, &c)| (lo + (i as f64 + 0.5) * width, c as f64 / n)).collect()
}

/// Draws the histograms into `path` (1200 × 400·rows px). Returns the number of panels drawn.
pub fn write_png(path: &Path, cases: &[CaseResult]) -> anyhow::Result<usize> {
    let Some(chain) = cases.iter().map(|c| c.chain).min() else { return Ok(0) };
    let mut sizes: Vec<usize> = cases.iter().map(|c| c.size_bytes).collect();
    sizes.sort_unstable();
    sizes.dedup();
    let mut transports: Vec<&str> = Vec::new();
    for c in cases {
        if !transports.contains(&c.transport.as_str()) {
            transports.push(&c.transport);
        }
    }
    let cols = sizes.len().min(2);
    let rows = sizes.len().div_ceil(2);
    let root = BitMapBackend::new(path, (1200, 420 * rows as u32)).into_drawing_area();
    let err = |e: DrawingAreaErrorKind<_>| anyhow!("drawing {}: {e}", path.display());
    root.fill(&WHITE).map_err(err)?;
    let font = fusion::plot::font_family();
    let panels = root.split_evenly((rows, cols));
    for (panel, &size) in panels.iter().zip(&sizes) {
        let here: Vec<&CaseResult> =
            cases.iter().filter(|c| c.size_bytes == size && c.chain == chain && !c.e2e_ns.is_empty()).collect();
        let all = here.iter().flat_map(|c| c.e2e_ns.iter()).map(|&s| (s.max(1) as f64 / 1000.0).log10());
        let (lo, hi) = all.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| (a.min(x), b.max(x)));
        if !lo.is_finite() {
            continue;
        }
        let (lo, hi) = (lo.floor(), hi.ceil().max(lo.floor() + 1.0));
        let series: Vec<(&str, Vec<(f64, f64)>)> =
            here.iter().map(|c| (c.transport.as_str(), log_histogram(&c.e2e_ns, lo, hi))).collect();
        let ymax = series.iter().flat_map(|(_, h)| h.iter().map(|p| p.1)).fold(0.0, f64::max).max(0.01) * 1.1;
        let mut builder = ChartBuilder::on(panel);
        builder.margin(12).margin_right(36);
        if let Some(f) = font {
            let what = if chain == 1 { "round trip".to_string() } else { format!("{} hops", chain + 1) };
            builder.caption(format!("{}, {chain} relay(s), end to end ({what})", size_label(size)), (f, 18));
            builder.x_label_area_size(40).y_label_area_size(56);
        }
        let mut chart = builder.build_cartesian_2d(lo..hi, 0.0..ymax).map_err(err)?;
        let mut mesh = chart.configure_mesh();
        let fmt_x = |x: &f64| {
            let us = 10f64.powf(*x);
            if us >= 1000.0 { format!("{:.0} ms", us / 1000.0) } else { format!("{us:.0} µs") }
        };
        mesh.x_label_formatter(&fmt_x).x_labels(((hi - lo) as usize + 1).clamp(2, 10));
        if let Some(f) = font {
            mesh.x_desc("latency (log scale)")
                .y_desc("fraction of messages")
                .label_style((f, 13))
                .axis_desc_style((f, 14));
        }
        mesh.draw().map_err(err)?;
        for (name, hist) in series {
            let k = transports.iter().position(|t| *t == name).unwrap_or(0) % COLORS.len();
            let style = COLORS[k].stroke_width(2);
            let anno = chart.draw_series(LineSeries::new(hist, style)).map_err(err)?;
            if font.is_some() {
                anno.label(name).legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
            }
        }
        if let Some(f) = font {
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font((f, 13))
                .draw()
                .map_err(err)?;
        }
    }
    root.present().with_context(|| format!("writing {}", path.display()))?;
    Ok(sizes.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_histogram_bins_sum_to_one_and_put_samples_in_their_decade() {
        // 10 µs and 1000 µs on a 0..4 (1 µs .. 10 ms) axis.
        let h = log_histogram(&[10_000, 10_000, 1_000_000, 1_000_000], 0.0, 4.0);
        assert_eq!(h.len(), BINS);
        let total: f64 = h.iter().map(|p| p.1).sum();
        assert!((total - 1.0).abs() < 1e-12);
        let at = |x: f64| h.iter().filter(|p| (p.0 - x).abs() < 0.1).map(|p| p.1).sum::<f64>();
        assert!((at(1.05) - 0.5).abs() < 1e-12, "{h:?}");
        assert!((at(3.05) - 0.5).abs() < 1e-12, "{h:?}");
    }
}
