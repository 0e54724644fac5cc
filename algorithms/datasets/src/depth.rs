//! Depth images and their back-projection to points (\[2D3D\] eq 6-8, EQUATIONS §7).
//!
//! Images are 16-bit: a 16-bit grayscale PNG (as RGB-D cameras and the TUM/ICL data sets store
//! depth) or raw little-endian u16 of a given width and height, row-major. A sample is in raw
//! units, `depth_scale` of them per metre (e.g. 1000 for millimetres, 5000 for TUM); 0 means no
//! return. Back-projection: z = d/s, x = (u − cx)·z/fx, y = (v − cy)·z/fy with (u, v) the
//! pixel's column and row, giving points in the camera optical frame (x right, y down,
//! z forward), metres.

use std::fs::File;
use std::io::{BufReader, BufWriter};
use std::path::Path;

use crate::error::{DatasetError, FileErrorKind, Result};
use crate::lines::{io_error, open_buffered, read_rest};

/// A 16-bit depth image, row-major: sample (u, v) is `data()[v * width + u]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DepthImage {
    width: u32,
    height: u32,
    data: Vec<u16>,
}

impl DepthImage {
    /// An image from its samples (row-major); `data` must hold `width * height` samples.
    pub fn new(width: u32, height: u32, data: Vec<u16>) -> Result<Self, DepthError> {
        if (width as usize).checked_mul(height as usize) != Some(data.len()) {
            return Err(DepthError::BufferSize { width, height, samples: data.len() });
        }
        Ok(Self { width, height, data })
    }

    /// Width, px.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height, px.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The samples, row-major, raw units.
    pub fn data(&self) -> &[u16] {
        &self.data
    }

    /// The sample at column `u`, row `v` (raw units), `None` outside the image.
    pub fn get(&self, u: u32, v: u32) -> Option<u16> {
        if u < self.width && v < self.height {
            self.data.get(v as usize * self.width as usize + u as usize).copied()
        } else {
            None
        }
    }

    /// The samples, consuming the image.
    pub fn into_data(self) -> Vec<u16> {
        self.data
    }
}

/// Pinhole intrinsics and depth conversion of a depth camera.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DepthIntrinsics {
    /// Focal length along u (columns), px.
    pub fx: f64,
    /// Focal length along v (rows), px.
    pub fy: f64,
    /// Principal point column, px.
    pub cx: f64,
    /// Principal point row, px.
    pub cy: f64,
    /// Raw depth units per metre (s in z = d/s), e.g. 1000 for millimetres.
    pub depth_scale: f64,
    /// Depths below this are skipped, m.
    pub min_depth_m: f64,
    /// Depths above this are skipped, m (may be infinite: no limit).
    pub max_depth_m: f64,
}

impl DepthIntrinsics {
    /// Checks that focal lengths and scale are positive and finite, the principal point finite,
    /// and 0 ≤ `min_depth_m` ≤ `max_depth_m`.
    pub fn validate(&self) -> Result<(), DepthError> {
        if !(self.fx.is_finite() && self.fy.is_finite() && self.fx > 0.0 && self.fy > 0.0) {
            return Err(DepthError::FocalLength { fx: self.fx, fy: self.fy });
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(DepthError::PrincipalPoint { cx: self.cx, cy: self.cy });
        }
        if !(self.depth_scale.is_finite() && self.depth_scale > 0.0) {
            return Err(DepthError::DepthScale { depth_scale: self.depth_scale });
        }
        if !(self.min_depth_m.is_finite() && self.min_depth_m >= 0.0 && self.max_depth_m >= self.min_depth_m) {
            return Err(DepthError::DepthRange { min_depth_m: self.min_depth_m, max_depth_m: self.max_depth_m });
        }
        Ok(())
    }
}

/// Invalid parameters of an in-memory depth image or of back-projection.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DepthError {
    /// The sample buffer does not hold width × height samples.
    #[error("depth image of {width}x{height} needs width x height samples, got {samples}")]
    BufferSize {
        /// Width, px.
        width: u32,
        /// Height, px.
        height: u32,
        /// Samples given.
        samples: usize,
    },
    /// A focal length is not positive and finite.
    #[error("focal lengths must be positive and finite, got fx = {fx}, fy = {fy}")]
    FocalLength {
        /// fx, px.
        fx: f64,
        /// fy, px.
        fy: f64,
    },
    /// The principal point is not finite.
    #[error("principal point must be finite, got cx = {cx}, cy = {cy}")]
    PrincipalPoint {
        /// cx, px.
        cx: f64,
        /// cy, px.
        cy: f64,
    },
    /// The depth scale is not positive and finite.
    #[error("depth scale must be positive and finite, got {depth_scale}")]
    DepthScale {
        /// Raw units per metre.
        depth_scale: f64,
    },
    /// The depth range is not 0 ≤ min ≤ max.
    #[error("depth range must satisfy 0 <= min <= max, got [{min_depth_m}, {max_depth_m}] m")]
    DepthRange {
        /// Minimum, m.
        min_depth_m: f64,
        /// Maximum, m.
        max_depth_m: f64,
    },
    /// The stride is zero.
    #[error("stride must be at least 1")]
    ZeroStride,
}

/// Back-projects every `stride`-th pixel in both directions (columns and rows 0, k, 2k, …) to a
/// point in the camera optical frame (x right, y down, z forward), m (\[2D3D\] eq 6-8):
/// z = d/s, x = (u − cx)·z/fx, y = (v − cy)·z/fy. Zero samples and depths outside
/// [`min_depth_m`, `max_depth_m`] are skipped. Points are in row-major pixel order.
///
/// [`min_depth_m`]: DepthIntrinsics::min_depth_m
/// [`max_depth_m`]: DepthIntrinsics::max_depth_m
pub fn back_project(
    image: &DepthImage,
    intrinsics: &DepthIntrinsics,
    stride: u32,
) -> Result<Vec<[f32; 3]>, DepthError> {
    intrinsics.validate()?;
    if stride == 0 {
        return Err(DepthError::ZeroStride);
    }
    let k = intrinsics;
    let step = stride as usize;
    let width = image.width as usize;
    // (u − cx)/fx per sampled column.
    let col_factor: Vec<(usize, f64)> = (0..width).step_by(step).map(|u| (u, (u as f64 - k.cx) / k.fx)).collect();
    let mut points = Vec::new();
    for v in (0..image.height as usize).step_by(step) {
        let row_factor = (v as f64 - k.cy) / k.fy;
        let row = &image.data[v * width..(v + 1) * width];
        for &(u, cf) in &col_factor {
            let d = row[u];
            if d == 0 {
                continue;
            }
            let z = f64::from(d) / k.depth_scale;
            if z < k.min_depth_m || z > k.max_depth_m {
                continue;
            }
            points.push([(cf * z) as f32, (row_factor * z) as f32, z as f32]);
        }
    }
    Ok(points)
}

/// Reads a 16-bit grayscale PNG depth image (interlaced or not).
pub fn read_depth_png(path: impl AsRef<Path>) -> Result<DepthImage> {
    let path = path.as_ref();
    let png_error = |source| DatasetError::PngDecode { path: path.to_path_buf(), source };
    let file = File::open(path).map_err(|e| io_error(path, e))?;
    let mut decoder = png::Decoder::new(BufReader::new(file));
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder.read_info().map_err(png_error)?;
    let (color_type, bit_depth) = (reader.info().color_type, reader.info().bit_depth);
    if color_type != png::ColorType::Grayscale || bit_depth != png::BitDepth::Sixteen {
        return Err(DatasetError::File {
            path: path.to_path_buf(),
            kind: FileErrorKind::UnsupportedPng { color_type, bit_depth: bit_depth as u8 },
        });
    }
    let (width, height) = (reader.info().width, reader.info().height);
    let size_error =
        || DatasetError::File { path: path.to_path_buf(), kind: FileErrorKind::ImageSize { width, height } };
    let mut buf = vec![0u8; reader.output_buffer_size().ok_or_else(size_error)?];
    let out = reader.next_frame(&mut buf).map_err(png_error)?;
    let row_bytes = width as usize * 2;
    if out.line_size < row_bytes {
        return Err(size_error());
    }
    let mut data = Vec::with_capacity(width as usize * height as usize);
    for row in buf.chunks(out.line_size).take(height as usize) {
        data.extend(row[..row_bytes].chunks_exact(2).map(|b| u16::from_be_bytes([b[0], b[1]])));
    }
    DepthImage::new(width, height, data).map_err(|_| size_error())
}

/// Reads a raw little-endian u16 depth image of `width` × `height` (row-major; plain or `.bz2`).
/// The file must hold exactly `width * height * 2` bytes.
pub fn read_depth_raw(path: impl AsRef<Path>, width: u32, height: u32) -> Result<DepthImage> {
    let path = path.as_ref();
    let size_error =
        || DatasetError::File { path: path.to_path_buf(), kind: FileErrorKind::ImageSize { width, height } };
    let expected_bytes = u64::from(width) * u64::from(height) * 2;
    if width == 0 || height == 0 || usize::try_from(expected_bytes).is_err() {
        return Err(size_error());
    }
    let bytes = read_rest(open_buffered(path)?, path)?;
    if bytes.len() as u64 != expected_bytes {
        return Err(DatasetError::File {
            path: path.to_path_buf(),
            kind: FileErrorKind::RawSizeMismatch { width, height, expected_bytes, got_bytes: bytes.len() as u64 },
        });
    }
    let data = bytes.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])).collect();
    DepthImage::new(width, height, data).map_err(|_| size_error())
}

/// Writes a depth image as a 16-bit grayscale PNG.
pub fn write_depth_png(path: impl AsRef<Path>, image: &DepthImage) -> Result<()> {
    let path = path.as_ref();
    let png_error = |source| DatasetError::PngEncode { path: path.to_path_buf(), source };
    let file = File::create(path).map_err(|e| io_error(path, e))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), image.width, image.height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Sixteen);
    let mut writer = encoder.write_header().map_err(png_error)?;
    let bytes: Vec<u8> = image.data.iter().flat_map(|d| d.to_be_bytes()).collect();
    writer.write_image_data(&bytes).map_err(png_error)?;
    writer.finish().map_err(png_error)
}

/// Writes a depth image as raw little-endian u16, row-major.
pub fn write_depth_raw(path: impl AsRef<Path>, image: &DepthImage) -> Result<()> {
    let path = path.as_ref();
    let bytes: Vec<u8> = image.data.iter().flat_map(|d| d.to_le_bytes()).collect();
    std::fs::write(path, bytes).map_err(|e| io_error(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    const K: DepthIntrinsics = DepthIntrinsics {
        fx: 525.0,
        fy: 520.0,
        cx: 319.5,
        cy: 239.5,
        depth_scale: 1000.0,
        min_depth_m: 0.1,
        max_depth_m: 8.0,
    };

    fn plane(width: u32, height: u32, raw: u16) -> DepthImage {
        DepthImage::new(width, height, vec![raw; (width * height) as usize]).unwrap()
    }

    #[test]
    fn plane_back_projects_to_its_depth() {
        let (w, h) = (640u32, 480u32);
        let img = plane(w, h, 2500);
        let pts = back_project(&img, &K, 1).unwrap();
        assert_eq!(pts.len(), (w * h) as usize);
        assert!(pts.iter().all(|p| p[2] == 2.5));
        let z = 2.5f64;
        let expect = |u: f64, v: f64| [((u - K.cx) * z / K.fx) as f32, ((v - K.cy) * z / K.fy) as f32, z as f32];
        // Corners: first, end of first row, start of last row, last.
        assert_eq!(pts[0], expect(0.0, 0.0));
        assert_eq!(pts[(w - 1) as usize], expect(639.0, 0.0));
        assert_eq!(pts[((h - 1) * w) as usize], expect(0.0, 479.0));
        assert_eq!(pts[(w * h - 1) as usize], expect(639.0, 479.0));
        // Optical frame: top-left pixel is left (x < 0) and up (y < 0).
        assert!(pts[0][0] < 0.0 && pts[0][1] < 0.0);
        assert!((pts[0][0] as f64 - (-319.5 * 2.5 / 525.0)).abs() < 1e-6);
    }

    #[test]
    fn stride_zero_and_out_of_range_depths() {
        let mut data = vec![1000u16; 16];
        data[0] = 0; // no return
        data[1] = 50; // 0.05 m < min
        data[2] = 9000; // 9 m > max
        let img = DepthImage::new(4, 4, data).unwrap();
        assert_eq!(back_project(&img, &K, 1).unwrap().len(), 13);
        // Stride 2: pixels (0,0) (2,0) (0,2) (2,2); (0,0) is zero, (2,0) is 9 m.
        let pts = back_project(&img, &K, 2).unwrap();
        assert_eq!(pts.len(), 2);
        assert_eq!(pts[0][1], ((2.0 - K.cy) * 1.0 / K.fy) as f32);
        assert_eq!(back_project(&img, &K, 100).unwrap().len(), 0); // only (0,0), which is zero
        assert_eq!(back_project(&img, &K, 0), Err(DepthError::ZeroStride));
        let bad = DepthIntrinsics { depth_scale: 0.0, ..K };
        assert_eq!(back_project(&img, &bad, 1), Err(DepthError::DepthScale { depth_scale: 0.0 }));
        let bad = DepthIntrinsics { fx: f64::NAN, ..K };
        assert!(matches!(back_project(&img, &bad, 1), Err(DepthError::FocalLength { .. })));
        let bad = DepthIntrinsics { min_depth_m: 3.0, max_depth_m: 2.0, ..K };
        assert!(matches!(bad.validate(), Err(DepthError::DepthRange { .. })));
        let unlimited = DepthIntrinsics { max_depth_m: f64::INFINITY, min_depth_m: 0.0, ..K };
        assert_eq!(back_project(&img, &unlimited, 1).unwrap().len(), 15);
        assert!(DepthImage::new(3, 3, vec![0; 8]).is_err());
    }

    #[test]
    fn png_round_trip_and_back_projection() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("depth.png");
        let (w, h) = (64u32, 48u32);
        // A plane at 1.234 m with a ramp in one corner to check byte order (values > 255).
        let mut data = vec![1234u16; (w * h) as usize];
        data[1] = 0x1234;
        data[2] = 65535;
        let img = DepthImage::new(w, h, data).unwrap();
        write_depth_png(&path, &img).unwrap();
        let back = read_depth_png(&path).unwrap();
        assert_eq!(back, img);
        assert_eq!(back.get(1, 0), Some(0x1234));
        assert_eq!(back.get(w, 0), None);
        let k = DepthIntrinsics { cx: 31.5, cy: 23.5, max_depth_m: 2.0, ..K };
        let pts = back_project(&back, &k, 1).unwrap();
        assert_eq!(pts.len(), (w * h - 2) as usize);
        assert!(pts.iter().all(|p| p[2] == 1.234));
        let last = pts.last().unwrap();
        assert_eq!(last[0], ((63.0 - 31.5) * 1.234 / K.fx) as f32);
        assert_eq!(last[1], ((47.0 - 23.5) * 1.234 / K.fy) as f32);
    }

    #[test]
    fn png_of_the_wrong_kind_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rgb8.png");
        let mut enc = png::Encoder::new(BufWriter::new(File::create(&path).unwrap()), 2, 2);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut wr = enc.write_header().unwrap();
        wr.write_image_data(&[0; 12]).unwrap();
        wr.finish().unwrap();
        let e = read_depth_png(&path).unwrap_err();
        assert_eq!(e.to_string(), format!("{}: depth PNG must be 16-bit grayscale, got Rgb at 8 bits", path.display()));

        let junk = dir.path().join("junk.png");
        std::fs::write(&junk, b"not a png").unwrap();
        let e = read_depth_png(&junk).unwrap_err();
        assert!(matches!(e, DatasetError::PngDecode { .. }), "{e}");
        assert!(e.to_string().starts_with(&format!("{}: cannot decode PNG", junk.display())));
    }

    #[test]
    fn raw_round_trip_and_size_check() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("depth.raw");
        let img = DepthImage::new(3, 2, vec![1, 2, 3, 0x0102, 5, 65535]).unwrap();
        write_depth_raw(&path, &img).unwrap();
        assert_eq!(std::fs::read(&path).unwrap()[6..8], [0x02, 0x01]); // little-endian
        assert_eq!(read_depth_raw(&path, 3, 2).unwrap(), img);
        let e = read_depth_raw(&path, 4, 2).unwrap_err();
        assert_eq!(e.to_string(), format!("{}: raw u16 image of 4x2 needs 16 bytes, file has 12", path.display()));
        let e = read_depth_raw(&path, 0, 2).unwrap_err();
        assert_eq!(e.to_string(), format!("{}: unsupported image size 0x2", path.display()));
    }
}
