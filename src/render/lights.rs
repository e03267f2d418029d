//! Lights: an environment (a constant radiance plus an optional lat-long map, importance-sampled)
//! and directional lights (suns, given by the direction their light travels and their irradiance).

use std::f32::consts::PI;

use glam::{Mat3, Quat, Vec3};

use crate::render::sampling::{uniform_sphere, Distribution1D, UNIFORM_SPHERE_PDF};

/// A lat-long environment map. In its own frame it is y up, in Mitsuba 3's orientation:
/// u = atan2(x, −z)/2π, v = θ/π with θ measured from +y; `oriented` turns that frame in the world.
/// Texels are piecewise constant, and so is the sampling density.
#[derive(Clone)]
pub struct EnvMap {
    width: usize,
    height: usize,
    texels: Vec<Vec3>,
    /// The map's frame in the world (its columns the map's x, y, z); none: the world's own.
    frame: Option<Mat3>,
    rows: Distribution1D,
    columns: Vec<Distribution1D>,
    /// The largest channel of any texel.
    brightest: f32,
}

pub fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

impl EnvMap {
    /// `texels` are RGB, rows top (θ = 0) to bottom.
    pub fn new(width: usize, height: usize, texels: Vec<Vec3>) -> Self {
        assert_eq!(texels.len(), width * height);
        let columns: Vec<Distribution1D> = (0..height)
            .map(|y| {
                let sin_theta = (PI * (y as f32 + 0.5) / height as f32).sin();
                let w: Vec<f32> = texels[y * width..(y + 1) * width]
                    .iter()
                    .map(|&c| luminance(c).max(0.0) * sin_theta)
                    .collect();
                Distribution1D::new(&w)
            })
            .collect();
        let rows = Distribution1D::new(&columns.iter().map(|c| c.total).collect::<Vec<_>>());
        let brightest = texels.iter().fold(0.0f32, |m, c| m.max(c.max_element()));
        EnvMap {
            width,
            height,
            texels,
            frame: None,
            rows,
            columns,
            brightest,
        }
    }

    /// The map with its top (+y of its frame) toward the unit vector `up` and then turned by
    /// `rotation` radians about `up`, right-handed (counter-clockwise seen from above). Its top
    /// is tilted onto `up` by the shortest turn, about y × up (about x when `up` is −y): with
    /// `up` = +z, u = 0 looks toward +y and u = 0.25 toward +x before the turn. A rotation keeps
    /// solid angles, so the sampling density is the map's own at the direction taken back.
    pub fn oriented(mut self, up: Vec3, rotation: f32) -> Self {
        let tilt = if up.dot(Vec3::Y) < -0.999_999 {
            Quat::from_rotation_x(PI)
        } else {
            Quat::from_rotation_arc(Vec3::Y, up)
        };
        let turn = Quat::from_axis_angle(up, rotation) * tilt;
        self.frame = (turn != Quat::IDENTITY).then(|| Mat3::from_quat(turn));
        self
    }

    /// The map's frame in the world (columns: its x, y, z), if `oriented` turned it.
    pub fn frame(&self) -> Option<Mat3> {
        self.frame
    }

    /// A world direction in the map's frame.
    #[inline]
    fn to_map(&self, dir: Vec3) -> Vec3 {
        self.frame.map_or(dir, |f| f.transpose() * dir)
    }

    /// (u, v) of a direction in the map's frame: u across, v down from the top row.
    fn uv(dir: Vec3) -> (f32, f32) {
        let u = (dir.x.atan2(-dir.z) / (2.0 * PI)).rem_euclid(1.0);
        let v = dir.y.clamp(-1.0, 1.0).acos() / PI;
        (u, v)
    }

    fn texel_of(&self, dir: Vec3) -> (usize, usize) {
        let (u, v) = Self::uv(dir);
        (
            ((u * self.width as f32) as usize).min(self.width - 1),
            ((v * self.height as f32) as usize).min(self.height - 1),
        )
    }

    fn direction(u: f32, v: f32) -> Vec3 {
        let (phi, theta) = (2.0 * PI * u, PI * v);
        Vec3::new(
            theta.sin() * phi.sin(),
            theta.cos(),
            -theta.sin() * phi.cos(),
        )
    }

    /// Width, height and the texels, rows top to bottom.
    pub fn texels(&self) -> (usize, usize, &[Vec3]) {
        (self.width, self.height, &self.texels)
    }

    pub fn eval(&self, dir: Vec3) -> Vec3 {
        let (x, y) = self.texel_of(self.to_map(dir));
        self.texels[y * self.width + x]
    }

    /// Solid-angle density of `sample` for `dir`: the texel's density in (u, v) over the Jacobian
    /// dω = 2π²·sin θ du dv at `dir`'s own θ (not its row's centre, which is only the weight the
    /// rows are drawn with: a map of a few rows spans much of θ in each).
    pub fn pdf(&self, dir: Vec3) -> f32 {
        let dir = self.to_map(dir);
        let (x, y) = self.texel_of(dir);
        // sin θ from the components across the axis, which keep their precision near the poles
        // (1 − cos²θ rounds to 0 there in f32). At a pole itself the density is unbounded: a
        // large one there gives the sample its limit, L/pdf → 0, instead of a division by 0.
        let sin_theta = (dir.x * dir.x + dir.z * dir.z).sqrt().max(1e-20);
        let p_uv = self.rows.bin_probability(y)
            * self.columns[y].bin_probability(x)
            * (self.width * self.height) as f32;
        p_uv / (2.0 * PI * PI * sin_theta)
    }

    pub fn sample(&self, u: [f32; 2]) -> Vec3 {
        let (y, dv) = self.rows.sample(u[0]);
        let (x, du) = self.columns[y].sample(u[1]);
        let local = Self::direction(
            (x as f32 + du) / self.width as f32,
            (y as f32 + dv) / self.height as f32,
        );
        self.frame.map_or(local, |f| f * local)
    }
}

/// Radiance arriving from infinitely far away in every direction.
#[derive(Default, Clone)]
pub struct Environment {
    pub constant: Vec3,
    pub map: Option<EnvMap>,
}

impl Environment {
    pub fn is_black(&self) -> bool {
        self.constant == Vec3::ZERO && self.map.is_none()
    }

    /// Radiance seen looking along `dir`.
    #[inline]
    pub fn eval(&self, dir: Vec3) -> Vec3 {
        self.constant + self.map.as_ref().map_or(Vec3::ZERO, |m| m.eval(dir))
    }

    /// Probability of picking the map (rather than uniform directions) when both exist.
    fn map_fraction(&self) -> f32 {
        match (&self.map, self.constant == Vec3::ZERO) {
            (None, _) => 0.0,
            (Some(_), true) => 1.0,
            (Some(_), false) => 0.5,
        }
    }

    /// Solid-angle density of `sample` for `dir`.
    #[inline]
    pub fn pdf(&self, dir: Vec3) -> f32 {
        if self.is_black() {
            return 0.0;
        }
        let f = self.map_fraction();
        let map_pdf = self.map.as_ref().map_or(0.0, |m| m.pdf(dir));
        f * map_pdf + (1.0 - f) * UNIFORM_SPHERE_PDF
    }

    /// A direction toward the environment; its density is `pdf(dir)`.
    #[inline]
    pub fn sample(&self, u: [f32; 3]) -> Vec3 {
        match &self.map {
            Some(m) if u[2] < self.map_fraction() => m.sample([u[0], u[1]]),
            _ => uniform_sphere([u[0], u[1]]),
        }
    }
}

/// A distant light with a single direction (a sun).
#[derive(Debug, Clone, Copy)]
pub struct DirectionalLight {
    /// Unit vector pointing toward the light (the opposite of the direction its light travels).
    pub to_light: Vec3,
    pub irradiance: Vec3,
}

#[derive(Default, Clone)]
pub struct Lights {
    pub environment: Environment,
    pub directional: Vec<DirectionalLight>,
}

impl Lights {
    /// The largest channel of any light: the environment's constant or brightest texel, a sun's
    /// irradiance (the scale of what a path can carry, `gradient::passes::sample_scale`).
    pub fn brightest(&self) -> f32 {
        let env = &self.environment;
        let map = env.map.as_ref().map_or(0.0, |m| m.brightest);
        (self.directional.iter())
            .map(|d| d.irradiance.max_element())
            .fold(env.constant.max_element().max(map), f32::max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::sampling::pixel_rng;
    use rand::Rng;

    #[test]
    fn envmap_pdf_matches_its_sampling_and_integrates_to_one() {
        // Maps of a few rows too: the pdf once took sin θ at the row's centre, which is exact
        // only for thin rows (a 1×1 map's ∫pdf was 2/π, and a furnace under it 14 % bright).
        for (w, h) in [(16, 8), (1, 1), (64, 1), (4, 2), (6, 3), (1, 64)] {
            check_envmap(w, h);
        }
    }

    #[test]
    fn a_turned_map_keeps_its_density() {
        let tilted = Vec3::new(1.0, -2.0, 0.5).normalize();
        for (up, rotation) in [(Vec3::Z, 1.3), (Vec3::NEG_Y, 0.0), (tilted, -2.0)] {
            check_envmap_turned(16, 8, up, rotation);
        }
    }

    fn check_envmap(w: usize, h: usize) {
        check_envmap_turned(w, h, Vec3::Y, 0.0);
    }

    fn check_envmap_turned(w: usize, h: usize, up: Vec3, rotation: f32) {
        let texels = (0..w * h)
            .map(|i| Vec3::splat(((i * 7919) % 13) as f32 + if i == 37 { 200.0 } else { 0.5 }))
            .collect();
        let map = EnvMap::new(w, h, texels).oriented(up, rotation);
        // ∫ pdf dω = 1, by stratified directions.
        let n = 400usize;
        let mut integral = 0.0f64;
        for i in 0..n {
            for j in 0..n {
                let dir =
                    uniform_sphere([(i as f32 + 0.5) / n as f32, (j as f32 + 0.5) / n as f32]);
                integral += map.pdf(dir) as f64;
            }
        }
        integral *= 4.0 * std::f64::consts::PI / (n * n) as f64;
        assert!((integral - 1.0).abs() < 0.01, "{w}×{h}: ∫pdf = {integral}");
        // E[L/pdf] over samples = ∫ L dω, the same as uniform estimation.
        let mut rng = pixel_rng(3, 0, 0);
        let m = 200_000;
        let importance: f64 = (0..m)
            .map(|_| {
                let d = map.sample([rng.gen(), rng.gen()]);
                (luminance(map.eval(d)) / map.pdf(d)) as f64
            })
            .sum::<f64>()
            / m as f64;
        let uniform: f64 = (0..m)
            .map(|_| {
                (luminance(map.eval(uniform_sphere([rng.gen(), rng.gen()]))) / UNIFORM_SPHERE_PDF)
                    as f64
            })
            .sum::<f64>()
            / m as f64;
        assert!(
            (importance / uniform - 1.0).abs() < 0.02,
            "{w}×{h}: importance {importance} vs uniform {uniform}"
        );
    }

    #[test]
    fn envmap_orientation_follows_mitsuba() {
        // u = 0 looks toward −z, u = 0.25 toward +x, v = 0 straight up.
        assert!((EnvMap::direction(0.0, 0.5) - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-6);
        assert!((EnvMap::direction(0.25, 0.5) - Vec3::X).length() < 1e-6);
        assert!((EnvMap::direction(0.3, 0.0) - Vec3::Y).length() < 1e-6);
    }

    /// `up = [0, 0, 1]`, `rotation_deg = 90` is Blender's world: Cycles' Environment Texture
    /// reads direction d at u = 0.5 − atan2(d.y, d.x)/2π and v = 1 − acos(d.z)/π from the
    /// bottom row (`direction_to_equirectangular` in Cycles' kernel), so acos(d.z)/π from the top.
    #[test]
    fn up_z_turned_a_quarter_reads_the_map_as_blender_does() {
        let map = EnvMap::new(1, 1, vec![Vec3::ONE]).oriented(Vec3::Z, 0.5 * PI);
        let mut rng = pixel_rng(5, 0, 0);
        for _ in 0..1000 {
            let d = uniform_sphere([rng.gen(), rng.gen()]);
            let (u, v) = EnvMap::uv(map.to_map(d));
            let u_cycles = (0.5 - d.y.atan2(d.x) / (2.0 * PI)).rem_euclid(1.0);
            let v_cycles = d.z.clamp(-1.0, 1.0).acos() / PI;
            let du = (u - u_cycles).abs();
            assert!(
                du.min(1.0 - du) < 1e-4 && (v - v_cycles).abs() < 1e-4,
                "{d}: ({u}, {v}) against Cycles' ({u_cycles}, {v_cycles})"
            );
        }
        // Unturned, the map is the world's own, to the bit.
        assert!(EnvMap::new(1, 1, vec![Vec3::ONE])
            .oriented(Vec3::Y, 0.0)
            .frame
            .is_none());
    }
}
