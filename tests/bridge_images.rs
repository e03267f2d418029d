//! Images through the C++ bridge (OpenImageIO), checked with independent pure-Rust decoders
//! (`exr`, `image`): EXR as float and half, 8-bit PNG, and errors that name the file.

mod bridge_common;
mod common;

use std::path::Path;

use bridge_common::*;
use glam::Vec3;
use volgrad::io::bridge::ffi::{self, ImageData};

// ------------------------------------------------------------------------------------------------
// Images

/// Reads an RGBA EXR with the pure-Rust `exr` crate: (width, height, interleaved RGBA).
fn exr_rgba(path: &Path) -> (usize, usize, Vec<f32>) {
    let image = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |size, _| (size.width(), vec![0f32; size.width() * size.height() * 4]),
        |(w, px): &mut (usize, Vec<f32>), pos, (r, g, b, a): (f32, f32, f32, f32)| {
            let i = 4 * (pos.y() * *w + pos.x());
            px[i..i + 4].copy_from_slice(&[r, g, b, a]);
        },
    )
    .unwrap();
    let size = image.layer_data.size;
    (
        size.width(),
        size.height(),
        image.layer_data.channel_data.pixels.1,
    )
}

fn exr_sample_types(path: &Path) -> Vec<exr::meta::attribute::SampleType> {
    let meta = exr::meta::MetaData::read_from_file(path, false).unwrap();
    meta.headers[0]
        .channels
        .list
        .iter()
        .map(|c| c.sample_type)
        .collect()
}

#[test]
fn exr_float_round_trip() {
    let img = test_image(7, 5, 4, false);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("f.exr");
    ffi::write_image(path_str(&out), &img, "float").unwrap();

    let back = ffi::read_image(path_str(&out)).unwrap();
    assert_eq!((back.width, back.height, back.channels), (7, 5, 4));
    assert_eq!(back.pixels, img.pixels);

    let (w, h, px) = exr_rgba(&out);
    assert_eq!((w, h), (7, 5));
    assert_eq!(px, img.pixels);
    assert!(exr_sample_types(&out)
        .iter()
        .all(|t| *t == exr::meta::attribute::SampleType::F32));
    let meta = exr::meta::MetaData::read_from_file(&out, false).unwrap();
    assert_eq!(
        meta.headers[0].compression,
        exr::compression::Compression::ZIP16
    );
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["f.exr"], "no temporary file is left behind");
}

#[test]
fn exr_half_round_trip() {
    let img = test_image(6, 4, 4, false);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("h.exr");
    ffi::write_image(path_str(&out), &img, "half").unwrap();
    let expect: Vec<f32> = img.pixels.iter().map(|&v| half(v)).collect();
    assert_ne!(expect, img.pixels);

    assert_eq!(ffi::read_image(path_str(&out)).unwrap().pixels, expect);
    let (w, h, px) = exr_rgba(&out);
    assert_eq!((w, h), (6, 4));
    assert_eq!(px, expect);
    assert!(exr_sample_types(&out)
        .iter()
        .all(|t| *t == exr::meta::attribute::SampleType::F16));
}

#[test]
fn png_uint8_round_trip() {
    let mut img = test_image(5, 3, 4, true);
    // Exact halves and the ends of the range; alpha < 1 must not premultiply anything.
    img.pixels[..8].copy_from_slice(&[0.5, 0.0, 1.0, 0.5, 0.8, 2.0 / 255.0, 1.5 / 255.0, 0.25]);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("img.png");
    ffi::write_image(path_str(&out), &img, "uint8").unwrap();

    let decoded = image::open(&out).unwrap();
    assert_eq!(decoded.color(), image::ColorType::Rgba8);
    let bytes = decoded.to_rgba8().into_raw();
    let expect: Vec<u8> = img
        .pixels
        .iter()
        .map(|&v| (v * 255.0).round() as u8)
        .collect();
    assert_eq!(bytes, expect);
    // OIIO rounds to nearest with halves up: 0.5 -> 127.5 -> 128.
    assert_eq!(bytes[0], 128);
    assert_eq!(&bytes[4..8], &[204, 2, 2, 64]);

    let back = ffi::read_image(path_str(&out)).unwrap();
    assert_eq!((back.width, back.height, back.channels), (5, 3, 4));
    let expect_f: Vec<f32> = expect.iter().map(|&b| b as f32 / 255.0).collect();
    for (a, b) in back.pixels.iter().zip(&expect_f) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
}

#[test]
fn image_errors_name_the_file() {
    let e = err_text(ffi::read_image("/no/such/image.exr"));
    assert_eq!(e, "cannot open '/no/such/image.exr': no such file");

    let dir = tempfile::tempdir().unwrap();
    let text = dir.path().join("notes.png");
    std::fs::write(&text, b"this is not a png").unwrap();
    let e = err_text(ffi::read_image(path_str(&text)));
    assert!(
        e.starts_with(&format!("cannot read image '{}'", path_str(&text))),
        "{e}"
    );

    // A header that promises pixels the file does not hold: OpenImageIO's PPM reader fails
    // without a message of its own.
    let truncated = dir.path().join("truncated.ppm");
    std::fs::write(&truncated, b"P6\n2 2\n255\n").unwrap();
    let e = err_text(ffi::read_image(path_str(&truncated)));
    assert!(
        e.starts_with(&format!("cannot read image '{}'", path_str(&truncated)))
            && e.contains("cut short or damaged"),
        "{e}"
    );

    // A PNG cut short, or with a damaged byte in its pixels: libpng's reader stacks a line per
    // layer ("Read error: hit end of file", "PNG read error: IDAT: …", "PNG library error"); the
    // error is one line that says what went wrong once.
    let whole = dir.path().join("whole.png");
    ffi::write_image(path_str(&whole), &test_image(64, 64, 4, true), "uint8").unwrap();
    let bytes = std::fs::read(&whole).unwrap();
    let cut = dir.path().join("cut.png");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let mut flipped = bytes.clone();
    flipped[bytes.len() / 2] ^= 0xff;
    let damaged = dir.path().join("damaged.png");
    std::fs::write(&damaged, &flipped).unwrap();
    // A TIFF cut short: libtiff says so once per strip it could not read; the first is kept.
    let tiff = dir.path().join("whole.tif");
    ffi::write_image(path_str(&tiff), &test_image(256, 256, 4, true), "uint8").unwrap();
    let bytes = std::fs::read(&tiff).unwrap();
    let cut_tiff = dir.path().join("cut.tif");
    std::fs::write(&cut_tiff, &bytes[..bytes.len() / 4]).unwrap();
    let e = err_text(ffi::read_image(path_str(&cut_tiff)));
    assert!(
        e.contains("cut short or damaged") && e.matches("TIFF").count() <= 1,
        "{e}"
    );
    for (path, says) in [(&cut, "end of file"), (&damaged, "PNG read error")] {
        let e = err_text(ffi::read_image(path_str(path)));
        assert!(
            e.starts_with(&format!("cannot read image '{}'", path_str(path)))
                && e.contains(says)
                && !e.contains('\n')
                && e.matches(says).count() == 1,
            "{e}"
        );
    }

    let img = test_image(2, 2, 3, true);
    let unknown = dir.path().join("x.unknownext");
    let e = err_text(ffi::write_image(path_str(&unknown), &img, "float"));
    assert!(
        e.contains("x.unknownext") && e.contains("unknown image format"),
        "{e}"
    );

    let e = err_text(ffi::write_image(
        path_str(&dir.path().join("y.exr")),
        &img,
        "int16",
    ));
    assert!(e.contains("unknown pixel type 'int16'"), "{e}");

    let mut short = img.clone();
    short.pixels.pop();
    let e = err_text(ffi::write_image(
        path_str(&dir.path().join("z.exr")),
        &short,
        "half",
    ));
    assert!(e.contains("11 values for 2x2x3"), "{e}");

    // PNG cannot hold floats: an error rather than a silent fallback to 8 bits.
    let png = dir.path().join("f.png");
    let e = err_text(ffi::write_image(path_str(&png), &img, "float"));
    assert!(
        e.contains("cannot store float pixels (it would store uint8)"),
        "{e}"
    );
    assert!(!png.exists());

    let e = err_text(ffi::write_image("/nonexistent-dir/a.exr", &img, "half"));
    assert!(e.contains("does not exist"), "{e}");

    // A folder that takes no new file (/proc, even for root): the system's reason, and the
    // folder, not the hidden temporary the image is written to first.
    for (name, format) in [("/proc/a.exr", "half"), ("/proc/a.png", "uint8")] {
        let e = err_text(ffi::write_image(name, &img, format));
        assert!(
            e.contains("cannot create a file in '/proc': no such file or directory")
                && !e.contains(".tmp"),
            "{e}"
        );
    }
}

/// PNGs as other programs write them (the `image` crate here): 8- and 16-bit values are decoded
/// from sRGB, straight alpha is read and the colour premultiplied by it; `color_space = linear`
/// takes the stored values as they are.
#[test]
fn pngs_are_decoded_from_srgb_with_their_alpha() {
    use volgrad::io::images::{read_picture, read_rgb, srgb_decode, ColorSpace, Decoding};
    let dir = tempfile::tempdir().unwrap();
    let rgba8 = dir.path().join("rgba8.png");
    image::RgbaImage::from_raw(2, 1, vec![128, 64, 255, 255, 200, 100, 0, 64])
        .unwrap()
        .save(&rgba8)
        .unwrap();
    let picture = read_picture(&rgba8, None).unwrap();
    assert_eq!(picture.decoded, Decoding::Srgb);
    let alpha = picture.alpha.as_ref().expect("the PNG's alpha");
    assert!((alpha[0] - 1.0).abs() < 1e-6 && (alpha[1] - 64.0 / 255.0).abs() < 1e-6);
    let linear = |b: u8| srgb_decode(b as f32 / 255.0);
    let first = picture.color.pixels[0];
    assert!((first - Vec3::new(linear(128), linear(64), 1.0)).length() < 1e-5);
    assert!(
        (first.x - 0.2158).abs() < 1e-3,
        "mid-grey is 0.22 in radiance, not 0.5"
    );
    let second = picture.color.pixels[1];
    let a = 64.0 / 255.0;
    assert!((second - Vec3::new(linear(200) * a, linear(100) * a, 0.0)).length() < 1e-5);
    let raw = read_picture(&rgba8, Some(ColorSpace::Linear)).unwrap();
    assert!((raw.color.pixels[0].x - 128.0 / 255.0).abs() < 1e-6);
    assert_eq!(raw.decoded, Decoding::Linear);

    let rgb16 = dir.path().join("rgb16.png");
    image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(1, 1, vec![32768u16, 0, 65535])
        .unwrap()
        .save(&rgb16)
        .unwrap();
    let picture = read_picture(&rgb16, None).unwrap();
    assert!(picture.alpha.is_none());
    let c = picture.color.pixels[0];
    assert!((c - Vec3::new(srgb_decode(32768.0 / 65535.0), 0.0, 1.0)).length() < 1e-5);
    assert_eq!(read_rgb(&rgb16).unwrap().pixels[0], c);
}

/// Writes an RGBA EXR (the pure-Rust `exr` crate) whose data window is `size` pixels at
/// `position` on a display window of `display` pixels at the origin: pixel (x, y) of the data
/// window holds (x + 10·y, 1, 2, 0.5).
fn exr_with_windows(
    path: &Path,
    display: (usize, usize),
    position: (i32, i32),
    size: (usize, usize),
) {
    use exr::prelude::*;
    let mut attributes = LayerAttributes::named("");
    attributes.layer_position = Vec2(position.0, position.1);
    let layer = Layer::new(
        size,
        attributes,
        Encoding::UNCOMPRESSED,
        SpecificChannels::rgba(|p: Vec2<usize>| {
            ((p.x() + 10 * p.y()) as f32, 1.0f32, 2.0f32, 0.5f32)
        }),
    );
    let mut image = Image::from_layer(layer);
    image.attributes.display_window = IntegerBounds::new(Vec2(0, 0), display);
    image.write().to_file(path).unwrap();
}

/// The RGBA of pixel (x, y) of an image read through the bridge, by the channels' names.
fn rgba_at(image: &ImageData, x: usize, y: usize) -> [f32; 4] {
    let c = image.channels as usize;
    let at = |name: &str| image.channel_names.iter().position(|n| n == name).unwrap();
    let base = (y * image.width as usize + x) * c;
    ["R", "G", "B", "A"].map(|n| image.pixels[base + at(n)])
}

/// An EXR's data window is placed on its display window, which is the image: a bounding box
/// smaller than the frame leaves black, transparent pixels around it (OpenEXR's rule), and
/// overscan beyond the frame is cut off. (They were read as the data window alone: an image of
/// the wrong size, or shifted.)
#[test]
fn an_exr_data_window_is_placed_on_its_display_window() {
    let dir = tempfile::tempdir().unwrap();
    let boxed = dir.path().join("bounding-box.exr");
    exr_with_windows(&boxed, (8, 6), (2, 1), (4, 3));
    let image = ffi::read_image(path_str(&boxed)).unwrap();
    assert_eq!((image.width, image.height), (8, 6));
    for y in 0..6 {
        for x in 0..8 {
            let inside = (2..6).contains(&x) && (1..4).contains(&y);
            let expected = if inside {
                [(x - 2 + 10 * (y - 1)) as f32, 1.0, 2.0, 0.5]
            } else {
                [0.0; 4]
            };
            assert_eq!(rgba_at(&image, x, y), expected, "pixel ({x}, {y})");
        }
    }
    let overscan = dir.path().join("overscan.exr");
    exr_with_windows(&overscan, (4, 3), (-1, -1), (6, 5));
    let image = ffi::read_image(path_str(&overscan)).unwrap();
    assert_eq!((image.width, image.height), (4, 3));
    for y in 0..3 {
        for x in 0..4 {
            let expected = [(x + 1 + 10 * (y + 1)) as f32, 1.0, 2.0, 0.5];
            assert_eq!(rgba_at(&image, x, y), expected, "pixel ({x}, {y})");
        }
    }
}

/// Only an EXR's data window is placed on a frame: a PNG's `oFFs` chunk (an offset ImageMagick
/// writes after a crop) says nothing of one, and the PNG is its stored pixels, unmoved; its size
/// from the header alone is the same.
#[test]
fn a_png_offset_does_not_move_its_pixels() {
    let img = test_image(5, 3, 3, true);
    let dir = tempfile::tempdir().unwrap();
    let plain = dir.path().join("plain.png");
    ffi::write_image(path_str(&plain), &img, "uint8").unwrap();
    let bytes = std::fs::read(&plain).unwrap();
    // oFFs: x and y (pixels, big-endian i32), unit 0 (pixels); right after IHDR (8 + 25 bytes).
    let offsets = [&5i32.to_be_bytes()[..], &7i32.to_be_bytes(), &[0]].concat();
    let chunk = common::png_chunk(b"oFFs", &offsets);
    let offset = dir.path().join("offset.png");
    std::fs::write(&offset, [&bytes[..33], &chunk, &bytes[33..]].concat()).unwrap();
    let (a, b) = (
        ffi::read_image(path_str(&plain)).unwrap(),
        ffi::read_image(path_str(&offset)).unwrap(),
    );
    assert_eq!((b.width, b.height), (5, 3));
    assert_eq!(a.pixels, b.pixels);
    let size = ffi::read_image_size(path_str(&offset)).unwrap();
    assert_eq!((size.width, size.height), (5, 3));
    let size = ffi::read_image_size(path_str(&dir.path().join("none.png")));
    assert!(size.is_err());
}

/// An EXR that states other primaries than Rec.709's (ACEScg's, here) is refused by name rather
/// than read as if its values were volgrad's RGB, unless the caller says how to take them; one
/// that states Rec.709's is read.
#[test]
fn an_exr_with_other_primaries_is_refused_unless_overridden() {
    use exr::prelude::*;
    use volgrad::io::images::{read_picture, ColorSpace};
    let write = |path: &Path, primaries: [(f32, f32); 4]| {
        let layer = Layer::new(
            (3, 2),
            LayerAttributes::named(""),
            Encoding::UNCOMPRESSED,
            SpecificChannels::rgba(|_: Vec2<usize>| (0.25f32, 0.5f32, 0.75f32, 1.0f32)),
        );
        let mut image = Image::from_layer(layer);
        let [r, g, b, w] = primaries.map(|(x, y)| Vec2(x, y));
        image.attributes.chromaticities = Some(exr::meta::attribute::Chromaticities {
            red: r,
            green: g,
            blue: b,
            white: w,
        });
        image.write().to_file(path).unwrap();
    };
    let dir = tempfile::tempdir().unwrap();
    let acescg = dir.path().join("acescg.exr");
    write(
        &acescg,
        [
            (0.713, 0.293),
            (0.165, 0.830),
            (0.128, 0.044),
            (0.32168, 0.33767),
        ],
    );
    assert_eq!(
        ffi::read_image(path_str(&acescg))
            .unwrap()
            .chromaticities
            .len(),
        8
    );
    let e = match read_picture(&acescg, None) {
        Ok(_) => panic!("a picture in ACEScg's primaries was read as Rec.709"),
        Err(e) => format!("{e:#}"),
    };
    assert!(
        e.contains("acescg.exr") && e.contains("primaries") && e.contains("color_space"),
        "{e}"
    );
    let taken = read_picture(&acescg, Some(ColorSpace::Linear)).unwrap();
    assert_eq!(taken.color.pixels[0], Vec3::new(0.25, 0.5, 0.75));
    let rec709 = dir.path().join("rec709.exr");
    write(
        &rec709,
        [(0.64, 0.33), (0.30, 0.60), (0.15, 0.06), (0.3127, 0.3290)],
    );
    assert_eq!(
        read_picture(&rec709, None).unwrap().color.pixels[0],
        Vec3::new(0.25, 0.5, 0.75)
    );
}

/// An EXR header (a few kilobytes on disk) declaring 8192² pixels of 64 half channels, 2^32
/// values, is refused with its size named before a buffer is asked for: each of the pixel count
/// and the channel count is within its own limit, and the buffer would have been 16 GiB.
#[test]
fn an_exr_header_declaring_too_many_values_is_refused() {
    let attribute = |name: &str, kind: &str, value: &[u8]| {
        let mut a = Vec::new();
        a.extend_from_slice(name.as_bytes());
        a.push(0);
        a.extend_from_slice(kind.as_bytes());
        a.push(0);
        a.extend_from_slice(&(value.len() as i32).to_le_bytes());
        a.extend_from_slice(value);
        a
    };
    let mut channels = Vec::new();
    for c in 0..64 {
        channels.extend_from_slice(format!("c{c:02}\0").as_bytes());
        channels.extend_from_slice(&1i32.to_le_bytes()); // HALF
        channels.extend_from_slice(&[0, 0, 0, 0]); // pLinear, reserved
        channels.extend_from_slice(&1i32.to_le_bytes());
        channels.extend_from_slice(&1i32.to_le_bytes());
    }
    channels.push(0);
    let side = 8192i32;
    let window: Vec<u8> = [0, 0, side - 1, side - 1]
        .iter()
        .flat_map(|v: &i32| v.to_le_bytes())
        .collect();
    let mut exr = vec![0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0];
    exr.extend(attribute("channels", "chlist", &channels));
    exr.extend(attribute("compression", "compression", &[0]));
    exr.extend(attribute("dataWindow", "box2i", &window));
    exr.extend(attribute("displayWindow", "box2i", &window));
    exr.extend(attribute("lineOrder", "lineOrder", &[0]));
    exr.extend(attribute("pixelAspectRatio", "float", &1f32.to_le_bytes()));
    exr.extend(attribute("screenWindowCenter", "v2f", &[0; 8]));
    exr.extend(attribute("screenWindowWidth", "float", &1f32.to_le_bytes()));
    exr.push(0);
    exr.extend(std::iter::repeat_n(0u8, 8 * side as usize)); // the line offset table
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bomb.exr");
    std::fs::write(&path, exr).unwrap();
    let e = match ffi::read_image(path_str(&path)) {
        Ok(_) => panic!("a header declaring 2^32 values was read"),
        Err(e) => e.what().to_string(),
    };
    assert!(
        e.contains("bomb.exr")
            && e.contains("8192x8192")
            && e.contains("64 channels")
            && e.contains("2^30 values"),
        "{e}"
    );
}

/// Files whose pixels are not one picture's radiance are refused, not read as if they were: an
/// EXR of two parts (the first a black utility part; reading it fitted black), one whose colour
/// channels are 32-bit unsigned integers (ids or counts, which OpenImageIO divides by 2³² − 1),
/// and a PNG whose gAMA chunk is damaged (gAMA 1, a gamma of 10⁵, darkened every pixel to 10⁻⁶).
#[test]
fn pictures_that_are_not_one_radiance_image_are_refused() {
    use exr::prelude::*;
    use volgrad::io::images::read_picture;
    let dir = tempfile::tempdir().unwrap();
    let refused = |path: &Path, says: &str| {
        let e = match read_picture(path, None) {
            Ok(_) => panic!("'{}' was read", path.display()),
            Err(e) => format!("{e:#}"),
        };
        assert!(e.contains(path_str(path)) && e.contains(says), "{e}");
    };
    let layer = |name: &str, value: f32| {
        Layer::new(
            (3, 2),
            LayerAttributes::named(name),
            Encoding::UNCOMPRESSED,
            SpecificChannels::rgb(move |_: Vec2<usize>| (value, value, value)),
        )
    };
    let parts = dir.path().join("parts.exr");
    Image::from_layers(
        ImageAttributes::new(IntegerBounds::from_dimensions((3, 2))),
        vec![layer("mask", 0.0), layer("beauty", 0.5)],
    )
    .write()
    .to_file(&parts)
    .unwrap();
    refused(&parts, "several images");
    let ids = dir.path().join("ids.exr");
    Image::from_layer(Layer::new(
        (3, 2),
        LayerAttributes::named(""),
        Encoding::UNCOMPRESSED,
        SpecificChannels::rgb(|_: Vec2<usize>| (700u32, 600u32, 500u32)),
    ))
    .write()
    .to_file(&ids)
    .unwrap();
    refused(&ids, "32-bit unsigned integers");
    // A PNG with a gAMA chunk (gamma × 10⁵, big-endian) after its header.
    let with_gamma = |name: &str, gama: u32| {
        let path = dir.path().join(name);
        image::RgbImage::from_pixel(3, 2, image::Rgb([128, 128, 128]))
            .save(&path)
            .unwrap();
        let png = std::fs::read(&path).unwrap();
        let mut chunk = b"gAMA".to_vec();
        chunk.extend_from_slice(&gama.to_be_bytes());
        let crc = crc32(&chunk);
        let mut out = png[..33].to_vec(); // the signature and IHDR
        out.extend_from_slice(&4u32.to_be_bytes());
        out.extend_from_slice(&chunk);
        out.extend_from_slice(&crc.to_be_bytes());
        out.extend_from_slice(&png[33..]);
        std::fs::write(&path, out).unwrap();
        path
    };
    refused(&with_gamma("damaged.png", 1), "gamma outside");
    let gamma22 = read_picture(&with_gamma("gamma22.png", 45455), None).unwrap();
    let expected = (128.0f32 / 255.0).powf(2.2);
    assert!(
        (gamma22.color.pixels[0].x - expected).abs() < 1e-3,
        "{:?}",
        gamma22.color.pixels[0]
    );
}

/// PNG's CRC-32 (ISO 3309), bit by bit.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}
