//! Builds the C++ half of the cxx bridge (`src/io/bridge.rs` <-> `cpp/`) against the system
//! OpenVDB and OpenImageIO (Debian: libopenvdb-dev, libopenimageio-dev, libtbb-dev, libboost-dev).
//!
//! `cpp/bridge.h` declares the bridge functions for the generated glue; they are defined by job:
//! `cpp/vdb_read.cpp` (grids copied into plain data, through the hardened archive reader in
//! `cpp/vdb_archive.h`),
//! `cpp/vdb_write.cpp` (grids built from plain data, written to a temporary file then renamed) and
//! `cpp/images.cpp` (OpenImageIO, no OpenVDB headers), with the errors and file checks they share
//! in `cpp/files.cpp` (declared in `cpp/internal.h`).

/// The translation units; each is also a `rerun-if-changed` input.
const SOURCES: [&str; 4] = [
    "cpp/vdb_read.cpp",
    "cpp/vdb_write.cpp",
    "cpp/images.cpp",
    "cpp/files.cpp",
];

fn main() {
    cxx_build::bridge("src/io/bridge.rs")
        .files(SOURCES)
        .std("c++17")
        .flag_if_supported("-O2")
        // OpenVDB 10 and OIIO 2.4 headers live in /usr/include: as system headers their own
        // warnings are already silenced, and no extra include directory is needed.
        .compile("volgrad_bridge");

    // Imath: the OpenVDB templates we instantiate convert half floats (imath_half_to_float_table).
    for lib in ["openvdb", "OpenImageIO", "OpenImageIO_Util", "tbb", "Imath"] {
        println!("cargo:rustc-link-lib={lib}");
    }

    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=src/io/bridge.rs");
    for file in SOURCES
        .iter()
        .chain(&["cpp/bridge.h", "cpp/internal.h", "cpp/vdb_archive.h"])
    {
        println!("cargo:rerun-if-changed={file}");
    }
}
