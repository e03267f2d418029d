//! Builds the C++ half of the cxx bridge (`src/io/bridge.rs` <-> `cpp/bridge.cpp`) against the system
//! OpenVDB and OpenImageIO (Debian: libopenvdb-dev, libopenimageio-dev, libtbb-dev, libboost-dev).

fn main() {
    cxx_build::bridge("src/io/bridge.rs")
        .file("cpp/bridge.cpp")
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
    println!("cargo:rerun-if-changed=cpp/bridge.cpp");
    println!("cargo:rerun-if-changed=cpp/bridge.h");
}
