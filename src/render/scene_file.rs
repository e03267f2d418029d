//! Scene files (TOML) as parsed: the structs that mirror the file's tables, their defaults, and
//! reading. Below both `scene_check` (which validates them) and `scene` (which loads them into
//! the renderer's types), so that neither imports the other.

use std::path::Path;

use anyhow::{Context, Result};
use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::io::vdb::LevelSet;
use crate::volume::majorant::{Majorant, MajorantMode};
use crate::volume::medium::Filter;

/// A grey value or an RGB triple.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(untagged)]
pub enum Spectrum {
    Grey(f32),
    Rgb([f32; 3]),
}

impl<'de> Deserialize<'de> for Spectrum {
    /// A number or exactly three, with an error that says so (serde's untagged enums name only
    /// the enum's type, and its arrays take the first three of a longer list).
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Given {
            Grey(f32),
            List(Vec<f32>),
        }
        let expected = "a number, or an array of 3 numbers [r, g, b]";
        match Given::deserialize(d)
            .map_err(|_| serde::de::Error::custom(format!("expected {expected}")))?
        {
            Given::Grey(v) => Ok(Spectrum::Grey(v)),
            Given::List(c) => (c.len() == 3)
                .then(|| Spectrum::Rgb([c[0], c[1], c[2]]))
                .ok_or_else(|| serde::de::Error::invalid_length(c.len(), &expected)),
        }
    }
}

impl Spectrum {
    pub fn rgb(self) -> Vec3 {
        match self {
            Spectrum::Grey(v) => Vec3::splat(v),
            Spectrum::Rgb(c) => Vec3::from(c),
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    /// Required to render; the scene of an `optimize` run whose views are all images may leave
    /// it out (each view is its own camera).
    pub camera: Option<CameraFile>,
    pub medium: MediumFile,
    #[serde(default, deserialize_with = "light_list")]
    pub light: Vec<LightFile>,
    #[serde(default)]
    pub render: RenderFile,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraFile {
    #[serde(deserialize_with = "crate::io::exact::array")]
    pub position: [f32; 3],
    #[serde(deserialize_with = "crate::io::exact::array")]
    pub target: [f32; 3],
    #[serde(default = "default_up", deserialize_with = "crate::io::exact::array")]
    pub up: [f32; 3],
    /// Horizontal field of view.
    pub fov_deg: f32,
    pub width: u32,
    pub height: u32,
}

/// A camera's up when the file gives none (+y), for scene and run files alike.
pub fn default_up() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MediumFile {
    /// The density grid's file. Required to render; the scene of an `optimize` run that solves
    /// for the density from images may leave it out (the unknown is the grid).
    pub vdb: Option<String>,
    pub grid: Option<String>,
    pub grid_index: Option<usize>,
    #[serde(default = "one")]
    pub density_scale: f32,
    #[serde(default = "white")]
    pub albedo: AlbedoFile,
    #[serde(default)]
    pub phase_g: f32,
    #[serde(default)]
    pub filter: Filter,
    /// A level-set grid is refused unless this is "fog" (converted by OpenVDB's sdfToFogVolume).
    #[serde(default)]
    pub levelset: LevelSet,
    /// Light the medium gives off, from a grid of its own.
    pub emission: Option<EmissionFile>,
}

/// `albedo = 0.9`, `albedo = [r, g, b]`, or `albedo = { grid = "Cd" }`: a grid of its own, RGB
/// (vec3) or grey (float), from `medium.vdb` or another file (`vdb = …`).
#[derive(Debug, Clone)]
pub enum AlbedoFile {
    Constant(Spectrum),
    Grid {
        grid: String,
        /// The file it is in (default: `medium.vdb`), relative to the scene file.
        vdb: Option<String>,
    },
}

/// `AlbedoFile`'s table form, its keys checked.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct AlbedoGridFile {
    grid: String,
    vdb: Option<String>,
}

impl<'de> Deserialize<'de> for AlbedoFile {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        Ok(match table_or_value(d)? {
            TableOr::Table(AlbedoGridFile { grid, vdb }) => AlbedoFile::Grid { grid, vdb },
            TableOr::Value(spectrum) => AlbedoFile::Constant(spectrum),
        })
    }
}

/// A key that is a table or a value of another form, e.g. `{ grid = "Cd" }` or `0.9`.
pub enum TableOr<T, U> {
    Table(T),
    Value(U),
}

/// Reads a key that is a table (as `T`, whose struct denies unknown keys) or any other value (as
/// `U`). Not `#[serde(untagged)]`: an untagged enum's struct variant reads a typo'd key as if it
/// were absent (`albedo = { grid = "Cd", vbd = "x.vdb" }` rendered `Cd` from the medium's file),
/// and with the struct denying it, answers only "did not match any variant"; here the table's
/// own error names the key.
pub fn table_or_value<'de, D, T, U>(d: D) -> std::result::Result<TableOr<T, U>, D::Error>
where
    D: serde::Deserializer<'de>,
    T: serde::de::DeserializeOwned,
    U: serde::de::DeserializeOwned,
{
    use serde::de::Error;
    match toml::Value::deserialize(d)? {
        table @ toml::Value::Table(_) => T::deserialize(table)
            .map(TableOr::Table)
            .map_err(D::Error::custom),
        value => U::deserialize(value)
            .map(TableOr::Value)
            .map_err(D::Error::custom),
    }
}

/// `emission = { grid = "temperature", blackbody = { … }, strength = S }` or
/// `emission = { grid = "flames", radiance = [r, g, b] }`: the medium emits σa·Le.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EmissionFile {
    /// The grid's name.
    pub grid: String,
    /// The file it is in (default: `medium.vdb`), relative to the scene file.
    pub vdb: Option<String>,
    /// Le = strength × the normalised blackbody at T = (v − offset) · scale kelvin (pbrt-v4's
    /// `Lescale`, `temperaturescale` and `temperatureoffset`, whose older name
    /// `temperaturecutoff` is that offset, not `BlackbodyFile::cutoff`).
    pub blackbody: Option<BlackbodyFile>,
    pub strength: Option<f32>,
    /// Le = radiance × v.
    pub radiance: Option<Spectrum>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BlackbodyFile {
    #[serde(default = "one")]
    pub scale: f32,
    #[serde(default)]
    pub offset: f32,
    /// Temperatures at or below this many kelvin emit nothing.
    #[serde(default)]
    pub cutoff: f32,
}

fn one() -> f32 {
    1.0
}

fn white() -> AlbedoFile {
    AlbedoFile::Constant(Spectrum::Grey(1.0))
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(tag = "type", rename_all = "lowercase", deny_unknown_fields)]
pub enum LightFile {
    Constant {
        radiance: Spectrum,
    },
    Envmap {
        /// A lat-long image (EXR, HDR, ...), relative to the scene file.
        file: String,
        #[serde(default = "one")]
        scale: f32,
        /// The world direction of the image's top row.
        #[serde(default = "default_up", deserialize_with = "crate::io::exact::array")]
        up: [f32; 3],
        /// Turns the image about `up`, counter-clockwise seen from above, in degrees.
        #[serde(default)]
        rotation_deg: f32,
    },
    Directional {
        /// The direction in which the light travels.
        #[serde(deserialize_with = "crate::io::exact::array")]
        direction: [f32; 3],
        irradiance: Spectrum,
    },
}

/// A list of lights, each error naming the light it is in (`light[1]: unknown field …`). A light
/// is a tagged enum, which serde reads from a copy of the table: its errors lose their own place
/// and are shown at the list's first line, whichever light they are in.
pub fn light_list<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<LightFile>, D::Error> {
    use serde::de::Error;
    let tables = Vec::<toml::Value>::deserialize(d)?;
    (tables.into_iter().enumerate())
        .map(|(i, table)| {
            // serde would say "expected internally tagged enum LightFile".
            if !table.is_table() {
                return Err(D::Error::custom(format!(
                    "light[{i}] must be a table of keys (a dict, from Python) with its `type`: constant, envmap or directional (got {table})"
                )));
            }
            LightFile::deserialize(table)
                .map_err(|e| D::Error::custom(format!("light[{i}]: {}", e.message())))
        })
        .collect()
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderFile {
    #[serde(default = "default_spp")]
    pub spp: u32,
    #[serde(default = "default_max_depth")]
    pub max_depth: u32,
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// Multiplies the image before the PNG's sRGB encoding (the EXR stays linear and unscaled).
    #[serde(default = "one")]
    pub exposure: f32,
    #[serde(default)]
    pub majorant: MajorantMode,
    /// Edge of a majorant cell, in voxels.
    #[serde(default = "default_majorant_cell")]
    pub majorant_cell: u32,
}

fn default_spp() -> u32 {
    64
}
fn default_max_depth() -> u32 {
    64
}
fn default_seed() -> u64 {
    1
}
/// 4³-voxel cells: on the Disney cloud, tracking efficiency 0.41 (8³: 0.29) at equal speed.
pub const DEFAULT_MAJORANT_CELL: u32 = 4;
fn default_majorant_cell() -> u32 {
    DEFAULT_MAJORANT_CELL
}

impl RenderFile {
    /// The tracking structure these settings ask for.
    pub fn majorant(&self) -> Majorant {
        Majorant {
            mode: self.majorant,
            cell_voxels: self.majorant_cell,
        }
    }
}

impl Default for RenderFile {
    fn default() -> Self {
        RenderFile {
            spp: default_spp(),
            max_depth: default_max_depth(),
            seed: default_seed(),
            exposure: 1.0,
            majorant: MajorantMode::Grid,
            majorant_cell: DEFAULT_MAJORANT_CELL,
        }
    }
}

impl SceneFile {
    pub fn parse(text: &str, origin: &Path) -> Result<Self> {
        let file = toml::from_str(text).map_err(|e| {
            // A run file names its scene; a scene file is what it names.
            let table = toml::from_str::<toml::Table>(text).ok();
            if table.is_some_and(|t| t.contains_key("scene") && !t.contains_key("medium")) {
                anyhow::anyhow!(
                    "{} is a run file (it names a `scene`), not a scene file: give it to `volgrad optimize`",
                    origin.display()
                )
            } else {
                anyhow::anyhow!("{}: {}", origin.display(), e.to_string().trim_end())
            }
        })?;
        crate::io::exact::within_f32(text).with_context(|| origin.display().to_string())?;
        Ok(file)
    }

    pub fn read(path: &Path) -> Result<Self> {
        let text = crate::io::input::read_text(path)
            .with_context(|| format!("cannot read scene file '{}'", path.display()))?;
        Self::parse(&text, path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = r#"
        [camera]
        position = [0, 0, 10]
        target = [0, 0, 0]
        fov_deg = 40
        width = 8
        height = 8
        [medium]
        vdb = "m.vdb"
        albedo = { grid = "Cd", vdb = "c.vdb" }
        emission = { grid = "t", blackbody = { scale = 1000 }, strength = 2 }
        [[light]]
        type = "constant"
        radiance = 1
        [render]
        spp = 4
    "#;

    /// A typo'd key in any table of a scene file is refused with the key named, never read as
    /// if it were absent: `albedo = { grid = "Cd", vbd = "x.vdb" }` once rendered `Cd` from the
    /// medium's file.
    #[test]
    fn a_typo_in_any_table_is_refused_by_name() {
        let parse = |text: &str| SceneFile::parse(text, Path::new("s.toml"));
        parse(GOOD).unwrap();
        let cases = [
            ("[camera]", "[camera]\n        fovdeg = 1", "fovdeg"),
            (
                "[medium]",
                "[medium]\n        densty_scale = 1",
                "densty_scale",
            ),
            (
                "vdb = \"c.vdb\" }",
                "vdb = \"c.vdb\", vbd = \"x.vdb\" }",
                "vbd",
            ),
            ("strength = 2 }", "strength = 2, strenght = 3 }", "strenght"),
            ("scale = 1000 }", "scale = 1000, ofset = 1 }", "ofset"),
            (
                "radiance = 1",
                "radiance = 1\n        radiance_scale = 2",
                "radiance_scale",
            ),
            ("[render]", "[render]\n        sp = 4", "sp"),
            ("[camera]", "sceen = 1\n        [camera]", "sceen"),
        ];
        for (from, to, key) in cases {
            assert!(GOOD.contains(from), "{from}");
            let e = format!("{:#}", parse(&GOOD.replacen(from, to, 1)).unwrap_err());
            assert!(e.contains(&format!("unknown field `{key}`")), "{key}: {e}");
        }
        // The albedo's other forms still parse.
        for albedo in ["0.5", "[0.1, 0.2, 0.3]", "{ grid = \"Cd\" }"] {
            let text = GOOD.replace("{ grid = \"Cd\", vdb = \"c.vdb\" }", albedo);
            parse(&text).unwrap();
        }
    }

    /// A triple given with more or fewer values is refused naming the length, not read as its
    /// first three (serde's arrays stop at their length) or as "no variant of enum Spectrum".
    #[test]
    fn triples_of_another_length_are_refused() {
        let parse = |text: &str| SceneFile::parse(text, Path::new("s.toml"));
        for (from, to) in [
            ("position = [0, 0, 10]", "position = [0, 0, 10, 1]"),
            ("target = [0, 0, 0]", "target = [0, 0]"),
            ("fov_deg = 40", "fov_deg = 40\n        up = [0, 1, 0, 0]"),
            ("radiance = 1", "radiance = [1, 1, 1, 1]"),
            ("{ grid = \"Cd\", vdb = \"c.vdb\" }", "[0.5, 0.5]"),
        ] {
            assert!(GOOD.contains(from), "{from}");
            let e = format!("{:#}", parse(&GOOD.replacen(from, to, 1)).unwrap_err());
            assert!(e.contains("array of 3 numbers"), "{to}: {e}");
        }
    }

    /// A run file given where a scene file goes is named for what it is.
    #[test]
    fn a_run_file_is_not_read_as_a_broken_scene() {
        let run = "scene = \"cloud.toml\"\n[unknown]\nbounds = \"views\"\n";
        let e = format!(
            "{:#}",
            SceneFile::parse(run, Path::new("r.toml")).unwrap_err()
        );
        assert!(
            e.contains("r.toml is a run file") && e.contains("volgrad optimize"),
            "{e}"
        );
    }
}
