// Helpers shared by the translation units of the C++ side of the bridge: errors, and the file
// checks and atomic replacement that reading and writing VDB files and images have in common.
// Defined in cpp/files.cpp, except init_openvdb (cpp/vdb_read.cpp).
//
// Internal: cpp/bridge.h (and so the cxx-generated glue) does not include it. It includes no
// OpenVDB or OpenImageIO header, so that cpp/images.cpp and cpp/files.cpp compile without
// OpenVDB's heavy headers; OpenVDB-typed code stays inside cpp/vdb_read.cpp and cpp/vdb_write.cpp.
#pragma once

#include "rust/cxx.h"

#include <filesystem>
#include <ios>
#include <new>
#include <stdexcept>
#include <string>

namespace volgrad {

// ------------------------------------------------------------------------------------------------
// Errors

/// An error whose message already names the file and the reason: passed through unchanged.
struct BridgeError : std::runtime_error {
    using std::runtime_error::runtime_error;
};

[[noreturn]] void fail(const std::string& msg);

std::string quoted(const std::string& path);

std::string errno_text(int err);

/// Runs `body`, turning any exception that does not already carry context into a BridgeError
/// prefixed by `context` (e.g. "'x.vdb' is not a valid VDB file (truncated or corrupt)").
/// OpenVDB's exceptions derive from std::exception only (what() is e.g. "IoError: ..."), so the
/// last clause covers them and this header needs no OpenVDB include.
template <typename F>
auto with_context(const std::string& context, F&& body) -> decltype(body()) {
    try {
        return body();
    } catch (const BridgeError&) {
        throw;
    } catch (const std::ios_base::failure&) {
        fail(context + ": unexpected end of file");
    } catch (const std::bad_alloc&) {
        fail(context + ": out of memory (a size field in the file is probably corrupt)");
    } catch (const std::exception& e) {
        fail(context + ": " + e.what());
    }
}

// ------------------------------------------------------------------------------------------------
// Files

std::string to_std(rust::Str s);

/// Fails with a plain message unless `path` names a readable regular file.
void check_readable(const std::string& path);

/// Fails unless the directory that will hold `path` exists and `path` is not a directory.
void check_writable_target(const std::string& path);

/// A temporary name beside `path` that no other process writing it at once takes and no user
/// file is likely to have: `.NAME.PID.tmp`, then `extension` (an image writer picks its format
/// by it).
std::filesystem::path temporary_beside(const std::string& path, const std::string& extension);

/// Flushes `tmp` to the disk and renames it over `path` (as the Rust side's whole-file writes
/// do), removing `tmp` on failure.
void commit_file(const std::filesystem::path& tmp, const std::string& path);

// ------------------------------------------------------------------------------------------------
// OpenVDB

/// Initialises OpenVDB (registers the grid and metadata types) once per process.
void init_openvdb();

}  // namespace volgrad
