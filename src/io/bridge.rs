//! The cxx bridge to OpenVDB and OpenImageIO (implemented in `cpp/`, declared in `cpp/bridge.h`).
//!
//! Everything crosses as plain data: the C++ side never hands out OpenVDB objects. Every function can
//! throw (I/O, corrupt files, wrong types), so every one is declared `Result`: an exception escaping a
//! non-`Result` cxx function would abort the process.

#[cxx::bridge(namespace = "volgrad")]
pub mod ffi {
    /// One metadata entry. `type_name` is OpenVDB's type name ("string", "float", "int32", "int64",
    /// "double", "bool", "vec3i", ...); `value` is its text form (floats in the shortest form that
    /// reads back exactly, vectors as "[x, y, z]"). Writing accepts string, float, int/int32, int64,
    /// double, bool and vec3i/vec3s/vec3d.
    #[derive(Debug, Clone, PartialEq)]
    pub struct MetaEntry {
        pub name: String,
        pub type_name: String,
        pub value: String,
    }

    /// An image's size in pixels.
    pub struct ImageSize {
        pub width: u32,
        pub height: u32,
    }

    /// What `volgrad info` prints about one grid; the tree is not copied.
    #[derive(Debug, Clone)]
    pub struct GridSummary {
        pub name: String,
        /// OpenVDB's value type name: "float", "double", "vec3s", "ptdataidx32", ...
        pub value_type: String,
        /// "fog volume", "level set", "staggered", "unknown".
        pub grid_class: String,
        /// Index-to-world affine map, column-vector convention, row-major:
        /// world[i] = sum_j m[4*i + j] * index[j] + m[4*i + 3]. NaN for non-linear maps.
        pub index_to_world: [f64; 16],
        pub voxel_size: [f64; 3],
        /// True when the map is a pure scale + translation (axis-aligned voxels).
        pub axis_aligned: bool,
        /// False for non-linear (frustum) maps, which volgrad cannot render.
        pub linear: bool,
        pub active_voxels: u64,
        pub leaf_count: u64,
        pub active_tiles: u64,
        /// Inclusive active index bounding box; min > max when the grid is empty (and then the
        /// world box is +inf..−inf).
        pub index_min: [i32; 3],
        pub index_max: [i32; 3],
        /// World-space box of the index box grown by half a voxel, through the transform.
        pub world_min: [f64; 3],
        pub world_max: [f64; 3],
        pub saved_as_half: bool,
        pub metadata: Vec<MetaEntry>,
    }

    /// One 8³ leaf: its origin (multiples of 8), its whole 512-value buffer (inactive voxels
    /// included, in OpenVDB order x*64 + y*8 + z) and its active mask (bit offset % 64 of word
    /// offset / 64). Laid out exactly as `volume::brickmap::Leaf`, so that the leaves a read
    /// returns become a brick map's without a copy (`Grid::from_data`).
    #[derive(Debug, Clone, PartialEq)]
    pub struct LeafData {
        pub origin: [i32; 3],
        pub values: [f32; 512],
        pub active: [u64; 8],
    }

    /// A float grid as plain data: every leaf and every active tile.
    #[derive(Debug, Clone)]
    pub struct FloatGridData {
        pub name: String,
        pub grid_class: String,
        pub index_to_world: [f64; 16],
        pub background: f32,
        pub saved_as_half: bool,
        pub leaves: Vec<LeafData>,
        /// 3 per active tile: its minimum index corner.
        pub tile_origins: Vec<i32>,
        /// 1 per active tile: its edge length in voxels (8, 128 or 4096 for the standard tree).
        pub tile_sizes: Vec<u32>,
        pub tile_values: Vec<f32>,
        /// Reading only (ignored on write): inactive tiles whose value is not the background.
        /// They are not copied, so volgrad reads 0 there where OpenVDB reads their value.
        pub inactive_tiles_off_background: u64,
        pub metadata: Vec<MetaEntry>,
    }

    /// An image in memory: `channels` interleaved f32 per pixel, rows top to bottom.
    #[derive(Debug, Clone)]
    pub struct ImageData {
        pub width: u32,
        pub height: u32,
        pub channels: u32,
        pub pixels: Vec<f32>,
        /// Reading only (ignored on write): the colour space the file declares (OpenImageIO's
        /// `oiio:ColorSpace`, e.g. "sRGB", "Linear", "Gamma2.2"; empty when it says none).
        pub color_space: String,
        /// Reading only: how the file stores its values ("uint8", "uint16", "half", "float", …).
        pub stored_type: String,
        /// Reading only: the alpha channel's index, or −1.
        pub alpha_channel: i32,
        /// Reading only: whether colour is stored unassociated with alpha ("straight", as PNG
        /// stores it) rather than premultiplied (as EXR does).
        pub alpha_unassociated: bool,
        /// Reading only: the channels' names ("R", "G", "B", "A", "Y", "Z", "diffuse.R", …).
        pub channel_names: Vec<String>,
        /// Reading only: the primaries and white point the file states (OpenEXR's
        /// `chromaticities`: x, y of red, green, blue and white), or none.
        pub chromaticities: Vec<f32>,
    }

    extern "Rust" {
        /// Resizes a vector to `len` values (new ones 0), so that C++ fills a large array through
        /// `data()`: `rust::Vec::push_back` costs four calls into Rust per value, most of the
        /// time of reading a large grid.
        /// Both fail (a C++ exception) where the memory cannot be had, rather than abort.
        fn resize_f32s(v: &mut Vec<f32>, len: usize) -> Result<()>;
        fn resize_leaves(v: &mut Vec<LeafData>, len: usize) -> Result<()>;
    }

    unsafe extern "C++" {
        include!("volgrad/cpp/bridge.h");

        /// Every grid in the file, in file order.
        fn list_grids(path: &str) -> Result<Vec<GridSummary>>;

        /// The names of the grids in the file, in file order, from its grid descriptors alone
        /// (`list_grids` reads every grid to summarize it).
        fn list_grid_names(path: &str) -> Result<Vec<String>>;

        /// Reads one float grid: by `index` (position in file order) when `index >= 0`, else by
        /// `name`. Errors name the file and the reason (missing, corrupt, no such grid, not float).
        /// With `level_set_to_fog`, a grid of class "level set" comes back converted by OpenVDB's
        /// `tools::sdfToFogVolume` (class "fog volume", background 0); other grids are unchanged.
        /// A float or double grid in a current-format file is read by OpenVDB without its voxel
        /// buffers, which are then decoded (by OpenVDB's decoder) on `threads` threads straight
        /// into the returned arrays; other grids are read by OpenVDB end to end and copied on
        /// `threads` threads.
        fn read_float_grid(
            path: &str,
            name: &str,
            index: i32,
            level_set_to_fog: bool,
            threads: u32,
        ) -> Result<FloatGridData>;

        /// `read_float_grid` through OpenVDB's own reader end to end (voxel buffers decoded one
        /// after another into its tree, then copied): the reference the parallel decoding is
        /// tested against, and the bench's measure of it.
        fn read_float_grid_through_openvdb(
            path: &str,
            name: &str,
            index: i32,
            level_set_to_fog: bool,
            threads: u32,
        ) -> Result<FloatGridData>;

        /// Reads one grid as float components: a float or double grid as one (as
        /// `read_float_grid`), a vec3s or vec3d grid (a colour) as three, its x, y and z, each
        /// with the grid's name, transform and topology. Other value types are refused.
        fn read_grid_components(
            path: &str,
            name: &str,
            index: i32,
            threads: u32,
        ) -> Result<Vec<FloatGridData>>;

        /// Writes float grids to one file (pruned; stored as half when `save_half`), replacing it.
        /// A "level set" needs a background > 0 (its narrow-band half-width); its inside is
        /// signed-flood-filled, so leaves around the surface are enough.
        fn write_float_grids(path: &str, grids: &[FloatGridData], save_half: bool) -> Result<()>;

        /// As `write_float_grids`, followed by vec3s grids (colours), each made of three float
        /// components of `colours` in turn: every voxel active in a component is active, with
        /// the name, transform and metadata of the first.
        fn write_grids_with_colours(
            path: &str,
            grids: &[FloatGridData],
            colours: &[FloatGridData],
            save_half: bool,
        ) -> Result<()>;

        /// The size of the image `read_image` would read, from the file's header alone.
        fn read_image_size(path: &str) -> Result<ImageSize>;

        /// Reads any image OpenImageIO can open, converted to f32 (no colour conversion; alpha
        /// unassociated as stored), with the colour space and storage the file declares.
        fn read_image(path: &str) -> Result<ImageData>;

        /// Writes an image; the format follows the extension. `pixel_type` is "half", "float" or
        /// "uint8" (8-bit values are the f32 values in [0, 1], already encoded by the caller).
        fn write_image(path: &str, image: &ImageData, pixel_type: &str) -> Result<()>;
    }
}

pub use ffi::{FloatGridData, GridSummary, ImageData, LeafData, MetaEntry};

/// A path as the C++ side takes it: UTF-8, and without a NUL, at which the C library's calls would
/// cut it short (`sky.png\0.exr` would open `sky.png`, past every check made on the whole path).
pub fn bridge_path(path: &std::path::Path) -> anyhow::Result<&str> {
    let text = (path.to_str())
        .ok_or_else(|| anyhow::anyhow!("path '{}' is not valid UTF-8", path.display()))?;
    if text.contains('\0') {
        anyhow::bail!("path '{}' holds a NUL character", text.replace('\0', "\\0"));
    }
    Ok(text)
}

/// A grid's name as the C++ side takes it: without a NUL, at which OpenVDB's C strings end.
pub fn check_grid_name(name: &str) -> anyhow::Result<()> {
    if name.contains('\0') {
        anyhow::bail!(
            "the grid name '{}' holds a NUL character",
            name.replace('\0', "\\0")
        );
    }
    Ok(())
}

/// A C++ exception as an error, its message as the C++ side wrote it. Where that message ends in
/// what the file system said (`cpp/files.cpp`'s `errno_text` and the checks beside it), the
/// error carries an `std::io::Error` of that kind in its chain, as a Rust file error would, so
/// that callers can tell a missing or unwritable file from a bad one (Python's FileNotFoundError
/// and OSError against ValueError).
pub fn bridge_error(e: cxx::Exception) -> anyhow::Error {
    use std::io::ErrorKind;
    let message = e.what().to_string();
    let kind = [
        (": no such file", ErrorKind::NotFound),
        ("does not exist", ErrorKind::NotFound),
        (": permission denied", ErrorKind::PermissionDenied),
        ("is a directory", ErrorKind::IsADirectory),
        ("is not a directory", ErrorKind::NotADirectory),
        (": not a regular file", ErrorKind::InvalidInput),
        (": no space left on device", ErrorKind::StorageFull),
        (": read-only file system", ErrorKind::ReadOnlyFilesystem),
    ]
    .into_iter()
    .find_map(|(said, kind)| message.contains(said).then_some(kind));
    match kind {
        Some(kind) => std::io::Error::new(kind, message).into(),
        None => anyhow::anyhow!(message),
    }
}

/// `v` as `len` zeros, for the bridge to fill (an image's pixels).
fn resize_f32s(v: &mut Vec<f32>, len: usize) -> Result<(), String> {
    // SAFETY: all-zero bytes are the f32 0.0.
    *v = unsafe { zeroed_vec(len) }?;
    Ok(())
}

/// `v` as `len` zeroed leaves, for the bridge to fill.
fn resize_leaves(v: &mut Vec<LeafData>, len: usize) -> Result<(), String> {
    // SAFETY: a LeafData is integers and floats only, for which all-zero bytes are a valid value.
    *v = unsafe { zeroed_vec(len) }?;
    Ok(())
}

/// `len` zeroed values, or an error where the memory cannot be had (a grid or an image larger
/// than the machine: an error the user reads, where `Vec`'s own allocation would abort). Memory
/// from `alloc_zeroed` gets its zero pages from the kernel as they are first written (by the
/// bridge's threads), where `resize` would write every byte once more first (≈ 40 ms per
/// 100 MiB).
///
/// # Safety
/// All-zero bytes must be a valid `T`.
unsafe fn zeroed_vec<T>(len: usize) -> Result<Vec<T>, String> {
    if len == 0 || std::mem::size_of::<T>() == 0 {
        return Ok(Vec::new());
    }
    let too_large = || {
        format!(
            "out of memory: {len} values of {} bytes cannot be allocated",
            std::mem::size_of::<T>()
        )
    };
    let layout = std::alloc::Layout::array::<T>(len).map_err(|_| too_large())?;
    // SAFETY: the layout is non-zero in size; the allocation has the layout of `len` values of
    // T, as `Vec::from_raw_parts` requires, and all-zero bytes are a valid T (the caller's word).
    let p = unsafe { std::alloc::alloc_zeroed(layout) }.cast::<T>();
    if p.is_null() {
        return Err(too_large());
    }
    Ok(unsafe { Vec::from_raw_parts(p, len, len) })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What no machine holds is an error the bridge throws to C++ (and the user reads), not an
    /// abort: the layout's own overflow, and an allocation the system refuses.
    #[test]
    fn memory_that_cannot_be_had_is_an_error() {
        let mut leaves = Vec::new();
        let e = resize_leaves(&mut leaves, usize::MAX / 2).unwrap_err();
        assert!(e.contains("out of memory"), "{e}");
        let mut pixels = Vec::new();
        let e = resize_f32s(&mut pixels, 1 << 60).unwrap_err();
        assert!(e.contains("out of memory"), "{e}");
        resize_f32s(&mut pixels, 3).unwrap();
        assert_eq!(pixels, [0.0; 3]);
    }
}
