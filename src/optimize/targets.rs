//! The views of a run file: its cameras (listed `[[view]]`s and orbits), then the image each
//! should see, read from its file or rendered from the truth. Cameras come first, so that what
//! they decide (the levels follow the finest view's pixel footprint) is known before any target
//! is rendered.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use glam::Vec3;

use crate::capture::{colmap, pictures, transforms};
use crate::cluster::images::{render_alpha_shared, render_shared, sum_image};
use crate::cluster::Cluster;
use crate::io::images::{self, ColorSpace, RgbImage};
use crate::optimize::run_file::RunFile;
use crate::optimize::target_cache::TargetCache;
use crate::optimize::view_files::{view_tables, ViewFile, ViewSetFile};
use crate::optimize::views::MAX_VIEWS;
use crate::render::camera::Camera;
use crate::render::image::RenderOptions;
use crate::render::lights::{Environment, Lights};
use crate::render::sampling::TARGET_SEED_SALT;
use crate::render::scene::{load_lights, CameraFile, Scene};
use crate::render::scene_check;
use crate::render::scene_file::LightFile;

/// A camera, the lights it saw the medium under and the image it should see.
#[derive(Clone)]
pub struct View {
    pub camera: Camera,
    /// Its lights: an index into the run's `LightSets` (0: the scene's).
    pub light_set: usize,
    /// A held-out view under lights no training view had: it measures the volume relit.
    pub relit: bool,
    pub target: RgbImage,
    /// Its alpha target (grey, `render::alpha`): the picture's alpha channel, or rendered from
    /// the truth when the run fits alpha; `None` without.
    pub alpha: Option<RgbImage>,
    /// The part of `target` that is the environment seen through the medium, where a picture
    /// with alpha was composited over it (`pictures::background_seen`).
    pub background: Option<RgbImage>,
    /// The capture its picture was taken in: an index into `Problem::captures`, whose fitted
    /// exposure it is compared at.
    pub capture: usize,
}

impl View {
    /// The target of a capture whose exposure is `exposure` (k) times the scene's: a picture
    /// with alpha holds k × the medium's light, composited over the scene's environment at its
    /// own brightness, so its background part must be k times brighter too. The target as it
    /// is otherwise.
    pub fn target_at(&self, exposure: f32) -> std::borrow::Cow<'_, RgbImage> {
        match &self.background {
            Some(background) if exposure != 1.0 => {
                let mut target = self.target.clone();
                (target.pixels.iter_mut())
                    .zip(&background.pixels)
                    .for_each(|(t, b)| *t += (exposure - 1.0) * *b);
                std::borrow::Cow::Owned(target)
            }
            _ => std::borrow::Cow::Borrowed(&self.target),
        }
    }
}

/// A camera of the run file, before its target is known.
pub struct ViewSpec {
    /// What errors call it: `view[2]`, `holdouts.orbit[0] camera 3`.
    pub name: String,
    pub camera: Camera,
    /// Its own lights (empty: the scene's).
    pub light: Vec<LightFile>,
    /// The target image's file.
    pub image: Option<PathBuf>,
    /// How its stored values decode to radiance (default: as the file says; see `io::images`).
    pub color_space: Option<ColorSpace>,
    /// Its set's capture (`ViewSetFile::capture`; "" unnamed).
    pub capture: String,
}

/// The distinct sets of lights a run's views were taken under; set 0 is the scene's own.
pub struct LightSets {
    files: Vec<Vec<LightFile>>,
    pub lights: Vec<Lights>,
}

impl LightSets {
    pub fn new(scene_lights: Lights) -> Self {
        LightSets {
            files: vec![Vec::new()],
            lights: vec![scene_lights],
        }
    }

    /// The index of a view's lights (checked by the run file), loaded the first time they are
    /// seen; an environment map's file is relative to the run file's folder `dir`.
    fn index(&mut self, files: &[LightFile], dir: &Path) -> Result<usize> {
        if let Some(i) = self.files.iter().position(|f| f == files) {
            return Ok(i);
        }
        self.lights.push(load_lights(files, dir)?);
        self.files.push(files.to_vec());
        Ok(self.lights.len() - 1)
    }
}

/// The cameras of every set of one kind (`key` is "view" or "holdout"): its listed views, orbits,
/// transforms files and COLMAP models, checked to lie outside the unknown's `world_box` (`None`
/// while it is not known: the box is being found from these cameras, and there are no orbits
/// around it).
pub fn view_specs(
    run_path: &Path,
    key: &str,
    listed: &[ViewFile],
    sets: &[ViewSetFile],
    world_box: Option<(Vec3, Vec3)>,
) -> Result<Vec<ViewSpec>> {
    let mut specs = Vec::new();
    for (key, name, listed, set) in view_tables(key, listed, sets) {
        specs.extend(set_specs(run_path, key, &name, listed, set, world_box)?);
    }
    Ok(specs)
}

/// What makes two paths one file: the device and inode (so that hard links, symbolic links and
/// `a/../b` agree), or the path where the file cannot be asked (it is then refused later).
#[derive(PartialEq, Eq, Hash)]
enum FileIdentity {
    Inode(u64, u64),
    Path(PathBuf),
}

impl FileIdentity {
    fn of(path: &Path) -> Self {
        #[cfg(unix)]
        if let Ok(meta) = std::fs::metadata(path) {
            use std::os::unix::fs::MetadataExt;
            return FileIdentity::Inode(meta.dev(), meta.ino());
        }
        FileIdentity::Path(path.canonicalize().unwrap_or_else(|_| path.to_path_buf()))
    }
}

/// An error if two views name one picture (as one file, however its path is written): a
/// held-out view the fit was trained on scores the fit against its own targets, and a picture
/// listed twice weighs twice (in the fit, or in the held-out score).
pub fn refuse_shared_pictures(training: &[ViewSpec], held_out: &[ViewSpec]) -> Result<()> {
    let mut seen: HashMap<FileIdentity, (&str, bool)> = HashMap::new();
    let views = (training.iter().map(|s| (s, true))).chain(held_out.iter().map(|s| (s, false)));
    for (spec, is_training) in views {
        let Some(image) = &spec.image else { continue };
        let key = FileIdentity::of(image);
        if let Some((first, first_is_training)) = seen.insert(key, (&spec.name, is_training)) {
            let why = match (first_is_training, is_training) {
                (true, false) => " (a held-out view must be a picture no training view uses)",
                _ => "",
            };
            bail!(
                "{first} and {} name the same picture '{}'{why}: list each picture once",
                spec.name,
                image.display()
            );
        }
    }
    Ok(())
}

/// `view_specs` of one set, named `set_name` in messages.
fn set_specs(
    run_path: &Path,
    key: &str,
    set_name: &str,
    listed: &[ViewFile],
    set: &ViewSetFile,
    world_box: Option<(Vec3, Vec3)>,
) -> Result<Vec<ViewSpec>> {
    let orbits = &set.orbit;
    let capture = set.capture.clone().unwrap_or_default();
    let mut specs = Vec::new();
    for (i, v) in listed.iter().enumerate() {
        let name = format!("{key}[{i}]");
        let file = CameraFile {
            position: v.position,
            target: v.target,
            up: v.up,
            fov_deg: v.fov_deg,
            width: v.width,
            height: v.height,
        };
        let camera = file
            .validate()
            .and_then(|_| file.camera())
            .with_context(|| name.clone())?;
        specs.push(ViewSpec {
            name,
            camera,
            light: v.light.clone(),
            image: v.image.as_ref().map(|i| RunFile::resolve(run_path, i)),
            color_space: set.color_space,
            capture: capture.clone(),
        });
    }
    let mut captured = Vec::new();
    if let Some(file) = &set.transforms {
        let path = RunFile::resolve(run_path, file);
        let views = transforms::read(&path).with_context(|| format!("{set_name}.transforms"))?;
        captured.push(("transforms", views));
    }
    if let Some(colmap) = &set.colmap {
        let model = RunFile::resolve(run_path, &colmap.model);
        let images = match &colmap.images {
            Some(images) => RunFile::resolve(run_path, images),
            None => colmap::default_images(&model),
        };
        let views = colmap::read(&model, &images).with_context(|| format!("{set_name}.colmap"))?;
        captured.push(("colmap", views));
    }
    for (source, views) in captured {
        if views.len() as u64 > MAX_VIEWS {
            bail!(
                "{set_name}.{source}: {} cameras; at most {MAX_VIEWS} views per set",
                views.len()
            );
        }
        for (i, v) in views.into_iter().enumerate() {
            specs.push(ViewSpec {
                name: format!("{set_name}.{source} camera {i}"),
                camera: v.camera,
                light: set.light.clone(),
                image: v.image,
                color_space: set.color_space,
                capture: capture.clone(),
            });
        }
    }
    for (k, o) in orbits.iter().enumerate() {
        let name = if orbits.len() == 1 {
            format!("{set_name}.orbit")
        } else {
            format!("{set_name}.orbit[{k}]")
        };
        let (lo, hi) = world_box.with_context(|| {
            format!("{name}: orbits circle the unknown's box, which bounds = \"views\" finds from the listed cameras; list the cameras instead")
        })?;
        let centre = (lo + hi) / 2.0;
        let cameras = o.orbit().cameras(centre).with_context(|| name.clone())?;
        for (i, camera) in cameras.into_iter().enumerate() {
            specs.push(ViewSpec {
                name: format!("{name} camera {i}"),
                camera,
                light: o.light.clone(),
                image: None,
                color_space: None,
                capture: capture.clone(),
            });
        }
    }
    let Some((lo, hi)) = world_box else {
        return Ok(specs);
    };
    for spec in &specs {
        let p = spec.camera.position;
        if p.cmpge(lo).all() && p.cmple(hi).all() {
            bail!(
                "{}: the camera at {p} is inside the unknown's box from {lo} to {hi} (move it out, or for an orbit raise `distance`)",
                spec.name,
            );
        }
    }
    Ok(specs)
}

/// A view of the run file with its lights resolved and its target image read, if it has one.
pub struct ReadView {
    name: String,
    camera: Camera,
    light_set: usize,
    target: Option<RgbImage>,
    alpha: Option<RgbImage>,
    background: Option<RgbImage>,
    capture: String,
}

impl ReadView {
    pub fn camera(&self) -> Camera {
        self.camera
    }

    /// What the view was read as (its name, camera, lights and pictures) as a fingerprint, named
    /// for a message that says it differs between ranks.
    pub fn fingerprint(&self) -> (String, u64) {
        let mut f = crate::io::fingerprint::Fingerprint::default();
        f.text(&format!(
            "{} {:?} {}",
            self.name, self.camera, self.light_set
        ));
        for picture in [&self.target, &self.alpha, &self.background] {
            f.text(
                &picture
                    .as_ref()
                    .map_or("none".into(), crate::io::fingerprint::image),
            );
        }
        let name = format!("{}: its camera, lights or pictures", self.name);
        (name, f.value())
    }
}

/// The views of `specs` with their lights indexed in `sets` and their image files read: all that
/// can fail on one rank and not another (a file one node cannot read), done before any rank
/// renders with the others.
pub fn read_views(
    run_path: &Path,
    specs: Vec<ViewSpec>,
    sets: &mut LightSets,
) -> Result<Vec<ReadView>> {
    let dir = run_path.parent().unwrap_or(Path::new("."));
    let mut views = Vec::with_capacity(specs.len());
    for ViewSpec {
        name,
        camera,
        light,
        image,
        color_space,
        capture,
    } in specs
    {
        let light_set = sets.index(&light, dir).with_context(|| name.clone())?;
        let background = &sets.lights[light_set].environment;
        let picture = image
            .map(|file| read_target(&file, color_space, background, &camera, &name))
            .transpose()?;
        let (target, alpha, background) = match picture {
            Some(p) => (Some(p.target), p.alpha, p.background),
            None => (None, None, None),
        };
        views.push(ReadView {
            name,
            camera,
            light_set,
            target,
            alpha,
            background,
            capture,
        });
    }
    Ok(views)
}

/// The captures of the training views `training`, in order of first appearance: each has an
/// exposure of its own when one is fitted.
pub fn captures(training: &[ReadView]) -> Vec<String> {
    let mut names: Vec<String> = Vec::new();
    for v in training {
        if !names.contains(&v.capture) {
            names.push(v.capture.clone());
        }
    }
    names
}

/// A held-out view is compared at its capture's exposure (with `fit_exposure`, that capture's
/// fitted factor): a capture no training view was taken in has none, with or without the fit.
pub fn check_captures(held_out: &[ReadView], captures: &[String]) -> Result<()> {
    match held_out.iter().find(|v| !captures.contains(&v.capture)) {
        Some(v) => {
            let named = match v.capture.as_str() {
                "" => "the unnamed capture".to_string(),
                name => format!("capture \"{name}\""),
            };
            bail!(
                "{}: {named} is no training set's (give a held-out set the `capture` of the training set its pictures were taken with)",
                v.name
            )
        }
        None => Ok(()),
    }
}

/// Gives views their targets, rendering from the truth the ones no image gives (every rank its
/// share of the pixels).
pub struct TargetRenderer<'a> {
    /// The scene with the true grid; each render sets its camera.
    pub truth: Option<Scene>,
    pub spp: u32,
    pub seed: u64,
    pub progress: bool,
    /// Targets rendered so far, or read from the cache (each has its own random streams).
    pub rendered: u64,
    /// Of those, how many the cache held.
    pub cached: u64,
    /// Alpha targets rendered so far.
    pub rendered_alpha: u64,
    pub cache: Option<TargetCache>,
    pub cluster: &'a Cluster,
    /// Render alpha targets too (the run fits alpha) for the views no image gives.
    pub alpha: bool,
}

impl TargetRenderer<'_> {
    /// The views of `read` with their targets (`relit` still false), their captures indexed in
    /// `captures` (0 for a name not there: `check_captures` refuses it where it matters).
    /// Held-out views (`held_out`) must not be black everywhere: their score is a PSNR, relative
    /// to the target's brightest value.
    pub fn complete(
        &mut self,
        read: Vec<ReadView>,
        sets: &LightSets,
        captures: &[String],
        held_out: bool,
    ) -> Result<Vec<View>> {
        read.into_iter()
            .map(|v| {
                let capture = captures.iter().position(|c| *c == v.capture);
                let capture = capture.unwrap_or(0);
                let (target, alpha) = match v.target {
                    Some(image) => (image, v.alpha),
                    None => {
                        let lights = &sets.lights[v.light_set];
                        let target = self.render(&v.camera, lights, &v.name)?;
                        let alpha = self.alpha.then(|| self.render_alpha(&v.camera));
                        (target, alpha.transpose()?)
                    }
                };
                if held_out && target.pixels.iter().all(|c| c.max_element() <= 0.0) {
                    bail!(
                        "{}: the held-out target is black everywhere, so its PSNR (relative to the target's brightest value) is undefined: light what it sees, or leave it out",
                        v.name
                    );
                }
                Ok(View {
                    camera: v.camera,
                    light_set: v.light_set,
                    relit: false,
                    target,
                    alpha,
                    background: v.background,
                    capture,
                })
            })
            .collect()
    }

    /// The truth's alpha seen by `camera`, every rank its share (cheap beside a colour render:
    /// not cached).
    fn render_alpha(&mut self, camera: &Camera) -> Result<RgbImage> {
        let truth = self.truth.as_mut().context("checked by the caller")?;
        truth.camera = *camera;
        self.rendered_alpha += 1;
        let options = RenderOptions {
            spp: self.spp,
            seed: self.seed
                ^ TARGET_SEED_SALT
                ^ self.rendered_alpha.wrapping_mul(0x9e37_79b9_7f4a_7c15),
            max_depth: 1,
            progress: false,
        };
        Ok(render_alpha_shared(self.cluster, truth, &options))
    }

    fn render(&mut self, camera: &Camera, lights: &Lights, name: &str) -> Result<RgbImage> {
        let truth = self
            .truth
            .as_mut()
            .with_context(|| format!("{name}: no image and no truth to render one from"))?;
        truth.camera = *camera;
        truth.lights = lights.clone();
        self.rendered += 1;
        let options = RenderOptions {
            spp: self.spp,
            seed: self.seed ^ TARGET_SEED_SALT ^ self.rendered.wrapping_mul(0x9e37_79b9_7f4a_7c15),
            max_depth: truth.settings.max_depth,
            progress: self.progress,
        };
        let key = self.cache.as_ref().map(|cache| cache.key(truth, &options));
        if let Some(image) = cached(self.cache.as_ref(), self.cluster, key.as_deref(), camera) {
            self.cached += 1;
            return Ok(image);
        }
        let image = render_shared(self.cluster, truth, &options).0;
        if let (Some(cache), Some(key)) = (&self.cache, &key) {
            let cluster = self.cluster;
            cluster.agree(cluster.on_root(|| cache.write(key, &image)))?;
        }
        Ok(image)
    }
}

/// The cache's entry `key`, if it holds one. Only rank 0 reads it (the folder need not be shared
/// between machines) and sends its pixels to the others.
fn cached(
    cache: Option<&TargetCache>,
    cluster: &Cluster,
    key: Option<&str>,
    camera: &Camera,
) -> Option<RgbImage> {
    let (cache, key) = (cache?, key?);
    let mine = cluster.is_root().then(|| cache.read(key, camera)).flatten();
    let [held] = cluster.max_each([f64::from(u8::from(mine.is_some()))]);
    if held == 0.0 {
        return None;
    }
    // x + 0 = x: the sum over ranks gives every rank rank 0's pixels, bit for bit.
    let mut image = mine.unwrap_or_else(|| RgbImage::new(camera.width, camera.height));
    sum_image(cluster, &mut image);
    Some(image)
}

/// A picture read as a target: composited over the view's environment (`pictures::over`), its
/// alpha as a grey image, and the environment's part of the composite.
struct TargetPicture {
    target: RgbImage,
    alpha: Option<RgbImage>,
    background: Option<RgbImage>,
}

/// A target image from its file, decoded to radiance and, where it has alpha, composited over the
/// view's `background`: the view's size, finite pixels.
fn read_target(
    path: &Path,
    color_space: Option<ColorSpace>,
    background: &Environment,
    camera: &Camera,
    name: &str,
) -> Result<TargetPicture> {
    let picture =
        images::read_picture(path, color_space).with_context(|| format!("{name}.image"))?;
    let target = pictures::over(&picture, background, camera);
    if (target.width, target.height) != (camera.width, camera.height) {
        bail!(
            "{name}.image: '{}' is {}×{} but the view is {}×{}",
            path.display(),
            target.width,
            target.height,
            camera.width,
            camera.height
        );
    }
    let what = format!("{name}.image: '{}'", path.display());
    scene_check::radiance_pixels(&what, &target.pixels)?;
    let alpha = picture.alpha.as_ref().map(|alpha| RgbImage {
        pixels: alpha.iter().map(|&a| Vec3::splat(a)).collect(),
        ..target.clone()
    });
    Ok(TargetPicture {
        alpha,
        background: pictures::background_seen(&picture, background, camera),
        target,
    })
}

/// The targets' mean squared channel value, each channel clipped to ±`clip`.
pub fn mean_square(views: &[View], clip: f32) -> f64 {
    let (sum, count) = views.iter().fold((0.0, 0usize), |(s, n), v| {
        let power: f64 = (v.target.pixels.iter())
            // In f64: a channel of 1e20 squares beyond f32.
            .map(|c| {
                c.clamp(Vec3::splat(-clip), Vec3::splat(clip))
                    .as_dvec3()
                    .length_squared()
            })
            .sum();
        (s + power, n + 3 * v.target.pixels.len())
    });
    sum / count.max(1) as f64
}

/// The brightest training targets a reconstruction takes: P up to 10¹⁸, pixels near 10⁹ (a sky
/// in cd/m² is near 10⁴). The priors' weights scale with P, and beyond it they, and then a step's
/// gradient, outgrow what the optimiser holds of their squares: the run stood still or fitted
/// nothing. The scale is the user's to choose: a reconstruction does not depend on it.
const MAX_IMAGE_POWER: f64 = 1e18;

/// The targets' mean squared pixel value per channel: the L2 loss of a black image (P of
/// `scene_units`); an error beyond `MAX_IMAGE_POWER`.
pub fn image_power(views: &[View]) -> Result<f64> {
    let power = mean_square(views, f32::INFINITY);
    if power.is_nan() || power > MAX_IMAGE_POWER {
        let brightest = (views.iter().enumerate())
            .flat_map(|(i, v)| v.target.pixels.iter().map(move |c| (c.max_element(), i)))
            .fold((f32::MIN, 0), |a, b| if b.0 > a.0 { b } else { a });
        bail!(
            "the training targets' mean squared value is {power:.3e}, above {MAX_IMAGE_POWER:e}, where the optimiser's squares overflow \
             (the brightest pixel, {:.1e}, is in training view {} of {}): scale the scene's lights and the pictures down by one factor \
             (pictures with alpha are composited over the scene's sky, which follows its lights); a reconstruction does not depend on their scale",
            brightest.0,
            brightest.1 + 1,
            views.len()
        );
    }
    Ok(power)
}
