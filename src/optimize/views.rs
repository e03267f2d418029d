//! Synthetic studies look at the medium from many sides: cameras on a Fibonacci spiral over a band
//! of elevations, all at one distance from the medium's centre and looking at it. The spiral gives
//! every camera about the same share of the band's area (equal steps in sin(elevation), azimuths a
//! golden angle apart), so no side is seen twice as often as another.

use anyhow::{bail, Result};
use glam::Vec3;

use crate::render::camera::Camera;

/// `[views.orbit]` of a run file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Orbit {
    pub count: u32,
    /// Lowest and highest elevation above the xz plane, in degrees (y is up).
    pub elevation_deg: (f32, f32),
    /// From the centre, in world units.
    pub distance: f32,
    pub fov_deg: f32,
    pub width: u32,
    pub height: u32,
    /// Turns the spiral about +y (e.g. held-out views between the training views).
    pub azimuth_offset_deg: f32,
}

/// Elevations this close to the poles would make +y (the cameras' up) parallel to the view.
const MAX_ELEVATION_DEG: f32 = 89.0;

impl Orbit {
    /// The cameras, looking at `centre`.
    pub fn cameras(&self, centre: Vec3) -> Result<Vec<Camera>> {
        let (lo, hi) = self.elevation_deg;
        if self.count == 0 {
            bail!("views.orbit.count must be at least 1");
        }
        if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
            bail!(
                "views.orbit.elevation_deg must be [low, high] with low ≤ high (got [{lo}, {hi}])"
            );
        }
        if lo.abs().max(hi.abs()) > MAX_ELEVATION_DEG {
            bail!("views.orbit.elevation_deg must lie within ±{MAX_ELEVATION_DEG}° (got [{lo}, {hi}]): the cameras' up is +y");
        }
        if !(self.distance > 0.0 && self.distance.is_finite()) {
            bail!(
                "views.orbit.distance must be a positive number (got {})",
                self.distance
            );
        }
        let golden_angle = std::f32::consts::PI * (3.0 - 5f32.sqrt());
        let (s_lo, s_hi) = (lo.to_radians().sin(), hi.to_radians().sin());
        Ok((0..self.count)
            .map(|i| {
                // Midpoints of `count` equal steps in sin(elevation): equal areas of the band.
                let s = s_lo + (s_hi - s_lo) * (i as f32 + 0.5) / self.count as f32;
                let (elevation, azimuth) = (
                    s.asin(),
                    i as f32 * golden_angle + self.azimuth_offset_deg.to_radians(),
                );
                let offset = Vec3::new(
                    elevation.cos() * azimuth.sin(),
                    elevation.sin(),
                    elevation.cos() * azimuth.cos(),
                );
                Camera::new(
                    centre + self.distance * offset,
                    centre,
                    Vec3::Y,
                    self.fov_deg,
                    self.width,
                    self.height,
                )
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cameras_circle_the_centre_evenly_within_the_band() {
        let orbit = Orbit {
            count: 16,
            elevation_deg: (-30.0, 80.0),
            distance: 50.0,
            fov_deg: 30.0,
            width: 8,
            height: 8,
            azimuth_offset_deg: 0.0,
        };
        let centre = Vec3::new(1.0, -2.0, 3.0);
        let cameras = orbit.cameras(centre).unwrap();
        assert_eq!(cameras.len(), 16);
        let offsets: Vec<Vec3> = cameras
            .iter()
            .map(|c| (c.position - centre) / 50.0)
            .collect();
        for (c, o) in cameras.iter().zip(&offsets) {
            assert!((o.length() - 1.0).abs() < 1e-5);
            let elevation = o.y.asin().to_degrees();
            assert!((-30.0..=80.0).contains(&elevation), "{elevation}");
            // The image centre looks at the medium's centre.
            assert!((c.direction(4.0, 4.0) + *o).length() < 1e-4);
        }
        // Spread: the band spans the elevations asked for, and no two cameras crowd each other
        // (16 cameras on this band's 4π·(sin 80° + sin 30°)/2 sr are ~0.58 rad apart on average).
        let elevations: Vec<f32> = offsets.iter().map(|o| o.y.asin().to_degrees()).collect();
        let (min, max) = elevations
            .iter()
            .fold((90.0f32, -90.0f32), |(a, b), &e| (a.min(e), b.max(e)));
        assert!(min < -20.0 && max > 65.0, "{min}..{max}");
        for i in 0..16 {
            for j in 0..i {
                let angle = offsets[i].dot(offsets[j]).clamp(-1.0, 1.0).acos();
                assert!(angle > 0.25, "cameras {i} and {j} are {angle} rad apart");
            }
        }
    }

    #[test]
    fn bad_orbits_are_refused_naming_the_key() {
        let good = Orbit {
            count: 4,
            elevation_deg: (0.0, 45.0),
            distance: 10.0,
            fov_deg: 40.0,
            width: 4,
            height: 4,
            azimuth_offset_deg: 10.0,
        };
        for (orbit, key) in [
            (Orbit { count: 0, ..good }, "count"),
            (
                Orbit {
                    elevation_deg: (50.0, 10.0),
                    ..good
                },
                "elevation_deg",
            ),
            (
                Orbit {
                    elevation_deg: (0.0, 90.0),
                    ..good
                },
                "elevation_deg",
            ),
            (
                Orbit {
                    distance: -1.0,
                    ..good
                },
                "distance",
            ),
            (
                Orbit {
                    distance: f32::NAN,
                    ..good
                },
                "distance",
            ),
        ] {
            let err = orbit.cameras(Vec3::ZERO).unwrap_err().to_string();
            assert!(err.contains(key), "{err}");
        }
    }
}
