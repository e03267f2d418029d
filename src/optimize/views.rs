//! Synthetic studies look at the medium from many sides: cameras on a Fibonacci spiral over a band
//! of elevations, all at one distance from the medium's centre and looking at it. The spiral gives
//! every camera about the same share of the band's area (equal steps in sin(elevation), azimuths a
//! golden angle apart), so no side is seen twice as often as another.

use anyhow::{bail, Context, Result};
use glam::{Quat, Vec3};

use crate::render::camera::Camera;
use crate::render::scene_check::{
    coordinates, field_of_view, image_size, unit, view_frame, MAX_COORDINATE,
};

/// `[views.orbit]` of a run file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Orbit {
    pub count: u32,
    /// Lowest and highest elevation above the plane normal to `up`, in degrees.
    pub elevation_deg: (f32, f32),
    /// From the centre, in world units.
    pub distance: f32,
    pub fov_deg: f32,
    pub width: u32,
    pub height: u32,
    /// Turns the spiral about `up` (e.g. held-out views between the training views).
    pub azimuth_offset_deg: f32,
    /// The orbit's pole and the cameras' up: +y, or +z for a z-up asset (Blender, Mantaflow).
    pub up: [f32; 3],
}

/// Elevations this close to the poles would make `up` parallel to the view.
const MAX_ELEVATION_DEG: f32 = 89.0;
/// The most views in a set (`[[view]]`s and the orbit's, or the held-out ones), and so in an
/// orbit: each is a target image held in memory, and an orbit of 2³² − 1 cameras would ask for
/// 300 GB (an abort, not an error).
pub const MAX_VIEWS: u64 = 10_000;

impl Orbit {
    /// The cameras, looking at `centre`.
    pub fn cameras(&self, centre: Vec3) -> Result<Vec<Camera>> {
        let (lo, hi) = self.elevation_deg;
        if !(1..=MAX_VIEWS).contains(&u64::from(self.count)) {
            bail!(
                "views.orbit.count must be from 1 to {MAX_VIEWS} (got {})",
                self.count
            );
        }
        coordinates("the orbit's centre", centre.to_array())?;
        if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
            bail!(
                "views.orbit.elevation_deg must be [low, high] with low ≤ high (got [{lo}, {hi}])"
            );
        }
        if lo.abs().max(hi.abs()) > MAX_ELEVATION_DEG {
            bail!("views.orbit.elevation_deg must lie within ±{MAX_ELEVATION_DEG}° (got [{lo}, {hi}]): the pole is the cameras' up");
        }
        if !self.azimuth_offset_deg.is_finite() {
            bail!(
                "views.orbit.azimuth_offset_deg must be a finite number of degrees (got {})",
                self.azimuth_offset_deg
            );
        }
        let up = unit("views.orbit.up", self.up)?;
        // The spiral is laid out about +y, then turned onto `up` (exactly the identity for +y).
        let to_up = Quat::from_rotation_arc(Vec3::Y, up);
        if !(self.distance > 0.0 && self.distance <= MAX_COORDINATE) {
            bail!(
                "views.orbit.distance must be a positive number of at most {MAX_COORDINATE:e} (got {})",
                self.distance
            );
        }
        image_size(
            "views.orbit.width",
            "views.orbit.height",
            self.width,
            self.height,
        )?;
        field_of_view("views.orbit.fov_deg", self.fov_deg, self.width, self.height)?;
        let golden_angle = std::f32::consts::PI * (3.0 - 5f32.sqrt());
        let (s_lo, s_hi) = (lo.to_radians().sin(), hi.to_radians().sin());
        (0..self.count)
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
                let position = centre + self.distance * (to_up * offset);
                // As a listed camera is checked: a distance lost beside the centre's coordinates
                // in f32 would put the camera on its target.
                coordinates("an orbit camera's position", position.to_array())?;
                view_frame(position.to_array(), centre.to_array(), up.to_array())
                    .context("views.orbit.distance is too small beside the centre's coordinates")?;
                Ok(Camera::new(
                    position,
                    centre,
                    up,
                    self.fov_deg,
                    self.width,
                    self.height,
                ))
            })
            .collect()
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
            up: [0.0, 1.0, 0.0],
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
            up: [0.0, 1.0, 0.0],
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
            (
                Orbit {
                    up: [0.0, 0.0, 0.0],
                    ..good
                },
                "up",
            ),
            (Orbit { width: 0, ..good }, "width"),
            (Orbit { height: 0, ..good }, "height"),
            (
                Orbit {
                    width: 1 << 16,
                    height: 1 << 16,
                    ..good
                },
                "too large",
            ),
            (
                Orbit {
                    fov_deg: 0.0,
                    ..good
                },
                "fov_deg",
            ),
            (
                Orbit {
                    fov_deg: 180.0,
                    ..good
                },
                "fov_deg",
            ),
            (
                Orbit {
                    fov_deg: f32::NAN,
                    ..good
                },
                "fov_deg",
            ),
            (
                Orbit {
                    fov_deg: -30.0,
                    ..good
                },
                "fov_deg",
            ),
            (
                Orbit {
                    distance: 1e30,
                    ..good
                },
                "distance",
            ),
            (
                Orbit {
                    up: [f32::INFINITY, 0.0, 0.0],
                    ..good
                },
                "up",
            ),
        ] {
            let err = orbit.cameras(Vec3::ZERO).unwrap_err().to_string();
            assert!(err.contains(key), "{err}");
        }
    }

    /// An orbit about +z is the +y orbit turned onto +z: the same spiral, elevations measured
    /// from the xy plane, every camera's up +z; about +y it is the +y spiral itself.
    #[test]
    fn an_orbit_about_z_is_the_y_orbit_turned_onto_z() {
        let about = |up: [f32; 3]| Orbit {
            count: 6,
            elevation_deg: (-20.0, 60.0),
            distance: 10.0,
            fov_deg: 30.0,
            width: 8,
            height: 8,
            azimuth_offset_deg: 25.0,
            up,
        };
        let centre = Vec3::new(2.0, 2.0, 1.5);
        let y = about([0.0, 1.0, 0.0]).cameras(centre).unwrap();
        let z = about([0.0, 0.0, 3.0]).cameras(centre).unwrap();
        let turn = Quat::from_rotation_x(std::f32::consts::FRAC_PI_2);
        for (a, b) in y.iter().zip(&z) {
            let expected = centre + turn * (a.position - centre);
            assert!(
                (b.position - expected).length() < 1e-4,
                "{} {expected}",
                b.position
            );
            let elevation = ((b.position.z - centre.z) / 10.0).asin().to_degrees();
            assert!((-20.0..=60.0).contains(&elevation), "{elevation}");
            // The image's up is +z: a point above the centre projects above the image centre.
            let (_, row) = b.project(centre + Vec3::Z).unwrap();
            assert!(row < 4.0, "{row}");
        }
        // Lengths f32 cannot square (1e30, 1e-30) are poles all the same.
        for pole in [[0.0, 0.0, 1e30], [0.0, 0.0, 1e-30]] {
            let far = about(pole).cameras(centre).unwrap();
            assert!(z.iter().zip(&far).all(|(a, b)| a.position == b.position));
        }
        let plain = about([0.0, 1.0, 0.0]).cameras(centre).unwrap();
        assert!(y.iter().zip(&plain).all(|(a, b)| a.position == b.position));
    }
}
