//! Pictures as they arrive from elsewhere, through `images::read_picture`: a PNG's own chunks
//! deciding its decoding (written by hand here, so that no encoder's choice hides in the test),
//! and damaged files of each format refused by name rather than read with a part filled in, with
//! volgrad's message the only one on stderr.

mod bridge_common;
mod common;

use std::path::{Path, PathBuf};

use bridge_common::*;
use common::{png_chunk, sphere_vdb, stderr, volgrad_in};
use volgrad::io::bridge::ffi::{self, ImageData};
use volgrad::io::images::{image_size, read_picture, srgb_decode, ColorSpace};

/// A PNG of `width` × 1 pixels, colour type `color_type` at 8 bits, whose one row of samples is
/// `row`, with `chunks` between its header and its data. The data is one stored (uncompressed)
/// deflate block, so that the file's bytes are all spelled out here.
fn png(width: u32, color_type: u8, row: &[u8], chunks: &[Vec<u8>]) -> Vec<u8> {
    let ihdr = [
        &width.to_be_bytes()[..],
        &1u32.to_be_bytes(),
        &[8, color_type, 0, 0, 0],
    ]
    .concat();
    let scanline = [&[0u8][..], row].concat(); // filter 0 (none)
    let len = scanline.len() as u16;
    let (mut a, mut b) = (1u32, 0u32);
    for &byte in &scanline {
        a = (a + byte as u32) % 65521;
        b = (b + a) % 65521;
    }
    let zlib = [
        &[0x78, 0x01, 0x01][..],
        &len.to_le_bytes(),
        &(!len).to_le_bytes(),
        &scanline,
        &((b << 16) | a).to_be_bytes(),
    ]
    .concat();
    let mut file = vec![0x89, b'P', b'N', b'G', b'\r', b'\n', 0x1a, b'\n'];
    file.extend(png_chunk(b"IHDR", &ihdr));
    for c in chunks {
        file.extend(c);
    }
    file.extend(png_chunk(b"IDAT", &zlib));
    file.extend(png_chunk(b"IEND", &[]));
    file
}

/// A PNG chunk of big-endian u32 values (gAMA, cHRM: 100,000 per unit).
fn scaled_chunk(kind: &[u8], values: &[f64]) -> Vec<u8> {
    let data: Vec<u8> = (values.iter())
        .flat_map(|v| ((v * 100_000.0).round() as u32).to_be_bytes())
        .collect();
    png_chunk(kind, &data)
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

fn error_of(path: &Path) -> String {
    match read_picture(path, None) {
        Ok(_) => panic!("'{}' was read", path.display()),
        Err(e) => format!("{e:#}"),
    }
}

/// The first pixel's red, read with the file's own decoding.
fn red(path: &Path) -> f32 {
    read_picture(path, None).unwrap().color.pixels[0].x
}

/// A PNG's chunks decide how its values become radiance: none, or an sRGB chunk, is sRGB; a gAMA
/// of 1 is linear, another gamma g decodes as v^(1/g); a cHRM of other primaries (Display P3) is
/// refused unless an sRGB chunk says the file is sRGB after all (the PNG rule), or the caller says
/// how to take it; a palette's tRNS and a grey file's alpha are alpha.
#[test]
fn a_pngs_chunks_decide_its_decoding() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let v = 100u8;
    let stored = v as f32 / 255.0;
    let rgb = [v, 50, 200];
    let srgb = png_chunk(b"sRGB", &[0]);
    let p3 = [0.68, 0.32, 0.265, 0.69, 0.15, 0.06];
    // cHRM stores white first: white x, y, then red, green, blue.
    let p3_chunk = scaled_chunk(b"cHRM", &[&[0.3127, 0.329][..], &p3].concat());
    let rec709_chunk = scaled_chunk(
        b"cHRM",
        &[0.3127, 0.329, 0.64, 0.33, 0.30, 0.60, 0.15, 0.06],
    );
    let close = |a: f32, b: f32| (a - b).abs() < 1e-5 * b.max(1e-3);

    let plain = write(d, "plain.png", &png(1, 2, &rgb, &[]));
    assert!(close(red(&plain), srgb_decode(stored)));
    let tagged = write(d, "srgb.png", &png(1, 2, &rgb, std::slice::from_ref(&srgb)));
    assert!(close(red(&tagged), srgb_decode(stored)));
    let linear = write(
        d,
        "linear.png",
        &png(1, 2, &rgb, &[scaled_chunk(b"gAMA", &[1.0])]),
    );
    assert!(close(red(&linear), stored));
    let gamma = write(
        d,
        "gamma.png",
        &png(1, 2, &rgb, &[scaled_chunk(b"gAMA", &[0.55556])]),
    );
    assert!(
        close(red(&gamma), stored.powf(1.0 / 0.55556)),
        "{}",
        red(&gamma)
    );
    let rec709 = write(d, "rec709.png", &png(1, 2, &rgb, &[rec709_chunk]));
    assert!(close(red(&rec709), srgb_decode(stored)));

    let wide = write(
        d,
        "p3.png",
        &png(1, 2, &rgb, std::slice::from_ref(&p3_chunk)),
    );
    let e = error_of(&wide);
    assert!(e.contains("p3.png") && e.contains("primaries"), "{e}");
    let taken = read_picture(&wide, Some(ColorSpace::Srgb)).unwrap();
    assert!(close(taken.color.pixels[0].x, srgb_decode(stored)));
    let declared = write(d, "p3-srgb.png", &png(1, 2, &rgb, &[p3_chunk, srgb]));
    assert!(close(red(&declared), srgb_decode(stored)));

    // A palette of two entries, the second half transparent (tRNS), pixels 0 and 1.
    let palette = png_chunk(b"PLTE", &[v, 0, 0, 0, v, 0]);
    let trns = png_chunk(b"tRNS", &[255, 128]);
    let indexed = write(d, "palette.png", &png(2, 3, &[0, 1], &[palette, trns]));
    let picture = read_picture(&indexed, None).unwrap();
    let alpha = picture.alpha.expect("tRNS is alpha");
    assert!(
        close(alpha[0], 1.0) && close(alpha[1], 128.0 / 255.0),
        "{alpha:?}"
    );
    let premultiplied = picture.color.pixels[1].y;
    assert!(close(premultiplied, srgb_decode(stored) * 128.0 / 255.0));

    let grey = write(d, "grey-alpha.png", &png(1, 4, &[v, 255], &[]));
    let picture = read_picture(&grey, None).unwrap();
    assert!(picture.alpha.is_some());
    assert!(close(picture.color.pixels[0].x, srgb_decode(stored)));
    assert_eq!(
        picture.color.pixels[0],
        glam::Vec3::splat(picture.color.pixels[0].x)
    );
    assert_eq!(image_size(&grey).unwrap(), (1, 1));
}

/// A header that declares more pixels than volgrad reads is refused with its size named, before a
/// buffer for them is asked for (the file holds a header and nothing else).
#[test]
fn a_png_header_declaring_too_many_pixels_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let side = 20_000u32;
    let ihdr = [
        &side.to_be_bytes()[..],
        &side.to_be_bytes(),
        &[8, 6, 0, 0, 0],
    ]
    .concat();
    let mut bytes = vec![0x89, b'P', b'N', b'G', b'\r', b'\n', 0x1a, b'\n'];
    bytes.extend(png_chunk(b"IHDR", &ihdr));
    bytes.extend(png_chunk(b"IEND", &[]));
    let bomb = write(dir.path(), "bomb.png", &bytes);
    let e = error_of(&bomb);
    assert!(e.contains("bomb.png") && e.contains("20000x20000"), "{e}");
}

/// A GIF of one frame, the 35-byte one-white-pixel file spelled out, reads as that pixel: the check
/// for a second frame used to leave OpenImageIO's GIF reader unfit to read the first (a crash).
#[test]
fn a_gif_of_one_frame_reads_its_pixel() {
    let dir = tempfile::tempdir().unwrap();
    let gif = [
        &b"GIF89a"[..],
        &[1, 0, 1, 0, 0x80, 0, 0], // 1 × 1, a global table of two colours
        &[0xff, 0xff, 0xff, 0, 0, 0], // white, black
        &[0x2c, 0, 0, 0, 0, 1, 0, 1, 0, 0], // the frame: at (0, 0), 1 × 1
        &[2, 2, 0x44, 0x01, 0],    // LZW: clear, colour 0, end
        &[0x3b],
    ]
    .concat();
    let path = write(dir.path(), "white.gif", &gif);
    let image = ffi::read_image(path_str(&path)).unwrap();
    assert_eq!((image.width, image.height), (1, 1));
    assert!(image.pixels.iter().all(|&v| v == 1.0), "{:?}", image.pixels);
}

/// `data` (an 8-bit RGB image OpenImageIO writes) as `name` in `dir`, and two damaged copies: cut
/// to half its bytes, and with 64 bytes in its middle inverted.
fn damaged_copies(dir: &Path, name: &str, data: &ImageData) -> [PathBuf; 2] {
    let whole = dir.join(name);
    ffi::write_image(path_str(&whole), data, "uint8").unwrap();
    let bytes = std::fs::read(&whole).unwrap();
    let mut flipped = bytes.clone();
    let middle = bytes.len() / 2;
    for b in &mut flipped[middle..middle + 64] {
        *b = !*b;
    }
    [
        write(dir, &format!("cut-{name}"), &bytes[..middle]),
        write(dir, &format!("damaged-{name}"), &flipped),
    ]
}

/// A picture cut short is refused naming its file, and so is a damaged PNG (its chunks carry
/// checksums): OpenImageIO reads a cut JPEG or TIFF as a success with the rest of the picture grey
/// or black, and only says so when asked. (Damaged bytes inside a JPEG's or an uncompressed TIFF's
/// data are refused only where the decoder notices them: they may decode as other values.)
#[test]
fn damaged_pictures_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let image = test_image(64, 64, 3, true);
    let [cut_png, damaged_png] = damaged_copies(d, "p.png", &image);
    let [cut_jpeg, _] = damaged_copies(d, "p.jpg", &image);
    let [cut_tiff, _] = damaged_copies(d, "p.tif", &image);
    // One byte of the data chunk's checksum changed (IDAT's CRC ends 12 bytes before the file).
    let mut bytes = png(1, 2, &[1, 2, 3], &[]);
    let crc_end = bytes.len() - 12;
    bytes[crc_end - 1] ^= 1;
    let bad_crc = write(d, "crc.png", &bytes);
    let says = [
        (&cut_png, "cut short"),
        (&damaged_png, "damaged"),
        (&bad_crc, "CRC error"),
        (&cut_jpeg, "Premature end"),
        (&cut_tiff, "Read error"),
    ];
    for (path, what) in says {
        let e = error_of(path);
        let file = path.file_name().unwrap().to_str().unwrap();
        assert!(
            e.starts_with("cannot read image") && e.contains(file) && e.contains(what),
            "{e}"
        );
        assert!(!e.contains('\n') && !e.contains("ChunkType {"), "{e}");
    }
    assert!(error_of(&bad_crc).contains("IDAT"));
    // The whole files are read, as they were written.
    for name in ["p.png", "p.jpg", "p.tif"] {
        let picture = read_picture(&d.join(name), Some(ColorSpace::Linear)).unwrap();
        assert_eq!((picture.color.width, picture.color.height), (64, 64));
        // JPEG keeps each block's mean, not its noise.
        let tolerance = if name.ends_with("jpg") {
            0.01
        } else {
            0.5 / 255.0
        };
        let mean = picture.color.mean().x;
        let written = image.pixels.iter().step_by(3).sum::<f32>() / (64.0 * 64.0);
        assert!(
            (mean - written).abs() <= tolerance,
            "{name}: {mean} {written}"
        );
    }
}

/// A scene in `dir` (the sphere of `sphere_vdb`, 8² pixels) lit by the environment map `sky`.
fn write_envmap_scene(dir: &Path, sky: &Path) {
    let scene = format!(
        "[camera]\nposition = [0.0, 0.0, 20.0]\ntarget = [0.0, 0.0, 0.0]\nfov_deg = 40\nwidth = 8\nheight = 8\n\n[medium]\nvdb = \"sphere.vdb\"\n\n[[light]]\ntype = \"envmap\"\nfile = \"{}\"\n",
        sky.file_name().unwrap().to_str().unwrap()
    );
    std::fs::write(dir.join("scene.toml"), scene).unwrap();
    sphere_vdb(dir);
}

/// On the command line a damaged PNG (here a scene's environment map) gives volgrad's one error
/// line and nothing else: OpenImageIO's PNG reader let libpng print "libpng error: …" before it.
#[test]
fn a_damaged_png_prints_only_volgrads_error() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let [cut, damaged] = damaged_copies(d, "sky.png", &test_image(32, 32, 3, true));
    for sky in [cut, damaged] {
        write_envmap_scene(d, &sky);
        let out = volgrad_in(d, &["render", "scene.toml", "-o", "x.exr", "-q"]);
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(
            err.lines().count() == 1 && err.starts_with("error: light[0].file: cannot read image"),
            "{err}"
        );
    }
}

/// A PNG's ICC profile, a chunk volgrad does not use, that is a megabyte on disk and inflates to
/// half a gigabyte is not inflated: rendering with it as the environment map peaks at a render's
/// memory (about 150 MB), where the decoder that parsed the chunk peaked 512 MB higher.
#[test]
fn a_pngs_unused_chunks_are_not_inflated() {
    use flate2::{write::ZlibEncoder, Compression};
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut bomb = ZlibEncoder::new(Vec::new(), Compression::best());
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..512 {
        bomb.write_all(&zeros).unwrap();
    }
    let profile = [&b"bomb\0\0"[..], &bomb.finish().unwrap()].concat();
    let chunk = png_chunk(b"iCCP", &profile);
    let sky = write(d, "sky.png", &png(1, 2, &[100, 50, 200], &[chunk]));
    write_envmap_scene(d, &sky);
    #[allow(clippy::zombie_processes)] // reaped by wait4 below, which gives its peak memory too
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_volgrad"))
        .current_dir(d)
        .args(["render", "scene.toml", "-o", "x.exr", "-q"])
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // This child's own peak, not the largest of every child the tests ran (getrusage).
    let (mut status, mut usage) = (0, unsafe { std::mem::zeroed::<libc::rusage>() });
    let pid = unsafe { libc::wait4(child.id() as i32, &mut status, 0, &mut usage) };
    assert_eq!(pid, child.id() as i32);
    assert!(
        libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0,
        "{status}"
    );
    let peak_mb = usage.ru_maxrss as f64 / 1024.0; // kilobytes on Linux
    assert!(peak_mb < 400.0, "peak {peak_mb:.0} MB");
}

/// volgrad's PNG decoder gives what OpenImageIO's gave, to the bit: the same channels, alpha,
/// stored type and values (times the reciprocal of 255 or 65535, as OpenImageIO converts), for
/// every colour type and both depths; so pictures read before read the same now.
#[test]
fn the_png_decoder_gives_openimageios_bits() {
    use volgrad::io::png_input::read_png;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (w, h) = (13u32, 5u32);
    let bytes = |n: u32| -> Vec<u8> { (0..w * h * n).map(|i| (i * 37 % 256) as u8).collect() };
    let words =
        |n: u32| -> Vec<u16> { (0..w * h * n).map(|i| (i * 4099 % 65536) as u16).collect() };
    let mut files = vec![
        write(d, "palette.png", &{
            let palette = png_chunk(b"PLTE", &[10, 20, 30, 200, 100, 0]);
            png(4, 3, &[0, 1, 1, 0], &[palette, png_chunk(b"tRNS", &[7])])
        }),
        d.join("grey.png"),
        d.join("grey-alpha.png"),
        d.join("rgb.png"),
        d.join("rgba.png"),
        d.join("grey16.png"),
        d.join("rgba16.png"),
    ];
    image::GrayImage::from_raw(w, h, bytes(1))
        .unwrap()
        .save(&files[1])
        .unwrap();
    image::GrayAlphaImage::from_raw(w, h, bytes(2))
        .unwrap()
        .save(&files[2])
        .unwrap();
    image::RgbImage::from_raw(w, h, bytes(3))
        .unwrap()
        .save(&files[3])
        .unwrap();
    image::RgbaImage::from_raw(w, h, bytes(4))
        .unwrap()
        .save(&files[4])
        .unwrap();
    image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, words(1))
        .unwrap()
        .save(&files[5])
        .unwrap();
    image::ImageBuffer::<image::Rgba<u16>, _>::from_raw(w, h, words(4))
        .unwrap()
        .save(&files[6])
        .unwrap();
    for path in files.drain(..) {
        let (ours, theirs) = (
            read_png(&path).unwrap(),
            ffi::read_image(path_str(&path)).unwrap(),
        );
        let name = path.display();
        assert_eq!(
            (ours.width, ours.height, ours.channels, ours.alpha_channel),
            (
                theirs.width,
                theirs.height,
                theirs.channels,
                theirs.alpha_channel
            ),
            "{name}"
        );
        assert_eq!(ours.channel_names, theirs.channel_names, "{name}");
        assert_eq!(ours.stored_type, theirs.stored_type, "{name}");
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&ours.pixels), bits(&theirs.pixels), "{name}");
    }
}
