//! `source = "cloud_files"` and `source = "depth_images"`: point clouds and depth images read from files.

use std::path::Path;

use nalgebra::Isometry3;

use crate::sources::*;

/// Point clouds from files (OctoMap scan.dat, optionally .bz2, with NODE poses; PLY), one cloud
/// per scan, at `rate_hz`, read when due.
pub struct CloudFileSource {
    files: Vec<std::path::PathBuf>,
    rate_hz: f64,
    repeat: u32,
    next_file: usize,
    queued: VecDeque<PosedCloud>,
    emitted: u64,
}

use std::collections::VecDeque;

/// A cloud with its world_from_sensor pose, when known.
type PosedCloud = (Option<Isometry3<f64>>, Vec<[f32; 3]>);

impl CloudFileSource {
    /// Checks that every file exists.
    pub fn new(config_dir: &Path, settings: &crate::CloudFileSettings) -> Result<Self, SourceError> {
        let files: Vec<_> = settings.files.iter().map(|f| crate::resolve(config_dir, f)).collect();
        for f in &files {
            if !f.is_file() {
                return Err(SourceError::Settings(format!("cloud file {} does not exist", f.display())));
            }
        }
        Ok(Self {
            files,
            rate_hz: settings.rate_hz,
            repeat: settings.repeat,
            next_file: 0,
            queued: VecDeque::new(),
            emitted: 0,
        })
    }

    fn load(path: &Path) -> Result<Vec<PosedCloud>, SourceError> {
        let name = path.to_string_lossy().to_lowercase();
        if name.ends_with(".ply") {
            Ok(vec![(None, datasets::read_ply(path)?)])
        } else {
            // scan.dat: the sensor is at the origin unless NODE lines give poses.
            Ok(datasets::read_scan_file(path)?.into_iter().map(|s| (Some(s.world_from_sensor()), s.points)).collect())
        }
    }
}

impl Source for CloudFileSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        while self.queued.is_empty() {
            if self.next_file >= self.files.len() * self.repeat as usize {
                return Ok(None);
            }
            let path = self.files[self.next_file % self.files.len()].clone();
            self.next_file += 1;
            self.queued.extend(Self::load(&path)?);
        }
        let (pose, points) = self.queued.pop_front().expect("not empty");
        self.emitted += 1;
        Ok(Some(Item::Cloud {
            stamp_ns: stamp_from_s(self.emitted as f64 / self.rate_hz),
            world_from_sensor: pose,
            points,
        }))
    }

    fn progress(&self) -> Option<f64> {
        Some(self.next_file as f64 / (self.files.len() * self.repeat as usize).max(1) as f64)
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        Ok(())
    }

    fn describe(&self) -> String {
        format!("{} cloud file(s) × {} at {} Hz", self.files.len(), self.repeat, self.rate_hz)
    }
}

/// Depth images back-projected to clouds in the camera optical frame ([2D3D] eq 6-8).
pub struct DepthImageSource {
    files: Vec<std::path::PathBuf>,
    settings: crate::DepthImageSettings,
    intrinsics: datasets::DepthIntrinsics,
    next: usize,
}

impl DepthImageSource {
    /// Checks the files and intrinsics.
    pub fn new(config_dir: &Path, settings: &crate::DepthImageSettings) -> Result<Self, SourceError> {
        let files: Vec<_> = settings.files.iter().map(|f| crate::resolve(config_dir, f)).collect();
        for f in &files {
            if !f.is_file() {
                return Err(SourceError::Settings(format!("depth image {} does not exist", f.display())));
            }
        }
        let intrinsics = datasets::DepthIntrinsics {
            fx: settings.fx_px,
            fy: settings.fy_px,
            cx: settings.cx_px,
            cy: settings.cy_px,
            depth_scale: settings.depth_scale,
            min_depth_m: settings.min_depth_m,
            max_depth_m: settings.max_depth_m,
        };
        intrinsics.validate()?;
        Ok(Self { files, settings: settings.clone(), intrinsics, next: 0 })
    }
}

impl Source for DepthImageSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        let Some(path) = self.files.get(self.next) else { return Ok(None) };
        self.next += 1;
        let is_png = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png"));
        let image = if is_png {
            datasets::read_depth_png(path)?
        } else {
            if self.settings.raw_width == 0 || self.settings.raw_height == 0 {
                return Err(SourceError::Settings(format!(
                    "{}: raw depth images need depth_images.raw_width and raw_height",
                    path.display()
                )));
            }
            datasets::read_depth_raw(path, self.settings.raw_width, self.settings.raw_height)?
        };
        let points = datasets::back_project(&image, &self.intrinsics, self.settings.stride)?;
        Ok(Some(Item::Cloud {
            stamp_ns: stamp_from_s(self.next as f64 / self.settings.rate_hz),
            world_from_sensor: None,
            points,
        }))
    }

    fn progress(&self) -> Option<f64> {
        Some(self.next as f64 / self.files.len().max(1) as f64)
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        Ok(())
    }

    fn describe(&self) -> String {
        format!("{} depth image(s) at {} Hz", self.files.len(), self.settings.rate_hz)
    }
}
