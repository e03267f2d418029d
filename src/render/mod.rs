//! The forward renderer: scene files, camera, lights, sampling, the path loop (`path`) and the
//! image loop (`image`) over all pixels or a set of them (`pixel_set`). Uses `volume` and `io`.

pub mod alpha;
pub mod camera;
pub mod fingerprint;
pub mod image;
pub mod interrupt;
pub mod lights;
pub mod medium_grids;
pub mod path;
pub mod pixel_set;
pub mod sampling;
pub mod scene;
pub mod scene_check;
pub mod scene_file;
