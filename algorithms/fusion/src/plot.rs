//! A top-view PNG of trajectories (x right, y up, metres) with equal axis scales, a grid, axis labels,
//! a title and a legend.
//!
//! Text needs a TrueType font: plotters' `ab_glyph` backend loads no system fonts by itself, so one is
//! looked for at run time in a few common places (bounded search) and registered once. Without a
//! font everything but the text is drawn and [`PlotReport::text`] is `false`: a missing font never
//! makes the plot fail.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;

use crate::FusionError;

/// One trajectory to draw.
#[derive(Debug, Clone, Copy)]
pub struct Series<'a> {
    /// Legend entry; an empty label gives no legend entry.
    pub label: &'a str,
    /// Line colour, RGB.
    pub color: (u8, u8, u8),
    /// (x, y) in metres, world frame (top view: x right, y up). Non-finite points are skipped and
    /// break the line.
    pub points: &'a [(f64, f64)],
    /// Dashed/thin style for references such as the ground truth.
    pub thin: bool,
}

/// What was drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlotReport {
    /// Labels, title and legend were drawn (a font was found and the image is large enough).
    pub text: bool,
    /// Finite points drawn, over all series.
    pub points: usize,
}

/// Largest accepted image side, px (bounds the memory of the bitmap).
pub const MAX_SIDE_PX: u32 = 8192;

/// Name under which the found font is registered with plotters (private, so nothing else clashes).
const FONT_FAMILY: &str = "fusion-plot-sans";
/// Half the side of the extent drawn when there is no finite point, m.
const DEFAULT_HALF_EXTENT_M: f64 = 5.0;
/// Padding on each side of the data bounding box, as a fraction of its size.
const PAD_FRACTION: f64 = 0.05;
/// Smallest extent drawn on either axis, m (a single point or a straight line still gets an area).
const MIN_SPAN_M: f64 = 1.0;
/// Smallest extent relative to the coordinates' magnitude (keeps the grid computable far from 0).
const MIN_RELATIVE_SPAN: f64 = 1e-6;
/// Text is drawn only on images at least this large, px.
const TEXT_MIN_SIZE_PX: (u32, u32) = (200, 160);

/// Writes a top-view PNG (`width_px`×`height_px`) of the series with equal axis scales (1 m in x =
/// 1 m in y), a grid, axis labels in metres, a title and a legend.
///
/// Empty series, and the non-finite points of the others, are skipped; with nothing to draw the image
/// still shows an empty grid over a default extent. Text is left out (and [`PlotReport::text`] is
/// `false`) when no font is found or the image is smaller than 200×160 px.
///
/// # Errors
/// [`FusionError::Io`] if the path does not end in `.png`, a side is 0 or above [`MAX_SIDE_PX`], or
/// the file cannot be written; [`FusionError::NonFinite`] if the coordinates are too large for their
/// extent to be finite.
pub fn plot_top_view(
    path: &Path,
    title: &str,
    series: &[Series],
    width_px: u32,
    height_px: u32,
) -> Result<PlotReport, FusionError> {
    let io_err = |message: String| FusionError::Io { path: path.display().to_string(), message };
    let is_png = path.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if !is_png {
        return Err(io_err("the file name must end in .png".to_owned()));
    }
    if !(1..=MAX_SIDE_PX).contains(&width_px) || !(1..=MAX_SIDE_PX).contains(&height_px) {
        return Err(io_err(format!("image size {width_px}×{height_px} px outside 1..={MAX_SIDE_PX} px per side")));
    }
    let large_enough = width_px >= TEXT_MIN_SIZE_PX.0 && height_px >= TEXT_MIN_SIZE_PX.1;
    let font = if large_enough { font_family() } else { None };
    let render = |font: Option<&str>| {
        let root = BitMapBackend::new(path, (width_px, height_px)).into_drawing_area();
        let report = draw_top_view(&root, title, series, font)?;
        root.present().map_err(|e| FusionError::Io { path: path.display().to_string(), message: e.to_string() })?;
        Ok(report)
    };
    match render(font) {
        // Text rendering should not fail, but if it does, a plot without text is still worth having.
        Err(_) if font.is_some() => render(None),
        result => result,
    }
}

/// Draws the plot on `root`; `font` is the registered family to write text with, `None` for no text
/// at all (no text-drawing call is then made, so an unregistered font cannot fail it).
fn draw_top_view<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    series: &[Series],
    font: Option<&str>,
) -> Result<PlotReport, FusionError> {
    let draw_err = |e: DrawingAreaErrorKind<DB::ErrorType>| FusionError::Io {
        path: "<plot>".to_owned(),
        message: format!("drawing failed: {e}"),
    };
    root.fill(&WHITE).map_err(draw_err)?;

    let (width_px, height_px) = root.dim_in_pixel();
    let area = match font {
        Some(family) if !title.is_empty() => root.titled(title, (family, 22)).map_err(draw_err)?,
        _ => root.clone(),
    };
    let margin = if width_px >= 40 && height_px >= 40 { 10 } else { 0 };
    let mut builder = ChartBuilder::on(&area);
    builder.margin(margin);
    if font.is_some() {
        builder.x_label_area_size(42).y_label_area_size(72);
    }

    // The plotting area's size is only known from a built chart; building draws nothing without a caption.
    let (plot_w, plot_h) =
        builder.build_cartesian_2d(0f64..1f64, 0f64..1f64).map_err(draw_err)?.plotting_area().dim_in_pixel();

    let runs: Vec<Vec<Vec<(f64, f64)>>> = series.iter().map(|s| finite_runs(s.points)).collect();
    let all: Vec<(f64, f64)> = runs.iter().flatten().flatten().copied().collect();
    // plotters maps a range onto (size - 1) pixels.
    let (x0, x1, y0, y1) = equal_aspect_extent(&all, plot_w.saturating_sub(1).max(1), plot_h.saturating_sub(1).max(1));
    if ![x0, x1, y0, y1].iter().all(|v| v.is_finite()) {
        return Err(FusionError::NonFinite("plot extent (coordinates too large)"));
    }

    let mut chart = builder.build_cartesian_2d(x0..x1, y0..y1).map_err(draw_err)?;
    let x_labels = (plot_w / 90).clamp(2, 12) as usize;
    let y_labels = (plot_h / 60).clamp(2, 12) as usize;
    let x_decimals = label_decimals((x1 - x0) / x_labels as f64);
    let y_decimals = label_decimals((y1 - y0) / y_labels as f64);
    let x_fmt = move |v: &f64| format_metres(*v, x_decimals);
    let y_fmt = move |v: &f64| format_metres(*v, y_decimals);
    let mut mesh = chart.configure_mesh();
    mesh.x_labels(x_labels)
        .y_labels(y_labels)
        .bold_line_style(RGBColor(200, 200, 200))
        .light_line_style(RGBColor(236, 236, 236))
        .x_label_formatter(&x_fmt)
        .y_label_formatter(&y_fmt);
    if let Some(family) = font {
        mesh.x_desc("x [m]").y_desc("y [m]").label_style((family, 14)).axis_desc_style((family, 16));
    }
    mesh.draw().map_err(draw_err)?;
    if font.is_none() {
        // Without label areas there are no axes: frame the plotting area instead.
        chart.plotting_area().draw(&Rectangle::new([(x0, y0), (x1, y1)], BLACK.stroke_width(1))).map_err(draw_err)?;
    }

    let mut points = 0;
    let mut labelled = false;
    for (s, runs) in series.iter().zip(&runs) {
        let color = RGBColor(s.color.0, s.color.1, s.color.2);
        let style = if s.thin { color.stroke_width(1) } else { color.stroke_width(2) };
        let mut first = true;
        for run in runs {
            points += run.len();
            let anno = if run.len() == 1 {
                chart.draw_series(std::iter::once(Circle::new(run[0], 2, color.filled())))
            } else if s.thin {
                chart.draw_series(DashedLineSeries::new(run.iter().copied(), 8, 5, style))
            } else {
                // plotters fills a wide polyline as one polygon, which comes out hollow or broken where the
                // path curves or crosses itself; a polygon per segment fills correctly.
                chart.draw_series(run.windows(2).map(|seg| PathElement::new(seg.to_vec(), style)))
            }
            .map_err(draw_err)?;
            if first && font.is_some() && !s.label.is_empty() {
                let anno = anno.label(s.label);
                if s.thin {
                    anno.legend(move |(x, y)| DashedPathElement::new(vec![(x, y), (x + 20, y)], 5, 3, style));
                } else {
                    anno.legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
                }
                labelled = true;
            }
            first = false;
        }
    }

    if let (Some(family), true) = (font, labelled) {
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font((family, 14))
            .draw()
            .map_err(draw_err)?;
    }
    Ok(PlotReport { text: font.is_some(), points })
}

/// The maximal runs of consecutive finite points: a non-finite point breaks the line.
fn finite_runs(points: &[(f64, f64)]) -> Vec<Vec<(f64, f64)>> {
    points
        .split(|(x, y)| !(x.is_finite() && y.is_finite()))
        .filter(|run| !run.is_empty())
        .map(<[(f64, f64)]>::to_vec)
        .collect()
}

/// Decimals for tick labels `step` metres apart.
fn label_decimals(step: f64) -> usize {
    if step.is_finite() && step > 0.0 && step < 1.0 { (-step.log10().floor()).clamp(0.0, 6.0) as usize } else { 0 }
}

/// A tick label: `v` with `decimals` decimals, without a "-0".
fn format_metres(v: f64, decimals: usize) -> String {
    let text = format!("{v:.decimals$}");
    if text.starts_with('-') && text[1..].chars().all(|c| c == '0' || c == '.') { text[1..].to_owned() } else { text }
}

/// The extent `(x0, x1, y0, y1)`, m, drawn for `points` on a plotting area spanning `width_px` ×
/// `height_px` pixels: the bounding box of the finite points (a default 10 m square around the origin
/// if there is none), padded by 5 % of its size on each side, at least 1 m (and 1e-6 of the
/// coordinates' magnitude) wide on each axis, then widened on the shorter side, about the same
/// centre, so that a metre spans as many pixels in x as in y. The result may be non-finite if the
/// coordinates are near `f64::MAX`.
fn equal_aspect_extent(points: &[(f64, f64)], width_px: u32, height_px: u32) -> (f64, f64, f64, f64) {
    let bbox = points.iter().filter(|(x, y)| x.is_finite() && y.is_finite()).fold(None, |bb, &(x, y)| match bb {
        None => Some((x, x, y, y)),
        Some((x0, x1, y0, y1)) => Some((f64::min(x0, x), f64::max(x1, x), f64::min(y0, y), f64::max(y1, y))),
    });
    let d = DEFAULT_HALF_EXTENT_M;
    let (x0, x1, y0, y1) = bbox.unwrap_or((-d, d, -d, d));
    let (cx, cy) = (x0 / 2.0 + x1 / 2.0, y0 / 2.0 + y1 / 2.0);
    let magnitude = x0.abs().max(x1.abs()).max(y0.abs()).max(y1.abs());
    let floor = MIN_SPAN_M.max(MIN_RELATIVE_SPAN * magnitude);
    let span_x = ((x1 - x0) * (1.0 + 2.0 * PAD_FRACTION)).max(floor);
    let span_y = ((y1 - y0) * (1.0 + 2.0 * PAD_FRACTION)).max(floor);
    let (w, h) = (f64::from(width_px.max(1)), f64::from(height_px.max(1)));
    let metres_per_px = (span_x / w).max(span_y / h);
    let (half_x, half_y) = (metres_per_px * w / 2.0, metres_per_px * h / 2.0);
    (cx - half_x, cx + half_x, cy - half_y, cy + half_y)
}

/// The registered font family, found and registered on first use; `None` if no usable font exists.
/// Other plots of the project (the latency benchmark's histogram) write their text with it too.
pub fn font_family() -> Option<&'static str> {
    static FONT: OnceLock<bool> = OnceLock::new();
    let registered = *FONT
        .get_or_init(|| font_candidates().into_iter().take(MAX_FONT_ATTEMPTS).any(|path| register_font_file(&path)));
    registered.then_some(FONT_FAMILY)
}

/// Most font files tried before giving up.
const MAX_FONT_ATTEMPTS: usize = 6;
/// Largest font file read, bytes.
const MAX_FONT_BYTES: u64 = 32 << 20;
/// Most directory entries looked at while searching the font directories.
const MAX_FONT_DIR_ENTRIES: usize = 5000;
/// Deepest directory level searched under a font directory.
const MAX_FONT_DIR_DEPTH: usize = 5;

/// Well-known regular sans-serif fonts, tried first.
const KNOWN_FONTS: &[&str] = &[
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu-sans-fonts/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation-sans/LiberationSans-Regular.ttf",
    "/usr/share/fonts/truetype/noto/NotoSans-Regular.ttf",
    "/usr/share/fonts/truetype/freefont/FreeSans.ttf",
    "/System/Library/Fonts/Supplemental/Arial.ttf",
    "/Library/Fonts/Arial.ttf",
    "C:\\Windows\\Fonts\\arial.ttf",
];

/// Directories searched (bounded) when none of [`KNOWN_FONTS`] exists.
const FONT_DIRS: &[&str] = &["/usr/share/fonts", "/usr/local/share/fonts"];

/// Font files to try, best first: the known ones that exist, then `*.ttf` under [`FONT_DIRS`], regular
/// sans-serif faces first.
fn font_candidates() -> Vec<PathBuf> {
    let mut found: Vec<PathBuf> = KNOWN_FONTS.iter().map(PathBuf::from).filter(|p| p.is_file()).collect();
    if !found.is_empty() {
        return found;
    }
    let mut budget = MAX_FONT_DIR_ENTRIES;
    for dir in FONT_DIRS {
        collect_ttf(Path::new(dir), MAX_FONT_DIR_DEPTH, &mut budget, &mut found);
    }
    found.sort_by_key(|p| {
        let name = p.file_name().map(|n| n.to_string_lossy().to_lowercase()).unwrap_or_default();
        let styled =
            ["bold", "italic", "oblique", "light", "condensed", "mono", "math"].iter().any(|s| name.contains(s));
        (!name.contains("sans"), styled, name)
    });
    found
}

/// Appends the `*.ttf` files under `dir` (sorted, depth-first, at most `depth` levels, spending at most
/// `budget` directory entries) to `out`.
fn collect_ttf(dir: &Path, depth: usize, budget: &mut usize, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    let mut paths = Vec::new();
    for entry in entries.flatten() {
        if *budget == 0 {
            break;
        }
        *budget -= 1;
        paths.push(entry.path());
    }
    paths.sort();
    for path in paths {
        let Ok(meta) = std::fs::metadata(&path) else { continue };
        if meta.is_dir() {
            if depth > 1 {
                collect_ttf(&path, depth - 1, budget, out);
            }
        } else if path.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("ttf")) {
            out.push(path);
        }
    }
}

/// Reads a font file and registers it as [`FONT_FAMILY`]; `false` if it is unreadable, too large or
/// not a font. The bytes are leaked on purpose: plotters needs them `'static`, and this runs at most
/// [`MAX_FONT_ATTEMPTS`] times per process.
fn register_font_file(path: &Path) -> bool {
    let Ok(meta) = std::fs::metadata(path) else { return false };
    if meta.len() > MAX_FONT_BYTES {
        return false;
    }
    let Ok(bytes) = std::fs::read(path) else { return false };
    // TrueType, OpenType (CFF) or Apple TrueType signature; anything else is not worth leaking.
    if !matches!(bytes.get(..4), Some([0, 1, 0, 0] | b"OTTO" | b"true")) {
        return false;
    }
    let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
    plotters::style::register_font(FONT_FAMILY, FontStyle::Normal, bytes).is_ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unique temporary PNG path, removed on drop.
    struct TempPng(PathBuf);
    impl TempPng {
        fn new(tag: &str) -> Self {
            use std::sync::atomic::{AtomicUsize, Ordering};
            static N: AtomicUsize = AtomicUsize::new(0);
            let n = N.fetch_add(1, Ordering::Relaxed);
            Self(std::env::temp_dir().join(format!("fusion-plot-{}-{tag}-{n}.png", std::process::id())))
        }
    }
    impl Drop for TempPng {
        fn drop(&mut self) {
            let _ = std::fs::remove_file(&self.0);
        }
    }

    /// The (width, height) of a PNG file, from its signature and IHDR chunk.
    fn png_size(path: &Path) -> (u32, u32) {
        let bytes = std::fs::read(path).expect("PNG written");
        assert!(bytes.len() > 24, "PNG too short");
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "PNG signature");
        assert_eq!(&bytes[12..16], b"IHDR", "first chunk is IHDR");
        let be = |i: usize| u32::from_be_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
        (be(16), be(20))
    }

    fn circle(cx: f64, cy: f64, r: f64, n: usize) -> Vec<(f64, f64)> {
        (0..=n)
            .map(|i| {
                let a = std::f64::consts::TAU * i as f64 / n as f64;
                (cx + r * a.cos(), cy + r * a.sin())
            })
            .collect()
    }

    #[test]
    fn plot_writes_png_of_requested_size() {
        let estimate = circle(3.0, -2.0, 20.0, 200);
        let truth: Vec<_> = estimate.iter().map(|(x, y)| (x + 0.5, y - 0.3)).collect();
        let series = [
            Series { label: "ground truth", color: (0, 0, 0), points: &truth, thin: true },
            Series { label: "fused", color: (220, 30, 30), points: &estimate, thin: false },
        ];
        let file = TempPng::new("basic");
        let report = plot_top_view(&file.0, "Top view", &series, 800, 600).expect("plot");
        println!("text drawn: {}", report.text);
        assert_eq!(report.points, 402);
        assert_eq!(png_size(&file.0), (800, 600));
    }

    #[test]
    fn plot_with_no_series_writes_valid_png() {
        let file = TempPng::new("empty");
        let report = plot_top_view(&file.0, "Nothing", &[], 640, 480).expect("plot");
        println!("text drawn: {}", report.text);
        assert_eq!(report.points, 0);
        assert_eq!(png_size(&file.0), (640, 480));
        // Empty series are skipped too.
        let series = [Series { label: "empty", color: (0, 0, 255), points: &[], thin: false }];
        let report = plot_top_view(&file.0, "", &series, 300, 200).expect("plot");
        assert_eq!(report.points, 0);
        assert_eq!(png_size(&file.0), (300, 200));
    }

    #[test]
    fn plot_skips_nan_points() {
        let points = [
            (0.0, 0.0),
            (f64::NAN, 1.0),
            (1.0, 1.0),
            (2.0, f64::NAN),
            (2.0, 0.5),
            (3.0, 0.0),
            (f64::INFINITY, 0.0),
            (4.0, 2.0),
        ];
        let all_nan = [(f64::NAN, f64::NAN); 3];
        let series = [
            Series { label: "with gaps", color: (0, 128, 0), points: &points, thin: false },
            Series { label: "all NaN", color: (0, 0, 255), points: &all_nan, thin: true },
        ];
        let file = TempPng::new("nan");
        let report = plot_top_view(&file.0, "NaN", &series, 400, 300).expect("plot");
        println!("text drawn: {}", report.text);
        assert_eq!(report.points, 5);
        assert_eq!(png_size(&file.0), (400, 300));
    }

    #[test]
    fn plot_rejects_bad_arguments_without_panicking() {
        let file = TempPng::new("bad");
        let pts = [(0.0, 0.0), (1.0, 1.0)];
        let series = [Series { label: "a", color: (1, 2, 3), points: &pts, thin: false }];
        for (w, h) in [(0, 100), (100, 0), (MAX_SIDE_PX + 1, 10)] {
            assert!(matches!(plot_top_view(&file.0, "t", &series, w, h), Err(FusionError::Io { .. })));
        }
        let not_png = file.0.with_extension("jpg");
        assert!(matches!(plot_top_view(&not_png, "t", &series, 100, 100), Err(FusionError::Io { .. })));
        let missing_dir = std::env::temp_dir().join("fusion-plot-no-such-dir").join("x.png");
        assert!(matches!(plot_top_view(&missing_dir, "t", &series, 100, 100), Err(FusionError::Io { .. })));
        let huge = [(-f64::MAX, 0.0), (f64::MAX, 0.0)];
        let series = [Series { label: "huge", color: (1, 2, 3), points: &huge, thin: false }];
        assert!(matches!(plot_top_view(&file.0, "t", &series, 100, 100), Err(FusionError::NonFinite(_))));
        // Tiny images and far-away coordinates still work.
        let far = [(1e12, 1e12), (1e12 + 0.5, 1e12)];
        let series = [Series { label: "far", color: (1, 2, 3), points: &far, thin: true }];
        for (w, h) in [(1, 1), (2, 3), (50, 30), (199, 500)] {
            let report = plot_top_view(&file.0, "t", &series, w, h).expect("plot");
            assert!(!report.text);
            assert_eq!(png_size(&file.0), (w, h));
        }
    }

    #[test]
    fn equal_aspect_extent_has_equal_scales_and_contains_padded_data() {
        let pts = [(0.0, 0.0), (10.0, 2.0), (f64::NAN, 100.0), (4.0, -1.0)];
        let (x0, x1, y0, y1) = equal_aspect_extent(&pts, 400, 400);
        // x is the longer side: padded by 5 % each side; y widened about its centre.
        assert!((x0 + 0.5).abs() < 1e-12 && (x1 - 10.5).abs() < 1e-12, "{x0} {x1}");
        assert!(((y0 + y1) / 2.0 - 0.5).abs() < 1e-12);
        assert!(((x1 - x0) / 400.0 - (y1 - y0) / 400.0).abs() < 1e-12);

        // Wide image, tall data: y padded, x widened.
        let pts = [(0.0, 0.0), (1.0, 20.0)];
        let (x0, x1, y0, y1) = equal_aspect_extent(&pts, 800, 200);
        assert!((y0 + 1.0).abs() < 1e-12 && (y1 - 21.0).abs() < 1e-12, "{y0} {y1}");
        assert!(((x1 - x0) / 800.0 - (y1 - y0) / 200.0).abs() < 1e-12);
        assert!(((x0 + x1) / 2.0 - 0.5).abs() < 1e-12);

        // No finite point: the default extent; a single point: at least 1 m.
        let (x0, x1, y0, y1) = equal_aspect_extent(&[(f64::NAN, 0.0)], 100, 100);
        assert_eq!((x0, x1, y0, y1), (-5.5, 5.5, -5.5, 5.5));
        let (x0, x1, y0, y1) = equal_aspect_extent(&[(2.0, 3.0)], 200, 100);
        assert_eq!((x0, x1, y0, y1), (1.0, 3.0, 2.5, 3.5));
    }

    /// The pixels of one colour in an RGB buffer: their bounding box (x0, x1, y0, y1).
    fn colour_bbox(buf: &[u8], width: u32, rgb: [u8; 3]) -> Option<(u32, u32, u32, u32)> {
        buf.chunks_exact(3).enumerate().filter(|(_, p)| *p == rgb).fold(None, |bb, (i, _)| {
            let (x, y) = (i as u32 % width, i as u32 / width);
            Some(match bb {
                None => (x, x, y, y),
                Some((x0, x1, y0, y1)) => (x0.min(x), x1.max(x), y0.min(y), y1.max(y)),
            })
        })
    }

    #[test]
    fn drawn_circle_is_round_without_text() {
        // No font: no text-drawing call may be made (plotters' default family is never registered).
        let ring = circle(100.0, 50.0, 10.0, 360);
        let series = [Series { label: "ring", color: (255, 0, 0), points: &ring, thin: false }];
        for (w, h) in [(400u32, 200u32), (200, 400)] {
            let mut buf = vec![0u8; (w * h * 3) as usize];
            {
                let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
                let report = draw_top_view(&root, "ignored", &series, None).expect("draw");
                assert_eq!(report, PlotReport { text: false, points: 361 });
                root.present().expect("present");
            }
            let (x0, x1, y0, y1) = colour_bbox(&buf, w, [255, 0, 0]).expect("ring drawn");
            let (dx, dy) = (i64::from(x1 - x0), i64::from(y1 - y0));
            assert!((dx - dy).abs() <= 2, "{w}×{h}: ring {dx}×{dy} px");
            assert!(dx > 50, "ring fills the plot: {dx} px");
        }
    }

    #[test]
    fn drawn_circle_is_round_with_text() {
        let Some(family) = font_family() else {
            println!("text drawn: false (no font found)");
            return;
        };
        println!("text drawn: true");
        let ring = circle(-3.0, 7.0, 2.0, 360);
        let line = [(-6.0, 4.0), (0.0, 4.5)];
        let series = [
            // No label, so the only red pixels are the ring's (the legend's sample is blue).
            Series { label: "", color: (255, 0, 0), points: &ring, thin: false },
            Series { label: "line", color: (0, 0, 255), points: &line, thin: true },
        ];
        let (w, h) = (500u32, 300u32);
        let mut buf = vec![0u8; (w * h * 3) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
            let report = draw_top_view(&root, "Ring", &series, Some(family)).expect("draw");
            assert_eq!(report, PlotReport { text: true, points: 363 });
            root.present().expect("present");
        }
        let (x0, x1, y0, y1) = colour_bbox(&buf, w, [255, 0, 0]).expect("ring drawn");
        let (dx, dy) = (i64::from(x1 - x0), i64::from(y1 - y0));
        assert!((dx - dy).abs() <= 2, "ring {dx}×{dy} px");
        assert!(dy > 50, "ring fills the plot: {dy} px");
        assert!(colour_bbox(&buf, w, [0, 0, 255]).is_some(), "line drawn");
    }

    #[test]
    fn tick_labels_are_tidy() {
        assert_eq!(label_decimals(5.0), 0);
        assert_eq!(label_decimals(0.2), 1);
        assert_eq!(label_decimals(0.05), 2);
        assert_eq!(format_metres(-0.0001, 1), "0.0");
        assert_eq!(format_metres(-1.26, 1), "-1.3");
        assert_eq!(format_metres(3.0, 0), "3");
    }
}
