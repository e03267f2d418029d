//! `Camera`: a pinhole camera given by look-at and field of view, by full intrinsics, or read
//! from a `transforms.json` or a COLMAP text model; every one passes the checks a scene file's
//! camera passes.

use std::path::PathBuf;

use glam::DVec3;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use volgrad::capture::{colmap, transforms};
use volgrad::optimize::views::Orbit;
use volgrad::render::camera::{Camera as RustCamera, Intrinsics};
use volgrad::render::scene::CameraFile;
use volgrad::render::scene_check::calibrated_camera;

use crate::errors::{check_path, narrow, OrRaise};

/// A pinhole camera. `fov_deg` is the horizontal field of view (40° by default); `fx`, `fy` (one
/// alone for square pixels), `cx`, `cy` (pixels, (0, 0) the top-left corner of the image) give
/// full intrinsics instead: a focal length in pixels and a field of view together are refused.
#[pyclass(name = "Camera", module = "volgrad", frozen, from_py_object)]
#[derive(Clone)]
pub struct Camera {
    pub camera: RustCamera,
}

#[pymethods]
impl Camera {
    #[new]
    #[pyo3(signature = (position, target, up = [0.0, 1.0, 0.0], fov_deg = None, width = 64, height = 64, fx = None, fy = None, cx = None, cy = None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        position: [f32; 3],
        target: [f32; 3],
        up: [f32; 3],
        fov_deg: Option<f64>,
        width: u32,
        height: u32,
        fx: Option<f64>,
        fy: Option<f64>,
        cx: Option<f64>,
        cy: Option<f64>,
    ) -> PyResult<Self> {
        let narrow = |key, value: Option<f64>| value.map(|v| narrow(key, v)).transpose();
        let (fov_deg, fx, fy) = (
            narrow("fov_deg", fov_deg)?,
            narrow("fx", fx)?,
            narrow("fy", fy)?,
        );
        let (cx, cy) = (narrow("cx", cx)?, narrow("cy", cy)?);
        if fov_deg.is_some() && (fx.is_some() || fy.is_some()) {
            return Err(PyValueError::new_err(
                "the focal length is either fov_deg or fx/fy (in pixels), not both",
            ));
        }
        // A focal length given alone stands for both (square pixels): name the one given.
        for (key, focal) in [("fx", fx), ("fy", fy)] {
            if let Some(f) = focal.filter(|f| !(*f > 0.0 && f.is_finite())) {
                return Err(PyValueError::new_err(format!(
                    "the focal length {key} must be a finite number of pixels > 0 (got {f})"
                )));
            }
        }
        let fov_deg = fov_deg.unwrap_or(40.0);
        let file = CameraFile {
            position,
            target,
            up,
            fov_deg,
            width,
            height,
        };
        let camera = if fx.is_none() && fy.is_none() && cx.is_none() && cy.is_none() {
            file.validate().and_then(|_| file.camera())
        } else {
            let fov = Intrinsics::from_fov(fov_deg, width, height);
            let focal = fx.or(fy);
            let k = Intrinsics {
                fx: fx.or(focal).unwrap_or(fov.fx),
                fy: fy.or(focal).unwrap_or(fov.fy),
                cx: cx.unwrap_or(fov.cx),
                cy: cy.unwrap_or(fov.cy),
            };
            let [p, t, u] = [position, target, up].map(|v| DVec3::from(v.map(f64::from)));
            calibrated_camera(p, t - p, u, k, width, height)
        };
        Ok(Camera {
            camera: camera.or_raise()?,
        })
    }

    /// The cameras of a NeRF / instant-ngp `transforms.json` (intrinsics per file or per frame,
    /// `scale` and `offset` applied), in frame order.
    #[staticmethod]
    fn from_transforms(path: PathBuf) -> PyResult<Vec<Camera>> {
        check_path(&path, "path")?;
        let views = transforms::read(&path).or_raise()?;
        Ok(views
            .into_iter()
            .map(|v| Camera { camera: v.camera })
            .collect())
    }

    /// The cameras of a COLMAP text model (`cameras.txt` and `images.txt` in `model`), in
    /// `images.txt`'s order; `images` is the folder its image names are relative to.
    #[staticmethod]
    #[pyo3(signature = (model, images = None))]
    fn from_colmap(model: PathBuf, images: Option<PathBuf>) -> PyResult<Vec<Camera>> {
        check_path(&model, "model")?;
        if let Some(images) = &images {
            check_path(images, "images")?;
        }
        let images = images.unwrap_or_else(|| model.clone());
        let views = colmap::read(&model, &images).or_raise()?;
        Ok(views
            .into_iter()
            .map(|v| Camera { camera: v.camera })
            .collect())
    }

    /// `count` cameras on a Fibonacci spiral at `distance` from `centre`, between the elevations
    /// `elevation_deg` above the plane normal to `up`: a run file's `[views.orbit]`, the same
    /// cameras.
    #[staticmethod]
    #[pyo3(signature = (count, distance, centre = [0.0, 0.0, 0.0], elevation_deg = (-30.0, 70.0), fov_deg = 40.0, width = 64, height = 64, azimuth_offset_deg = 0.0, up = [0.0, 1.0, 0.0]))]
    #[allow(clippy::too_many_arguments)]
    fn orbit(
        count: u32,
        distance: f64,
        centre: [f32; 3],
        elevation_deg: (f32, f32),
        fov_deg: f64,
        width: u32,
        height: u32,
        azimuth_offset_deg: f64,
        up: [f32; 3],
    ) -> PyResult<Vec<Camera>> {
        let distance = narrow("distance", distance)?;
        let fov_deg = narrow("fov_deg", fov_deg)?;
        let azimuth_offset_deg = narrow("azimuth_offset_deg", azimuth_offset_deg)?;
        let orbit = Orbit {
            count,
            elevation_deg,
            distance,
            fov_deg,
            width,
            height,
            azimuth_offset_deg,
            up,
        };
        let cameras = orbit.cameras(glam::Vec3::from(centre)).or_raise()?;
        Ok(cameras
            .into_iter()
            .map(|camera| Camera { camera })
            .collect())
    }

    #[getter]
    fn width(&self) -> u32 {
        self.camera.width
    }

    #[getter]
    fn height(&self) -> u32 {
        self.camera.height
    }

    #[getter]
    fn position(&self) -> [f32; 3] {
        self.camera.position.to_array()
    }

    /// (fx, fy, cx, cy) in pixels.
    #[getter]
    fn intrinsics(&self) -> (f32, f32, f32, f32) {
        let k = self.camera.intrinsics();
        (k.fx, k.fy, k.cx, k.cy)
    }

    fn __repr__(&self) -> String {
        let (c, k) = (&self.camera, self.camera.intrinsics());
        format!(
            "Camera(position={:?}, {}×{}, fx={:.2}, fy={:.2}, cx={:.2}, cy={:.2})",
            c.position.to_array(),
            c.width,
            c.height,
            k.fx,
            k.fy,
            k.cx,
            k.cy
        )
    }
}
