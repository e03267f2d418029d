//! Images in and out through OpenImageIO: linear EXR (half or float) and 8-bit sRGB PNG out; in,
//! any format OpenImageIO reads (PNG through `png_input`, in Rust), decoded to linear radiance
//! from the colour space it is encoded in, alpha kept.
//!
//! Which decoding applies: the caller's override (a view set's `color_space`) when given;
//! otherwise what the file declares (OpenImageIO's `oiio:ColorSpace`: sRGB, linear, or a gamma;
//! other primaries, by name or by OpenEXR's `chromaticities`, and curves such as a log are refused
//! rather than guessed); otherwise sRGB for integer-valued files (8 or 16 bits: what cameras, browsers and Blender's PNG
//! output mean) and linear for float ones (EXR, HDR). An 8-bit PNG taken as linear would be fitted
//! several times too bright: mid-grey 0.5 encodes radiance 0.21.
//!
//! Alpha: colour is made premultiplied (associated), as a renderer's image over a transparent
//! background is. PNG and TIFF store colour unassociated ("straight"), so the decoded colour is
//! multiplied by alpha; EXR stores it premultiplied already.

use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::io::bridge::ImageData;
use crate::io::bridge::{bridge_error, bridge_path, ffi};
use crate::io::png_input::{is_png, png_size, read_png};

/// A linear RGB image, rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<Vec3>,
}

impl RgbImage {
    pub fn new(width: u32, height: u32) -> Self {
        RgbImage {
            width,
            height,
            pixels: vec![Vec3::ZERO; width as usize * height as usize],
        }
    }

    /// Every pixel × `k` (k = 1 leaves the bits as they are).
    pub fn scale(&mut self, k: f32) {
        if k != 1.0 {
            self.pixels.iter_mut().for_each(|c| *c *= k);
        }
    }

    /// The pixelwise mean of two images of one size (two independent halves of a render's
    /// samples are one render).
    pub fn average(a: &RgbImage, b: &RgbImage) -> RgbImage {
        RgbImage {
            pixels: (a.pixels.iter().zip(&b.pixels))
                .map(|(x, y)| (*x + *y) * 0.5)
                .collect(),
            ..a.clone()
        }
    }

    /// a·(1 − t) + b·t, pixelwise, for images of one size (renders of n and m samples per pixel
    /// are one of n + m with t = m/(n + m)).
    pub fn blend(a: &RgbImage, b: &RgbImage, t: f32) -> RgbImage {
        RgbImage {
            pixels: (a.pixels.iter().zip(&b.pixels))
                .map(|(x, y)| x.lerp(*y, t))
                .collect(),
            ..a.clone()
        }
    }

    pub fn mean(&self) -> Vec3 {
        self.pixels.iter().copied().sum::<Vec3>() / self.pixels.len().max(1) as f32
    }

    fn to_data(&self, encode: impl Fn(f32) -> f32) -> ImageData {
        ImageData {
            width: self.width,
            height: self.height,
            channels: 3,
            pixels: self
                .pixels
                .iter()
                .flat_map(|c| c.to_array())
                .map(encode)
                .collect(),
            color_space: String::new(),
            stored_type: String::new(),
            alpha_channel: -1,
            channel_names: Vec::new(),
            alpha_unassociated: false,
            chromaticities: Vec::new(),
        }
    }
}

/// The sRGB transfer function (IEC 61966-2-1) of a linear value in [0, 1].
pub fn srgb_encode(linear: f32) -> f32 {
    let x = linear.clamp(0.0, 1.0);
    if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

/// The largest finite half float: larger values would be stored as infinite.
pub const HALF_MAX: f32 = 65504.0;

/// Writes a linear EXR, as half or float (refused if a value is beyond `HALF_MAX`).
pub fn write_exr(path: &Path, image: &RgbImage, half: bool) -> Result<()> {
    if half {
        let largest = (image.pixels.iter()).fold(0.0f32, |m, p| m.max(p.abs().max_element()));
        if largest > HALF_MAX {
            bail!(
                "'{}': the image holds values up to {largest:e}, beyond half floats' largest ({HALF_MAX}): store it as float",
                path.display()
            );
        }
    }
    ffi::write_image(
        bridge_path(path)?,
        &image.to_data(|v| v),
        if half { "half" } else { "float" },
    )
    .map_err(bridge_error)
}

/// Writes an 8-bit PNG: `exposure`·value, clamped, sRGB-encoded here (OpenImageIO does not).
pub fn write_png(path: &Path, image: &RgbImage, exposure: f32) -> Result<()> {
    let data = image.to_data(|v| srgb_encode(v * exposure));
    ffi::write_image(bridge_path(path)?, &data, "uint8").map_err(bridge_error)
}

/// Reads any image OpenImageIO opens as linear RGB (grey images are spread to three channels),
/// decoded as `read_picture` decodes it, colour premultiplied by any alpha.
pub fn read_rgb(path: &Path) -> Result<RgbImage> {
    Ok(read_picture(path, None)?.color)
}

/// How a picture's stored values map to linear radiance.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ColorSpace {
    /// Stored values are radiance.
    Linear,
    /// The sRGB transfer curve (IEC 61966-2-1).
    Srgb,
}

/// A decoded picture: linear colour, premultiplied by alpha where the picture has alpha.
pub struct Picture {
    pub color: RgbImage,
    /// Coverage per pixel (1: opaque), rows top to bottom; `None` without an alpha channel.
    pub alpha: Option<Vec<f32>>,
    /// What the stored colour was decoded from.
    pub decoded: Decoding,
}

/// The transfer curve a picture's colour was decoded with.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Decoding {
    Linear,
    Srgb,
    /// value^gamma, as a file that declares "Gamma2.2" asks.
    Gamma(f32),
}

impl Decoding {
    fn linear(self, stored: f32) -> f32 {
        match self {
            Decoding::Linear => stored,
            Decoding::Srgb => srgb_decode(stored),
            Decoding::Gamma(g) => stored.max(0.0).powf(g),
        }
    }
}

/// The inverse of the sRGB transfer function (IEC 61966-2-1): the linear value of an encoded one.
pub fn srgb_decode(encoded: f32) -> f32 {
    let x = encoded.clamp(0.0, 1.0);
    if x <= 0.040_45 {
        x / 12.92
    } else {
        ((x + 0.055) / 1.055).powf(2.4)
    }
}

/// Rec.709's (and sRGB's) primaries and D65 white, x and y of red, green, blue and white: the
/// primaries volgrad's RGB (its lights, albedos and renders) is in.
const REC709_CHROMATICITIES: [f32; 8] = [0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290];

/// Names a file may declare (OpenImageIO's `oiio:ColorSpace`, lower-cased) for sRGB's curve on
/// Rec.709's primaries, and for linear values on them.
const SRGB_NAMES: [&str; 5] = [
    "srgb",
    "srgb_texture",
    "srgb texture",
    "srgb_rec709_scene",
    "srgb_rec709_display",
];
const LINEAR_NAMES: [&str; 6] = [
    "linear",
    "lin_srgb",
    "lin_rec709",
    "lin_rec709_scene",
    "scene_linear",
    "linear rec.709 (srgb)",
];

/// The gammas a "GammaN" colour space is decoded with.
const MIN_GAMMA: f32 = 0.1;
const MAX_GAMMA: f32 = 10.0;

/// The decoding `override_space` or, without one, the file's declaration and storage ask for.
/// A file that declares other primaries (`chromaticities`, or a space such as ACEScg or Display
/// P3) or a curve volgrad does not decode (a log encoding) is refused rather than read as if it
/// were sRGB or linear Rec.709; an override takes its values as they are, whatever it declares.
fn decoding(
    declared: &str,
    stored_type: &str,
    chromaticities: &[f32],
    override_space: Option<ColorSpace>,
) -> Result<Decoding> {
    match override_space {
        Some(ColorSpace::Linear) => return Ok(Decoding::Linear),
        Some(ColorSpace::Srgb) => return Ok(Decoding::Srgb),
        None => {}
    }
    let convert = "convert it to sRGB or linear Rec.709 (as a run file's target, its view set's `color_space = \"linear\"` or `\"srgb\"` takes its values as they are instead)";
    if !chromaticities.is_empty() {
        let rec709 = chromaticities.len() == 8
            && (chromaticities.iter().zip(REC709_CHROMATICITIES))
                .all(|(&a, b)| (a - b).abs() <= 0.005);
        if !rec709 {
            bail!("it declares primaries (chromaticities {chromaticities:?}) other than Rec.709's and sRGB's, which volgrad's colours are in: {convert}");
        }
    }
    let name = declared.trim().to_ascii_lowercase();
    // OpenImageIO 2.4 labels every PNM file (PPM, PGM, PFM) "Rec709" whatever it holds: a label
    // that says nothing, read by the storage as an unlabelled file is.
    if name.is_empty() || name == "rec709" {
        let integer = stored_type.starts_with("uint") || stored_type.starts_with("int");
        return Ok(if integer {
            Decoding::Srgb
        } else {
            Decoding::Linear
        });
    }
    if SRGB_NAMES.contains(&name.as_str()) {
        return Ok(Decoding::Srgb);
    }
    if LINEAR_NAMES.contains(&name.as_str()) {
        return Ok(Decoding::Linear);
    }
    if let Some(g) = name
        .strip_prefix("gamma")
        .and_then(|g| g.trim().parse::<f32>().ok())
        .filter(|g| g.is_finite() && *g > 0.0)
    {
        // A PNG's gAMA chunk becomes "GammaN"; a damaged one (gAMA 1, N = 100000) would
        // darken or flatten every pixel. Displays' gammas lie near 1 to 3.
        if !(MIN_GAMMA..=MAX_GAMMA).contains(&g) {
            bail!("it declares the colour space \"{declared}\", a gamma outside {MIN_GAMMA}..{MAX_GAMMA} (a damaged gAMA chunk?): {convert}");
        }
        return Ok(Decoding::Gamma(g));
    }
    bail!("it declares the colour space \"{declared}\", which volgrad does not decode (it reads sRGB, linear Rec.709 and GammaN): {convert}")
}

/// How far beyond [0, 1] a picture's alpha may stray before it is an error, not a filter's
/// ringing (a Mitchell or Lanczos pixel filter overshoots at the medium's edge) to clamp.
const ALPHA_OVERSHOOT: f32 = 0.01;

/// The size (width, height) of the image `read_picture` would read, from its file's header alone:
/// no pixel is decoded.
pub fn image_size(path: &Path) -> Result<(u32, u32)> {
    if is_png(path) {
        return png_size(path);
    }
    let size = ffi::read_image_size(bridge_path(path)?).map_err(bridge_error)?;
    Ok((size.width, size.height))
}

/// Reads a picture: colour decoded to linear (see the module's documentation) and alpha.
pub fn read_picture(path: &Path, override_space: Option<ColorSpace>) -> Result<Picture> {
    let data = if is_png(path) {
        read_png(path)?
    } else {
        ffi::read_image(bridge_path(path)?).map_err(bridge_error)?
    };
    let c = data.channels as usize;
    if c == 0 {
        bail!("'{}' has no channels", path.display());
    }
    let decoded = decoding(
        &data.color_space,
        &data.stored_type,
        &data.chromaticities,
        override_space,
    )
    .with_context(|| format!("'{}'", path.display()))?;
    let alpha_at = usize::try_from(data.alpha_channel).ok().filter(|&a| a < c);
    let colour = colour_channels(&data.channel_names, c, alpha_at)
        .with_context(|| format!("'{}'", path.display()))?;
    let mut alpha = alpha_at.map(|_| Vec::with_capacity(data.pixels.len() / c));
    if let Some(a) = alpha_at {
        let bad = (data.pixels.chunks_exact(c).map(|p| p[a]).enumerate())
            .find(|(_, v)| !(-ALPHA_OVERSHOOT..=1.0 + ALPHA_OVERSHOOT).contains(v));
        if let Some((i, v)) = bad {
            bail!(
                "'{}': pixel {i} has an alpha of {v}; alpha is in [0, 1] (a filter's overshoot of up to {ALPHA_OVERSHOOT} is clamped)",
                path.display()
            );
        }
    }
    let pixels = data
        .pixels
        .chunks_exact(c)
        .map(|p| {
            let stored = match colour {
                Colour::Grey(y) => Vec3::splat(p[y]),
                Colour::Rgb([r, g, b]) => Vec3::new(p[r], p[g], p[b]),
            };
            let mut linear = Vec3::from_array(stored.to_array().map(|v| decoded.linear(v)));
            if let (Some(a), Some(alpha)) = (alpha_at, alpha.as_mut()) {
                let coverage = p[a].clamp(0.0, 1.0);
                if data.alpha_unassociated {
                    linear *= coverage;
                }
                alpha.push(coverage);
            }
            linear
        })
        .collect();
    Ok(Picture {
        color: RgbImage {
            width: data.width,
            height: data.height,
            pixels,
        },
        alpha,
        decoded,
    })
}

/// Where a picture's colour is: three channels, or one grey channel.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Colour {
    Rgb([usize; 3]),
    Grey(usize),
}

/// The colour channels of an image with channels named `names` (none: an image volgrad made),
/// `c` of them, alpha at `alpha`: R, G and B by name (or one layer's `x.R`, `x.G`, `x.B`), else a
/// grey Y (with alpha or alone). An image whose channels are none of these (depth alone, X Y Z,
/// R and G) holds no radiance to compare with and is refused, rather than its first channels
/// read as colour.
fn colour_channels(names: &[String], c: usize, alpha: Option<usize>) -> Result<Colour> {
    if names.is_empty() {
        let grey = c < 3 || alpha.is_some_and(|a| a < 3);
        return Ok(if grey {
            Colour::Grey(0)
        } else {
            Colour::Rgb([0, 1, 2])
        });
    }
    let find = |name: &str| names.iter().position(|n| n == name);
    if let (Some(r), Some(g), Some(b)) = (find("R"), find("G"), find("B")) {
        return Ok(Colour::Rgb([r, g, b]));
    }
    // Y with nothing but alpha beside it (X Y Z is a colour space of its own, not grey).
    if let Some(y) = find("Y").filter(|_| names.iter().all(|n| n == "Y" || n == "A")) {
        return Ok(Colour::Grey(y));
    }
    let layers: Vec<&str> = (names.iter())
        .filter_map(|n| n.strip_suffix(".R"))
        .filter(|layer| {
            [".G", ".B"]
                .iter()
                .all(|s| find(&format!("{layer}{s}")).is_some())
        })
        .collect();
    if let [layer] = layers[..] {
        let at = |s: &str| find(&format!("{layer}{s}")).unwrap_or_default();
        return Ok(Colour::Rgb([at(".R"), at(".G"), at(".B")]));
    }
    bail!(
        "no colour channels: its channels are {} (volgrad reads R, G and B, or a grey Y alone or beside A: not Y beside chroma, as RY and BY)",
        names.join(", ")
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colour_is_found_by_the_channels_names() {
        let names = |list: &[&str]| list.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let rgb = |list: &[&str]| colour_channels(&names(list), list.len(), None);
        assert_eq!(rgb(&["R", "G", "B", "A"]).unwrap(), Colour::Rgb([0, 1, 2]));
        assert_eq!(rgb(&["B", "G", "R"]).unwrap(), Colour::Rgb([2, 1, 0]));
        assert_eq!(rgb(&["Y", "A"]).unwrap(), Colour::Grey(0));
        assert_eq!(
            rgb(&["A", "beauty.B", "beauty.G", "beauty.R"]).unwrap(),
            Colour::Rgb([3, 2, 1])
        );
        for refused in [
            &["Z"][..],
            &["X", "Y", "Z"],
            &["R", "G"],
            &["A"],
            &["a.R", "a.G", "a.B", "b.R", "b.G", "b.B"],
        ] {
            let error = rgb(refused).unwrap_err().to_string();
            assert!(error.contains("no colour channels"), "{refused:?}: {error}");
        }
        // Y beside chroma (a luminance-chroma EXR) is not a grey picture, and the message says so.
        let error = rgb(&["BY", "RY", "Y"]).unwrap_err().to_string();
        assert!(error.contains("not Y beside chroma"), "{error}");
        // An image volgrad made itself names no channels: the first three, or grey.
        assert_eq!(
            colour_channels(&[], 4, Some(3)).unwrap(),
            Colour::Rgb([0, 1, 2])
        );
        assert_eq!(colour_channels(&[], 2, Some(1)).unwrap(), Colour::Grey(0));
    }

    #[test]
    fn srgb_decoding_inverts_the_encoding() {
        for v in [0.0, 0.001, 0.003, 0.01, 0.2140, 0.5, 0.9, 1.0] {
            assert!((srgb_decode(srgb_encode(v)) - v).abs() < 1e-6, "{v}");
        }
        // Mid-grey as stored in an 8-bit file is 0.214 in radiance, not 0.5.
        assert!((srgb_decode(0.5) - 0.214_04).abs() < 1e-4);
    }

    #[test]
    fn the_declared_space_then_the_storage_decide_the_decoding() {
        let d = |declared, stored, over| decoding(declared, stored, &[], over).unwrap();
        assert_eq!(d("", "uint8", None), Decoding::Srgb);
        assert_eq!(d("", "uint16", None), Decoding::Srgb);
        assert_eq!(d("", "half", None), Decoding::Linear);
        assert_eq!(d("", "float", None), Decoding::Linear);
        assert_eq!(d("sRGB", "float", None), Decoding::Srgb);
        assert_eq!(d("srgb_rec709_scene", "uint8", None), Decoding::Srgb);
        assert_eq!(d("Linear", "uint8", None), Decoding::Linear);
        assert_eq!(d("lin_rec709", "uint16", None), Decoding::Linear);
        assert_eq!(d("Gamma2.2", "uint8", None), Decoding::Gamma(2.2));
        // OpenImageIO's label of every PNM file: by the storage, as no label.
        assert_eq!(d("Rec709", "uint8", None), Decoding::Srgb);
        assert_eq!(d("Rec709", "float", None), Decoding::Linear);
        assert_eq!(
            d("sRGB", "uint8", Some(ColorSpace::Linear)),
            Decoding::Linear
        );
        assert_eq!(d("Linear", "float", Some(ColorSpace::Srgb)), Decoding::Srgb);
    }

    #[test]
    fn other_primaries_and_curves_are_refused_unless_overridden() {
        let d = |declared, chromaticities: &[f32], over| {
            decoding(declared, "half", chromaticities, over)
        };
        // Other primaries by name (ACEScg, Display P3), a log curve, a name nobody defined.
        for declared in [
            "ACEScg",
            "lin_ap1",
            "srgb_p3d65",
            "KodakLog",
            "Rec2020",
            "whatever",
        ] {
            let e = d(declared, &[], None).unwrap_err().to_string();
            assert!(e.contains(declared) && e.contains("convert it"), "{e}");
            assert_eq!(
                d(declared, &[], Some(ColorSpace::Linear)).unwrap(),
                Decoding::Linear
            );
        }
        // OpenEXR's chromaticities: Rec.709's are read, ACEScg's (AP1) refused.
        let ap1 = [0.713, 0.293, 0.165, 0.830, 0.128, 0.044, 0.32168, 0.33767];
        assert_eq!(
            d("", &REC709_CHROMATICITIES, None).unwrap(),
            Decoding::Linear
        );
        let e = d("", &ap1, None).unwrap_err().to_string();
        assert!(e.contains("primaries"), "{e}");
        assert_eq!(d("", &ap1, Some(ColorSpace::Srgb)).unwrap(), Decoding::Srgb);
    }
}
