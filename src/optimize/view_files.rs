//! The views of a run file: cameras listed with their images (`[[view]]`, `[[holdout]]`), orbits
//! whose targets are rendered from a true grid, a `transforms.json`, each optionally under lights
//! of its own; and the checks on their number and size, made before anything is allocated.

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::io::images::ColorSpace;
use crate::optimize::optimizer_file::one_or_many;
use crate::optimize::views::{Orbit, MAX_VIEWS};
use crate::render::scene_check::check_lights;
use crate::render::scene_file::LightFile;

/// The most target pixels of a run, all views together (2^28: 3 GiB of RGB f32).
pub const MAX_TARGET_PIXELS: u64 = 1 << 28;

/// A camera as in a scene file, with the image it sees.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ViewFile {
    #[serde(deserialize_with = "crate::io::exact::array")]
    pub position: [f32; 3],
    #[serde(deserialize_with = "crate::io::exact::array")]
    pub target: [f32; 3],
    #[serde(
        default = "crate::render::scene::default_up",
        deserialize_with = "crate::io::exact::array"
    )]
    pub up: [f32; 3],
    pub fov_deg: f32,
    pub width: u32,
    pub height: u32,
    /// The target image (linear; any format OpenImageIO reads). Without it the view's target is
    /// rendered from `truth`.
    pub image: Option<String>,
    /// The lights this view was taken under, as a scene file's `[[light]]`s (default: the
    /// scene's).
    #[serde(
        default,
        deserialize_with = "listed_lights",
        skip_serializing_if = "Vec::is_empty"
    )]
    pub light: Vec<LightFile>,
}

#[derive(Debug, Clone, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ViewSetFile {
    /// One orbit (`[views.orbit]`) or several (`[[views.orbit]]`), e.g. each under its own
    /// lights.
    #[serde(default, deserialize_with = "one_or_many")]
    pub orbit: Vec<OrbitFile>,
    /// A `transforms.json` (NeRF / instant-ngp convention, `transforms`), relative to the run
    /// file: its frames' cameras, and their images as targets.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub transforms: Option<String>,
    /// A COLMAP text model (`[views.colmap]`): its cameras, and their images as targets.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub colmap: Option<ColmapFile>,
    /// The lights of the transforms file's and COLMAP model's views (default: the scene's).
    #[serde(
        default,
        deserialize_with = "listed_lights",
        skip_serializing_if = "Vec::is_empty"
    )]
    pub light: Vec<LightFile>,
    /// How the set's images (listed and the transforms file's) decode to radiance: "srgb" or
    /// "linear" (default: as each file declares, else sRGB for 8/16-bit and linear for float).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub color_space: Option<ColorSpace>,
    /// The capture the set's pictures were taken in: with `fit_exposure`, the views of one capture
    /// share one fitted exposure (default: the unnamed capture every unnamed set is part of). A
    /// held-out set names a capture some training set names.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub capture: Option<String>,
}

/// A COLMAP text model and the folder of its images.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ColmapFile {
    /// The folder holding `cameras.txt` and `images.txt`, relative to the run file.
    pub model: String,
    /// The folder the images' names are relative to, relative to the run file (default: COLMAP's
    /// project layout, `images` beside the model's `sparse` folder: `P/sparse/0` → `P/images`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub images: Option<String>,
}

impl ViewSetFile {
    /// Whether the set has any view: listed in `listed`, on an orbit or in a camera file.
    pub fn has_views(&self, listed: &[ViewFile]) -> bool {
        !listed.is_empty()
            || !self.orbit.is_empty()
            || self.transforms.is_some()
            || self.colmap.is_some()
    }
}

/// Cameras on a Fibonacci spiral around the unknown's box, targets rendered from `truth`.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct OrbitFile {
    pub count: u32,
    #[serde(deserialize_with = "crate::io::exact::array")]
    pub elevation_deg: [f32; 2],
    pub distance: f32,
    pub fov_deg: f32,
    pub width: u32,
    pub height: u32,
    /// Turns the whole spiral about `up`, e.g. to put held-out views between the training views.
    #[serde(default)]
    pub azimuth_offset_deg: f32,
    /// The orbit's pole and the cameras' up (default +y; +z for a z-up asset).
    #[serde(
        default = "crate::render::scene::default_up",
        deserialize_with = "crate::io::exact::array"
    )]
    pub up: [f32; 3],
    /// The lights of these views, as a scene file's `[[light]]`s (default: the scene's).
    #[serde(
        default,
        deserialize_with = "listed_lights",
        skip_serializing_if = "Vec::is_empty"
    )]
    pub light: Vec<LightFile>,
}

impl OrbitFile {
    pub fn orbit(&self) -> Orbit {
        Orbit {
            count: self.count,
            elevation_deg: (self.elevation_deg[0], self.elevation_deg[1]),
            distance: self.distance,
            fov_deg: self.fov_deg,
            width: self.width,
            height: self.height,
            azimuth_offset_deg: self.azimuth_offset_deg,
            up: self.up,
        }
    }
}

/// One set of views as a run file gives it: its views' key ("view" or "holdout"), the set's name
/// in messages (`views`, or `holdouts[1]` among several), the listed views (the first set's) and
/// the set's table (orbits, transforms file, COLMAP model, lights).
pub type ViewTables<'a> = (&'a str, String, &'a [ViewFile], &'a ViewSetFile);

/// The sets of one kind (`[views]` or `[[views]]`, with the `[[view]]`s listed beside them),
/// each with its name.
pub fn view_tables<'a>(
    key: &'a str,
    listed: &'a [ViewFile],
    sets: &'a [ViewSetFile],
) -> Vec<ViewTables<'a>> {
    (sets.iter().enumerate())
        .map(|(j, set)| {
            let name = match sets.len() {
                1 => format!("{key}s"),
                _ => format!("{key}s[{j}]"),
            };
            (key, name, if j == 0 { listed } else { &[] }, set)
        })
        .collect()
}

/// A run file's sets of one kind when it gives none: one empty set (its listed views alone).
pub fn one_set() -> Vec<ViewSetFile> {
    vec![ViewSetFile::default()]
}

/// `one_or_many`, with no set read as one empty set.
pub fn view_sets<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<ViewSetFile>, D::Error> {
    let sets: Vec<ViewSetFile> = one_or_many(d)?;
    Ok(if sets.is_empty() { one_set() } else { sets })
}

/// Every view's target is an image kept in memory for the whole run, and a truth renders it
/// before the first iteration: the counts and pixels are checked before anything is
/// allocated or rendered.
pub fn check_sizes(sets: &[ViewTables]) -> Result<()> {
    let mut pixels = 0u64;
    for (_, name, listed, set) in sets {
        // Saturating: a view's pixels fit in a u64, but the sums and an orbit's count times its
        // pixels can wrap, and all that matters is whether the total is past the limit.
        for v in listed.iter() {
            pixels = pixels.saturating_add(u64::from(v.width) * u64::from(v.height));
        }
        let mut count = listed.len() as u64;
        for o in &set.orbit {
            count = count.saturating_add(u64::from(o.count));
            let orbit = u64::from(o.width) * u64::from(o.height);
            pixels = pixels.saturating_add(orbit.saturating_mul(u64::from(o.count)));
        }
        if count > MAX_VIEWS {
            bail!(
                "{name}: {count} views (listed and on orbits): at most {MAX_VIEWS} per set (each is a target image held in memory, rendered before the first iteration when it comes from a truth)"
            );
        }
    }
    target_pixels(pixels)
}

/// The budget of all target pixels of a run: checked on the listed views and orbits when the run
/// file is read, and again with the transforms files' frames once their cameras are known.
pub fn target_pixels(pixels: u64) -> Result<()> {
    if pixels > MAX_TARGET_PIXELS {
        bail!(
            "the views and held-out views have {pixels} pixels in all: at most 2^28 = {MAX_TARGET_PIXELS} (3 GiB of target images); use fewer or smaller views"
        );
    }
    Ok(())
}

/// A view's or set's `light` list as written. Leaving the key out means the scene's lights, so an
/// empty list would silently mean them too, not the darkness it seems to say: it is refused.
fn listed_lights<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<LightFile>, D::Error> {
    let lights = crate::render::scene_file::light_list(d)?;
    if lights.is_empty() {
        return Err(serde::de::Error::custom(
            "light = [] lists no light: leave `light` out for the scene's lights, or give \
             [{ type = \"constant\", radiance = 0 }] for pictures taken in the dark",
        ));
    }
    Ok(lights)
}

/// Every view's and orbit's own lights, as a scene file's are checked.
pub fn check_view_lights(sets: &[ViewTables]) -> Result<()> {
    for (key, name, listed, set) in sets {
        for (i, v) in listed.iter().enumerate() {
            check_lights(&v.light).with_context(|| format!("{key}[{i}]"))?;
        }
        for (i, o) in set.orbit.iter().enumerate() {
            check_lights(&o.light).with_context(|| format!("{name}.orbit[{i}]"))?;
        }
        check_lights(&set.light).with_context(|| format!("{name}.light"))?;
    }
    Ok(())
}
