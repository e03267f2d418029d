//! PNG pictures decoded in Rust (the `png` crate), not by OpenImageIO: its PNG reader leaves
//! libpng's own handlers in place, which print "libpng error: …" (and warnings such as "iCCP: known
//! incorrect sRGB profile") on stderr beside volgrad's message. What comes back is what the bridge's
//! `read_image` returns for any other format, with OpenImageIO 2.4's conventions for a PNG (its
//! channel names, stored type and colour space), so that `images::read_picture` decodes both alike.
//!
//! The colour space a PNG declares: an `sRGB` chunk is sRGB whatever else the file says (the PNG
//! specification's rule); otherwise a `gAMA` of 1 is linear and any other gamma g is decoded as
//! value^(1/g); a `cHRM` chunk gives the primaries, which `images` checks as it checks an EXR's. An
//! embedded ICC profile is not read (OpenImageIO does not read it either): such a file is decoded
//! by its other chunks, sRGB if it has none.

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use anyhow::{bail, Result};
use png::{BitDepth, ColorType, Decoder, DecodingError, Limits, Transformations};

use crate::io::bridge::ImageData;
use crate::io::input::open_regular;

/// The largest picture read, as the bridge refuses it for other formats: 2^28 pixels, 2^30 values.
const MAX_PIXELS: u64 = 1 << 28;
const MAX_VALUES: u64 = 1 << 30;

const SIGNATURE: [u8; 8] = [0x89, b'P', b'N', b'G', b'\r', b'\n', 0x1a, b'\n'];

/// Whether the file at `path` starts as a PNG does (whatever its name says). A file that cannot be
/// opened, or is not a regular file (a FIFO would block the open until something wrote to it), is
/// not: OpenImageIO's reader then says why, as for any other picture.
pub fn is_png(path: &Path) -> bool {
    let mut head = [0u8; 8];
    open_regular(path).is_ok_and(|mut f| f.read_exact(&mut head).is_ok() && head == SIGNATURE)
}

fn decoder(path: &Path) -> Result<Decoder<BufReader<File>>> {
    let file = open_regular(path).map_err(|e| cannot_read(path, e))?;
    let mut decoder = Decoder::new_with_limits(
        BufReader::new(file),
        // The sizes are checked against MAX_PIXELS and MAX_VALUES before any pixel is decoded;
        // this only keeps the crate's own 64 MiB default from refusing what they allow.
        Limits {
            bytes: (MAX_VALUES * 2) as usize,
        },
    );
    // 1-, 2- and 4-bit samples to 8, a palette to RGB, a tRNS chunk to alpha (as libpng's
    // png_set_expand, which OpenImageIO asks for); 16-bit samples stay 16-bit.
    decoder.set_transformations(Transformations::EXPAND);
    // Neither is used, and each is compressed: an ICC profile of a megabyte on disk can inflate
    // to a gigabyte, which the crate would allocate as it parses the chunk.
    decoder.set_ignore_iccp_chunk(true);
    decoder.set_ignore_text_chunk(true);
    Ok(decoder)
}

fn cannot_read(path: &Path, e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("cannot read image '{}': {e}", path.display())
}

/// What the decoder found wrong, for a reader of the error: the crate prints a chunk's type in
/// its debugging form ("ChunkType { type: IDAT, critical: true, … }"), here just its name, and a
/// file that ends early says so.
fn decoding_error(path: &Path, e: DecodingError) -> anyhow::Error {
    const CHUNK: &str = "ChunkType { type: ";
    let text = e.to_string();
    let (mut said, mut rest) = (String::new(), text.as_str());
    while let Some(at) = rest.find(CHUNK) {
        said.push_str(&rest[..at]);
        let after = &rest[at + CHUNK.len()..];
        said.push_str(&after[..after.find(',').unwrap_or(after.len())]);
        rest = after.find('}').map_or("", |end| &after[end + 1..]);
    }
    said.push_str(rest);
    let said = said.trim_end_matches('.');
    match e {
        DecodingError::IoError(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            cannot_read(path, "it ends before its image does (is it cut short?)")
        }
        DecodingError::Format(_) => cannot_read(path, format!("it is damaged ({said})")),
        _ => cannot_read(path, said),
    }
}

/// The size a PNG declares, from its header alone.
pub fn png_size(path: &Path) -> Result<(u32, u32)> {
    let mut decoder = decoder(path)?;
    let info = decoder
        .read_header_info()
        .map_err(|e| decoding_error(path, e))?;
    Ok((info.width, info.height))
}

/// Decodes a PNG: samples normalised to [0, 1] (colour as stored, unassociated from alpha).
pub fn read_png(path: &Path) -> Result<ImageData> {
    let mut decoder = decoder(path)?;
    let header = decoder
        .read_header_info()
        .map_err(|e| decoding_error(path, e))?;
    let (width, height) = (header.width, header.height);
    // At most 4 (RGBA), whatever the colour type: checked before anything past the header is read.
    let pixels = width as u64 * height as u64;
    if pixels > MAX_PIXELS || pixels * 4 > MAX_VALUES {
        bail!(
            "cannot read image '{}': it declares {width}x{height} pixels, more than volgrad reads (2^28 pixels, 2^30 values)",
            path.display()
        );
    }
    let mut reader = decoder.read_info().map_err(|e| decoding_error(path, e))?;
    let (color_type, depth) = reader.output_color_type();
    let color_space = declared_space(reader.info());
    let chromaticities = match (&reader.info().srgb, &reader.info().chrm_chunk) {
        (None, Some(c)) => [c.red, c.green, c.blue, c.white]
            .iter()
            .flat_map(|(x, y)| [x.into_value(), y.into_value()])
            .collect(),
        _ => Vec::new(),
    };
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| cannot_read(path, "its size overflows"))?;
    let mut bytes = vec![0u8; size];
    reader
        .next_frame(&mut bytes)
        .and_then(|_| reader.finish())
        .map_err(|e| decoding_error(path, e))?;
    // Times the reciprocal, as OpenImageIO converts: the same bits as the pictures read before.
    let (values, stored_type) = match depth {
        BitDepth::Sixteen => (
            (bytes.chunks_exact(2))
                .map(|b| u16::from_be_bytes([b[0], b[1]]) as f32 * (1.0 / 65535.0))
                .collect(),
            "uint16",
        ),
        _ => (
            bytes.iter().map(|&b| b as f32 * (1.0 / 255.0)).collect(),
            "uint8",
        ),
    };
    let names: &[&str] = match color_type {
        ColorType::Grayscale => &["Y"],
        ColorType::GrayscaleAlpha => &["Y", "A"],
        ColorType::Rgb => &["R", "G", "B"],
        _ => &["R", "G", "B", "A"],
    };
    Ok(ImageData {
        width,
        height,
        channels: names.len() as u32,
        pixels: values,
        color_space,
        stored_type: stored_type.into(),
        alpha_channel: names
            .iter()
            .position(|&n| n == "A")
            .map_or(-1, |a| a as i32),
        alpha_unassociated: true,
        channel_names: names.iter().map(|&n| n.into()).collect(),
        chromaticities,
    })
}

/// The colour space as OpenImageIO's `oiio:ColorSpace` would name it ("" where the file says
/// nothing; `images` then decodes an integer file as sRGB).
fn declared_space(info: &png::Info) -> String {
    if info.srgb.is_some() {
        return "sRGB".into();
    }
    match info.gama_chunk.map(|g| g.into_value()) {
        Some(g) if (g - 1.0).abs() < 1e-5 => "linear".into(),
        Some(g) if g > 0.0 => format!("Gamma{}", 1.0 / g),
        _ => String::new(),
    }
}
