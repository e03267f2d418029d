//! Pictures and cameras from elsewhere: images as targets (alpha composited over the scene's
//! background; their colour decoding is `io::images`'), and camera sets as other tools export
//! them (`transforms.json`, COLMAP's text model). Uses `io` and `render` (cameras and their
//! checks); `optimize` reads its views through it.

use std::path::PathBuf;

use crate::render::camera::Camera;

pub mod colmap;
pub mod pictures;
pub mod transforms;

/// A camera of an exported camera set, and its image if the set names one.
pub struct CapturedView {
    pub camera: Camera,
    pub image: Option<PathBuf>,
}

/// A number from a camera file as a message quotes it: as written for most, in exponent form
/// where the plain form runs long (`1e-300`, not three hundred digits).
fn quoted_number(v: f64) -> String {
    let plain = v.to_string();
    if plain.len() > 16 {
        format!("{v:e}")
    } else {
        plain
    }
}

/// An error if two views name one image (as one file, however its path is written): a picture
/// listed twice would weigh twice in the fit, and is more likely a mistake in the export than a
/// wish. `what` names a view by its index.
pub(crate) fn refuse_repeated_images(
    views: &[CapturedView],
    what: impl Fn(usize) -> String,
) -> anyhow::Result<()> {
    let mut seen = std::collections::HashMap::new();
    for (i, view) in views.iter().enumerate() {
        let Some(image) = &view.image else { continue };
        let key = image.canonicalize().unwrap_or_else(|_| image.clone());
        if let Some(first) = seen.insert(key, i) {
            anyhow::bail!(
                "{} and {} name the same image '{}': list each picture once",
                what(first),
                what(i),
                image.display()
            );
        }
    }
    Ok(())
}
