//! Scenes ready to render: a scene file, validated, loaded into the renderer's types (camera,
//! medium, lights). Paths inside a scene are relative to the scene file.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use glam::{DVec3, Vec3};

use crate::io::images;
use crate::io::vdb::{self, GridSelector};
use crate::render::camera::{Camera, Intrinsics};
use crate::render::lights::{DirectionalLight, EnvMap, Environment, Lights};
use crate::render::medium_grids;
use crate::render::scene_check::{self, MAX_EXTINCTION, MAX_LIGHT};
use crate::volume::brickmap::BrickMap;
use crate::volume::majorant::{Majorant, MajorantGrid, MajorantMode};
use crate::volume::medium::Medium;
use crate::volume::transform::IndexTransform;

// The file's structs are named here too: the layers above load a scene and its settings through
// `render::scene` alone; they live in `scene_file`, below `scene_check`, which validates them.
pub use crate::render::scene_file::{
    default_up, CameraFile, LightFile, MediumFile, RenderFile, SceneFile, Spectrum,
    DEFAULT_MAJORANT_CELL,
};

/// A scene ready to render.
#[derive(Clone)]
pub struct Scene {
    pub path: PathBuf,
    pub camera: Camera,
    pub medium: Medium,
    pub lights: Lights,
    pub settings: RenderFile,
    /// The grid the medium came from, as loaded (name, transform, metadata) for exports.
    pub grid_name: String,
    /// Its file; `None` for an optimize run's scene without a grid (`SceneNeeds::Constants`).
    pub vdb_path: Option<PathBuf>,
}

impl CameraFile {
    /// The camera, after `validate`.
    pub fn camera(&self) -> Result<Camera> {
        let c = self;
        // The direction is found in f64: a target close to a distant position does not round
        // onto it.
        let (forward, up) = scene_check::view_frame(c.position, c.target, c.up)?;
        Ok(Camera::looking(
            Vec3::from(c.position),
            forward,
            up,
            Intrinsics::from_fov(c.fov_deg, c.width, c.height),
            c.width,
            c.height,
        ))
    }
}

/// What a scene file must name. A scene to render names its grid and its camera; the scene of an
/// `optimize` run whose views are all images may leave both out: it gives the medium's optical
/// constants and the lights, the unknown stands in for the grid and each view is its own camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SceneNeeds {
    GridAndCamera,
    Constants,
}

impl Scene {
    /// Reads, validates and loads a scene file with its grid and lights.
    pub fn load(path: &Path) -> Result<Scene> {
        Self::load_as(path, SceneNeeds::GridAndCamera)
    }

    /// Reads, validates and loads a scene file that must name what `needs` says.
    pub fn load_as(path: &Path, needs: SceneNeeds) -> Result<Scene> {
        let file = SceneFile::read(path)?;
        Self::from_file_as(file, path, needs)
    }

    /// Loads a parsed scene; `path` locates the files it names.
    pub fn from_file(file: SceneFile, path: &Path) -> Result<Scene> {
        Self::from_file_as(file, path, SceneNeeds::GridAndCamera)
    }

    /// Loads a parsed scene that must name what `needs` says (the Python binding builds one from
    /// parts, its grid given as an array).
    pub fn from_file_as(file: SceneFile, path: &Path, needs: SceneNeeds) -> Result<Scene> {
        file.validate()
            .with_context(|| format!("invalid scene '{}'", path.display()))?;
        if needs == SceneNeeds::GridAndCamera {
            let missing = match (&file.camera, &file.medium.vdb) {
                (None, _) => Some("camera ([camera])"),
                (_, None) => Some("grid (medium.vdb)"),
                _ => None,
            };
            if let Some(missing) = missing {
                bail!(
                    "scene '{}' names no {missing}: a scene to render needs one (only the scene of an optimize run whose views are images may leave it out)",
                    path.display()
                );
            }
        }
        let dir = path.parent().unwrap_or(Path::new("."));
        let filter = file.medium.filter;
        let mode = file.render.majorant();
        let (grid_name, bricks, transform, vdb_path) = match &file.medium.vdb {
            Some(vdb) => {
                let vdb_path = dir.join(vdb);
                let grid = density_grid(&file, &vdb_path)?;
                (grid.name, grid.bricks, grid.transform, Some(vdb_path))
            }
            // No grid: an empty medium, which the run's unknown replaces.
            None => (
                "density".to_string(),
                BrickMap::new(Vec::new(), Vec::new()),
                IndexTransform::uniform(1.0, DVec3::ZERO),
                None,
            ),
        };
        let camera = match &file.camera {
            Some(camera) => camera.camera()?,
            // Never rendered through: every view of the run sets its own.
            None => Camera::new(Vec3::Z, Vec3::ZERO, Vec3::Y, 40.0, 1, 1),
        };
        let mut medium = Medium::new(bricks, transform, file.medium.density_scale, filter, mode);
        let own = vdb_path.as_deref();
        medium.albedo = medium_grids::load_albedo(&file.medium.albedo, dir, own, filter)?;
        medium.phase_g = file.medium.phase_g;
        if let Some(e) = &file.medium.emission {
            medium.emission = Some(medium_grids::load_emission(e, dir, own, filter)?);
        }
        let lights = load_lights(&file.light, dir)?;
        Ok(Scene {
            path: path.to_path_buf(),
            camera,
            medium,
            lights,
            settings: file.render,
            grid_name,
            vdb_path,
        })
    }

    /// Rebuilds the majorant structure (e.g. for `--majorant global` from the command line).
    pub fn set_majorant(&mut self, majorant: Majorant) {
        let m = &mut self.medium;
        m.majorant = MajorantGrid::build(&m.grid, m.bounds, m.density_scale, majorant)
            .with_hot_spots(&m.grid, m.transform.voxel_diagonal());
        self.settings.majorant = majorant.mode;
        if majorant.mode == MajorantMode::Grid {
            self.settings.majorant_cell = majorant.cell_voxels;
        }
    }
}

/// The density grid `file` names in `vdb_path`: ≥ 0 everywhere, its extinction trackable.
fn density_grid(file: &SceneFile, vdb_path: &Path) -> Result<vdb::Grid> {
    match std::fs::metadata(vdb_path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => bail!(
            "medium.vdb: file '{}' does not exist (paths are relative to the scene file)",
            vdb_path.display()
        ),
        // A link loop, a folder without permission: the system's own words.
        Err(e) => {
            let context = format!("medium.vdb: cannot read '{}'", vdb_path.display());
            return Err(anyhow::Error::new(e).context(context));
        }
        Ok(_) => {}
    }
    let selector = match (&file.medium.grid, file.medium.grid_index) {
        (Some(name), _) => GridSelector::Name(name.clone()),
        (None, Some(i)) => GridSelector::Index(i),
        (None, None) => GridSelector::Default,
    };
    let grid =
        vdb::read_density(vdb_path, &selector, file.medium.levelset).context("medium.vdb")?;
    if grid.bricks.min_value() < 0.0 {
        bail!(
            "grid '{}' in '{}' has negative values (min {}): extinction must be ≥ 0 (signed distances must be stored as class \"level set\" to be converted)",
            grid.name,
            vdb_path.display(),
            grid.bricks.min_value()
        );
    }
    let extinction = file.medium.density_scale as f64 * grid.bricks.max_value() as f64;
    if extinction > MAX_EXTINCTION {
        bail!(
            "medium.density_scale × the largest value of grid '{}' in '{}' is {extinction:.3e}: too large to track (at most {MAX_EXTINCTION:e} per world unit; the medium is opaque long before)",
            grid.name,
            vdb_path.display()
        );
    }
    Ok(grid)
}

/// The renderer's lights from a checked list of scene-file lights (`scene_check::check_lights`);
/// an environment map's file is relative to `dir`.
pub fn load_lights(files: &[LightFile], dir: &Path) -> Result<Lights> {
    let mut lights = Lights::default();
    let mut environment = Environment::default();
    for (i, light) in files.iter().enumerate() {
        match light {
            LightFile::Constant { radiance } => environment.constant += radiance.rgb(),
            LightFile::Envmap {
                file,
                scale,
                up,
                rotation_deg,
            } => {
                let path = dir.join(file);
                let image = images::read_rgb(&path).with_context(|| format!("light[{i}].file"))?;
                if image
                    .pixels
                    .iter()
                    .any(|c| !c.is_finite() || c.cmplt(Vec3::ZERO).any())
                {
                    bail!(
                        "light[{i}].file: '{}' has negative or non-finite pixels",
                        path.display()
                    );
                }
                let texels: Vec<Vec3> = image.pixels.iter().map(|&c| c * *scale).collect();
                // The pixels are finite and ≥ 0 and so is the scale: only overflow is left.
                let brightest = texels.iter().fold(0.0f32, |m, c| m.max(c.max_element()));
                if brightest > MAX_LIGHT {
                    bail!(
                        "light[{i}]: scale × the brightest pixel of '{}' is {brightest:e}, too large (at most {MAX_LIGHT:e})",
                        path.display()
                    );
                }
                let up = scene_check::unit(&format!("light[{i}].up"), *up)?;
                environment.map = Some(
                    EnvMap::new(image.width as usize, image.height as usize, texels)
                        .oriented(up, rotation_deg.to_radians()),
                );
            }
            LightFile::Directional {
                direction,
                irradiance,
            } => lights.directional.push(DirectionalLight {
                to_light: -scene_check::unit(&format!("light[{i}].direction"), *direction)?,
                irradiance: irradiance.rgb(),
            }),
        }
    }
    lights.environment = environment;
    Ok(lights)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::medium::Filter;

    const MINIMAL: &str = r#"
[camera]
position = [0, 0, 10]
target = [0, 0, 0]
fov_deg = 40
width = 8
height = 8
[medium]
vdb = "x.vdb"
"#;

    fn parse(extra: &str) -> Result<SceneFile> {
        let f = SceneFile::parse(&format!("{MINIMAL}{extra}"), Path::new("t.toml"))?;
        f.validate()?;
        Ok(f)
    }

    #[test]
    fn minimal_scene_has_defaults() {
        let f = parse("").unwrap();
        assert_eq!(f.render.spp, 64);
        assert_eq!(f.medium.filter, Filter::Trilinear);
        assert!(f.light.is_empty());
    }

    #[test]
    fn lights_accept_grey_and_rgb() {
        let f = parse("[[light]]\ntype = \"constant\"\nradiance = [1, 0.5, 0]\n[[light]]\ntype = \"directional\"\ndirection = [0, -1, 0]\nirradiance = 3\n").unwrap();
        assert_eq!(f.light.len(), 2);
    }

    /// A scene file's `up` and `rotation_deg` reach the map: Blender's world (z up, turned a
    /// quarter) shows each direction the texel Cycles' own formula picks
    /// (`lights::tests::up_z_turned_a_quarter_reads_the_map_as_blender_does`).
    #[test]
    fn an_envmap_turns_as_its_scene_file_says() {
        let dir = std::env::temp_dir().join(format!("volgrad-envmap-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (w, h) = (8u32, 4u32);
        let mut image = crate::io::images::RgbImage::new(w, h);
        for (i, p) in image.pixels.iter_mut().enumerate() {
            *p = Vec3::splat(i as f32 + 1.0);
        }
        crate::io::images::write_exr(&dir.join("sky.exr"), &image, false).unwrap();
        let text =
            "[[light]]\ntype = \"envmap\"\nfile = \"sky.exr\"\nup = [0, 0, 1]\nrotation_deg = 90\n";
        let f = parse(text).unwrap();
        let lights = load_lights(&f.light, &dir).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        for d in [
            [1.0, 0.2, 0.3],
            [-0.3, 0.9, -0.5],
            [0.1, -1.0, 0.8],
            [-1.0, -0.4, -0.1],
        ] {
            let d = Vec3::from(d).normalize();
            let u = (0.5 - d.y.atan2(d.x) / std::f32::consts::TAU).rem_euclid(1.0);
            let v = d.z.acos() / std::f32::consts::PI;
            let texel = (v * h as f32) as u32 * w + (u * w as f32) as u32;
            assert_eq!(
                lights.environment.eval(d),
                Vec3::splat(texel as f32 + 1.0),
                "{d}"
            );
        }
    }

    #[test]
    fn errors_name_the_key() {
        let cases = [
            ("[render]\nspp = 0\n", "render.spp"),
            ("[render]\nmajorant = \"fast\"\n", "majorant"),
            (
                "[[light]]\ntype = \"constant\"\nradiance = -1\n",
                "light[0].radiance",
            ),
            (
                "[[light]]\ntype = \"constant\"\nradiance = 1\ncolour = 2\n",
                "colour",
            ),
            ("[[light]]\ntype = \"spot\"\n", "spot"),
            (
                "[[light]]\ntype = \"directional\"\ndirection = [0, 0, 0]\nirradiance = 1\n",
                "light[0].direction",
            ),
            ("[render]\nsamples = 3\n", "samples"),
            (
                "[[light]]\ntype = \"envmap\"\nfile = \"sky.exr\"\nup = [0, 0, 0]\n",
                "light[0].up",
            ),
            (
                "[[light]]\ntype = \"envmap\"\nfile = \"sky.exr\"\nrotation_deg = inf\n",
                "light[0].rotation_deg",
            ),
        ];
        for (extra, key) in cases {
            let err = format!("{:#}", parse(extra).unwrap_err());
            assert!(
                err.contains(key),
                "error for {extra:?} does not name {key}: {err}"
            );
        }
        let bad_medium = [
            ("density_scale = -1", "medium.density_scale"),
            ("phase_g = 1.0", "medium.phase_g"),
            ("albedo = 1.5", "medium.albedo"),
            ("albedo = [0.5, 2, 0.5]", "medium.albedo"),
            ("grid = \"a\"\ngrid_index = 1", "grid_index"),
            ("filter = \"cubic\"", "cubic"),
            ("unknown_key = 1", "unknown_key"),
        ];
        for (line, key) in bad_medium {
            let text = MINIMAL.replace("vdb = \"x.vdb\"", &format!("vdb = \"x.vdb\"\n{line}"));
            let err =
                SceneFile::parse(&text, Path::new("t.toml")).and_then(|f| f.validate().map(|_| f));
            let err = format!("{:#}", err.unwrap_err());
            assert!(
                err.contains(key),
                "error for {line:?} does not name {key}: {err}"
            );
        }
        for (from, to, key) in [
            ("width = 8", "width = 0", "camera.width"),
            ("fov_deg = 40", "fov_deg = 180", "camera.fov_deg"),
            (
                "fov_deg = 40",
                "fov_deg = 1e-44",
                "camera.fov_deg = 1e-44 is too narrow",
            ),
            ("target = [0, 0, 0]", "target = [0, 0, 10]", "camera.target"),
        ] {
            let err = SceneFile::parse(&MINIMAL.replace(from, to), Path::new("t.toml"))
                .unwrap()
                .validate()
                .unwrap_err();
            assert!(format!("{err}").contains(key), "{err}");
        }
    }
}
