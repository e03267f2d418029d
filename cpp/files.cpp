// Errors and file checks shared by the VDB and image code (declared in cpp/internal.h). Every
// message names the file and the reason; cxx turns the exception into the Rust Err.

#include "volgrad/cpp/internal.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <system_error>

namespace fs = std::filesystem;

namespace volgrad {

// ------------------------------------------------------------------------------------------------
// Errors

[[noreturn]] void fail(const std::string& msg) { throw BridgeError(msg); }

std::string quoted(const std::string& path) { return "'" + path + "'"; }

std::string errno_text(int err) {
    if (err == ENOENT) return "no such file or directory";
    if (err == EACCES || err == EPERM) return "permission denied";
    if (err == EISDIR) return "is a directory";
    if (err == ENOSPC) return "no space left on device";
    if (err == EROFS) return "read-only file system";
    return std::strerror(err);
}

// ------------------------------------------------------------------------------------------------
// Files

std::string to_std(rust::Str s) { return std::string(s.data(), s.size()); }

void check_readable(const std::string& path) {
    std::error_code ec;
    const fs::file_status st = fs::status(path, ec);
    if (ec || !fs::exists(st)) {
        if (ec && ec != std::errc::no_such_file_or_directory) {
            fail("cannot open " + quoted(path) + ": " + ec.message());
        }
        fail("cannot open " + quoted(path) + ": no such file");
    }
    if (fs::is_directory(st)) fail("cannot open " + quoted(path) + ": it is a directory");
    if (!fs::is_regular_file(st)) fail("cannot open " + quoted(path) + ": not a regular file");
    std::ifstream probe(path, std::ios::binary);
    if (!probe) fail("cannot open " + quoted(path) + ": " + errno_text(errno));
}

void check_writable_target(const std::string& path) {
    const fs::path p(path);
    fs::path dir = p.parent_path();
    if (dir.empty()) dir = ".";
    std::error_code ec;
    if (!fs::exists(dir, ec)) {
        fail("cannot write " + quoted(path) + ": directory " + quoted(dir.string()) +
             " does not exist");
    }
    if (!fs::is_directory(dir, ec)) {
        fail("cannot write " + quoted(path) + ": " + quoted(dir.string()) + " is not a directory");
    }
    if (fs::is_directory(p, ec)) fail("cannot write " + quoted(path) + ": it is a directory");
}

fs::path temporary_beside(const std::string& path, const std::string& extension) {
    const fs::path p(path);
    const std::string name =
        "." + p.filename().string() + "." + std::to_string(::getpid()) + ".tmp" + extension;
    return p.parent_path() / name;
}

void commit_file(const fs::path& tmp, const std::string& path) {
    // On the disk before the rename: a crash must leave the old file or the whole new one.
    const int fd = ::open(tmp.c_str(), O_RDONLY);
    const bool synced = fd >= 0 && ::fsync(fd) == 0;
    const int sync_errno = errno;
    if (fd >= 0) ::close(fd);
    if (!synced) {
        std::error_code ignored;
        fs::remove(tmp, ignored);
        fail("cannot write " + quoted(path) + ": " + errno_text(sync_errno));
    }
    std::error_code ec;
    fs::rename(tmp, path, ec);
    if (ec) {
        std::error_code ignored;
        fs::remove(tmp, ignored);
        fail("cannot write " + quoted(path) + ": cannot replace it: " + ec.message());
    }
}

}  // namespace volgrad
