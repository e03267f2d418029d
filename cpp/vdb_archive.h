// The VDB archive reader behind cpp/vdb_read.cpp: a file's header and grid descriptors read and
// checked against the file size, grids read one at a time, and float grids' voxel buffers located
// for decoding on several threads. Internal to cpp/vdb_read.cpp (the only file that includes it):
// it pulls in OpenVDB's headers, which the bridge's other translation units do not need.
//
// VDB files are read through a small io::Archive subclass rather than io::File, because:
//  * io::File lists grids sorted by name (its descriptors live in a std::multimap), while the
//    bridge promises file order; the subclass sees the descriptors in the order they are stored.
//  * It validates every grid's byte range against the file size before reading anything, and sets
//    the stream to throw on a short read, so a truncated file raises instead of being read from
//    uninitialised lengths (OpenVDB does not check its istream after every read). The length
//    fields of the file and grid metadata and of the descriptors are checked before OpenVDB
//    allocates strings of those sizes (garbage lengths otherwise cost multi-GB allocations).
//  * It reads a float or double grid's metadata, transform and topology the way Archive::readGrid
//    does, but decodes the voxel buffers itself, with OpenVDB's decoder on several threads, from
//    the grid's bytes read into memory (OpenVDB's reader decodes one leaf after another: most of a
//    large grid's load). Other grids, and level sets to be converted to fog, go through readGrid.
//    Known limit: a file whose compressed voxel payload is corrupted in place (not truncated) can
//    still crash inside OpenVDB 10 (io::bloscFromStream reads an uncompressed chunk into its buffer
//    before checking the chunk's length); nothing outside OpenVDB can check that cheaply.
#pragma once

#include "volgrad/cpp/internal.h"

#include <openvdb/Grid.h>
#include <openvdb/Metadata.h>
#include <openvdb/io/Archive.h>
#include <openvdb/io/Compression.h>
#include <openvdb/io/GridDescriptor.h>
#include <openvdb/io/io.h>
#include <openvdb/openvdb.h>

#include <algorithm>
#include <cerrno>
#include <filesystem>
#include <fstream>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>
#include <vector>

#include <fcntl.h>
#include <unistd.h>

namespace volgrad {

namespace fs = std::filesystem;


/// The bytes `[begin, end)` of a file, read into memory, so that several threads can read them at
/// once without a system call per seek. Read, not mapped: a mapped file that another program
/// truncates or rewrites in place while the decoders run faults them (SIGBUS), where a copy
/// only goes stale; a file shorter than its checked size by the time it is read is an error.
class FileBytes {
public:
    FileBytes(const std::string& path, int64_t begin, int64_t end) : first_(begin) {
        const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
        if (fd < 0) fail("cannot open " + quoted(path) + ": " + errno_text(errno));
        size_ = size_t(std::max<int64_t>(end - begin, 0));
        data_.reset(new char[size_ == 0 ? 1 : size_]);
        size_t done = 0;
        while (done < size_) {
            const ssize_t n = ::pread(fd, data_.get() + done, size_ - done, off_t(begin + done));
            if (n < 0 && errno == EINTR) continue;
            if (n <= 0) {
                const int err = errno;
                ::close(fd);
                fail("cannot read " + quoted(path) + ": " +
                     (n == 0 ? std::string("it is shorter than when it was opened (changed while "
                                           "being read?)")
                             : errno_text(err)));
            }
            done += size_t(n);
        }
        ::close(fd);
    }
    FileBytes(const FileBytes&) = delete;
    FileBytes& operator=(const FileBytes&) = delete;
    const char* data() const { return data_.get(); }
    size_t size() const { return size_; }
    /// The file offset of `data()[0]`.
    int64_t first() const { return first_; }

private:
    std::unique_ptr<char[]> data_;
    size_t size_ = 0;
    int64_t first_ = 0;
};

/// A seekable stream buffer over bytes in memory whose positions are the file's offsets:
/// OpenVDB's decoders read std::istreams (and seek to offsets in the file), and each thread that
/// decodes leaves needs a stream of its own over the same bytes.
class MemoryBuffer : public std::streambuf {
public:
    explicit MemoryBuffer(const FileBytes& bytes) : first_(bytes.first()) {
        char* begin = const_cast<char*>(bytes.data());  // only ever read: the get area
        setg(begin, begin, begin + bytes.size());
    }

protected:
    pos_type seekoff(off_type off, std::ios_base::seekdir dir, std::ios_base::openmode) override {
        // In offsets from the get area's start.
        const off_type target = dir == std::ios_base::beg   ? off - first_
                                : dir == std::ios_base::cur ? (gptr() - eback()) + off
                                                            : (egptr() - eback()) + off;
        if (target < 0 || target > egptr() - eback()) return pos_type(off_type(-1));
        setg(eback(), eback() + target, egptr());
        return pos_type(target + first_);
    }
    pos_type seekpos(pos_type pos, std::ios_base::openmode mode) override {
        return seekoff(off_type(pos), std::ios_base::beg, mode);
    }

private:
    off_type first_;
};

/// What decoding a grid's voxel buffers needs after `VdbArchive::read_topology`: the grid's bytes,
/// a stream whose OpenVDB state (format version, compression, half floats, background) is the
/// grid's, and where each leaf's buffer starts, in leaf-iteration order (the order they are
/// stored in).
struct DeferredBuffers {
    std::unique_ptr<FileBytes> file;
    std::unique_ptr<MemoryBuffer> buffer;
    std::unique_ptr<std::istream> state;
    openvdb::io::StreamMetadata::Ptr meta;  // the grid's stream metadata, which `state` points to
    std::vector<std::streamoff> offsets;
    bool from_half = false;
    std::mutex copying_state;  // the decoding threads copy `state` one at a time
};

/// Minimal io::Archive client: header, descriptors in file order, one grid at a time.
class VdbArchive : public openvdb::io::Archive {
public:
    /// Opens `path` and reads the header and every grid descriptor (validated against the file
    /// size). Throws plain exceptions; callers wrap them with context.
    explicit VdbArchive(const std::string& path) : path_(path) {
        file_size_ = static_cast<int64_t>(fs::file_size(path));
        if (file_size_ == 0) corrupt("the file is empty");
        is_.open(path, std::ios::in | std::ios::binary);
        if (!is_) fail("cannot open " + quoted(path) + ": " + errno_text(errno));
        // Every short read throws (std::ios_base::failure) instead of leaving a length unset.
        is_.exceptions(std::ios::failbit | std::ios::badbit);

        // The format version is checked here because readHeader() only warns about it.
        if (file_size_ < 8 || pod<int64_t>() != openvdb::OPENVDB_MAGIC) corrupt("not a VDB file");
        const auto version = pod<uint32_t>();
        if (version > openvdb::OPENVDB_FILE_VERSION) {
            corrupt("file format version " + std::to_string(version) + " is newer than the " +
                    std::to_string(openvdb::OPENVDB_FILE_VERSION) + " this OpenVDB reads");
        }
        is_.seekg(0);
        readHeader(is_);
        stream_meta_ = std::make_shared<openvdb::io::StreamMetadata>();
        stream_meta_->setSeekable(true);
        openvdb::io::setStreamMetadataPtr(is_, stream_meta_, /*transfer=*/false);
        setFormatVersion(is_);
        setLibraryVersion(is_);
        setDataCompression(is_);
        // Lengths are validated before OpenVDB allocates buffers of those sizes.
        check_meta_map(file_size_, "the file metadata");
        file_meta_.readMeta(is_);

        const int32_t count = readGridCount(is_);
        // A descriptor takes at least 3 lengths + 3 offsets = 36 bytes.
        const int64_t rest = file_size_ - int64_t(is_.tellg());
        if (count < 0 || int64_t(count) * 36 > rest) {
            corrupt("it declares " + std::to_string(count) + " grids but only " +
                    std::to_string(rest) + " bytes follow");
        }
        if (inputHasGridOffsets()) {
            for (int32_t i = 0; i < count; ++i) {
                const int64_t here = int64_t(is_.tellg());
                if (here >= file_size_) {
                    corrupt("grid " + std::to_string(i) + " of " + std::to_string(count) +
                            " starts past the end of the file");
                }
                check_descriptor(i);
                openvdb::io::GridDescriptor gd;
                gd.read(is_);  // also checks that the grid type is registered
                const std::string name = gd.gridName();
                if (gd.getGridPos() != int64_t(is_.tellg()) || gd.getBlockPos() < gd.getGridPos() ||
                    gd.getEndPos() < gd.getBlockPos()) {
                    corrupt("grid '" + name + "' has inconsistent offsets");
                }
                if (gd.getEndPos() > file_size_) {
                    corrupt("grid '" + name + "' ends at byte " + std::to_string(gd.getEndPos()) +
                            " but the file has " + std::to_string(file_size_) + " bytes");
                }
                descriptors_.push_back(gd);
                gd.seekToEnd(is_);
            }
        } else {
            // Old streamed layout (io::Stream): no offsets, so everything is read now, in order.
            NamedGridMap named;
            for (int32_t i = 0; i < count; ++i) {
                openvdb::io::GridDescriptor gd;
                openvdb::GridBase::Ptr grid = gd.read(is_);
                if (!grid) corrupt("cannot create a grid of type " + gd.gridType());
                Archive::readGrid(grid, gd, is_);
                descriptors_.push_back(gd);
                streamed_.push_back(grid);
                named[gd.uniqueName()] = grid;
            }
            for (const auto& gd : descriptors_) connectInstance(gd, named);
        }
    }

    size_t size() const { return descriptors_.size(); }
    std::string name(size_t i) const { return descriptors_[i].gridName(); }
    /// OpenVDB's type name of grid `i` ("Tree_float_5_4_3", ...), from its descriptor.
    std::string grid_type(size_t i) const { return descriptors_[i].gridType(); }
    const std::string& path() const { return path_; }

    /// Reads grid `i` completely (metadata, transform, tree).
    openvdb::GridBase::Ptr read_grid(size_t i, int depth = 0) {
        if (!streamed_.empty()) return streamed_[i];
        const openvdb::io::GridDescriptor& gd = descriptors_[i];
        openvdb::GridBase::Ptr grid = openvdb::GridBase::createGrid(gd.gridType());
        if (!grid) corrupt("cannot create a grid of type " + gd.gridType());
        grid->setSaveFloatAsHalf(gd.saveFloatAsHalf());
        check_grid_metadata(gd);
        Archive::readGrid(grid, gd, is_);
        if (gd.isInstance()) {
            // The tree is stored once, with the instance parent.
            if (depth > int(descriptors_.size())) corrupt("grid instances form a cycle");
            const auto parent = std::find_if(
                descriptors_.begin(), descriptors_.end(),
                [&](const auto& d) { return d.uniqueName() == gd.instanceParentName(); });
            if (parent == descriptors_.end()) {
                corrupt("grid '" + gd.gridName() + "' is an instance of a missing grid");
            }
            grid->setTree(read_grid(size_t(parent - descriptors_.begin()), depth + 1)->baseTreePtr());
        }
        return grid;
    }

    /// Whether grid `i` can be read by `read_topology` and its buffers decoded in parallel: a
    /// float or double grid with a tree of its own, in a file of the current layout (per-grid
    /// compression, format 222 and later). Anything else goes through OpenVDB's reader.
    bool can_defer_buffers(size_t i) const {
        const openvdb::io::GridDescriptor& gd = descriptors_[i];
        return streamed_.empty() && !gd.isInstance() &&
               fileVersion() >= openvdb::OPENVDB_FILE_VERSION_NODE_MASK_COMPRESSION &&
               (gd.gridType() == openvdb::FloatGrid::gridType() ||
                gd.gridType() == openvdb::DoubleGrid::gridType());
    }

    /// Grid `i` read as Archive::readGrid reads it (compression, metadata, transform, topology),
    /// but from the grid's bytes in memory and without its voxel buffers: the leaves are created with their
    /// masks and no values. `deferred` receives the stream state to decode the buffers with,
    /// which `find_leaf_buffers` then locates. Only for grids that `can_defer_buffers`.
    openvdb::GridBase::Ptr read_topology(size_t i, DeferredBuffers& deferred) {
        const openvdb::io::GridDescriptor& gd = descriptors_[i];
        check_grid_metadata(gd);
        deferred.file = std::make_unique<FileBytes>(path_, gd.getGridPos(), gd.getEndPos());
        deferred.buffer = std::make_unique<MemoryBuffer>(*deferred.file);
        deferred.state = std::make_unique<std::istream>(deferred.buffer.get());
        std::istream& is = *deferred.state;
        is.copyfmt(is_);  // the file's format version and compression, and short reads throw
        gd.seekToGrid(is);
        readGridCompression(is);

        openvdb::GridBase::Ptr grid = openvdb::GridBase::createGrid(gd.gridType());
        if (!grid) corrupt("cannot create a grid of type " + gd.gridType());
        grid->setSaveFloatAsHalf(gd.saveFloatAsHalf());
        deferred.from_half = gd.saveFloatAsHalf();
        deferred.meta = std::make_shared<openvdb::io::StreamMetadata>(*stream_meta_);
        deferred.meta->setHalfFloat(gd.saveFloatAsHalf());
        openvdb::io::setStreamMetadataPtr(is, deferred.meta, /*transfer=*/false);
        openvdb::io::setGridClass(is, openvdb::GRID_UNKNOWN);
        openvdb::io::setGridBackgroundValuePtr(is, nullptr);
        grid->readMeta(is);
        // Delayed-load metadata would make the decoders take each buffer's layout from it rather
        // than from the buffer itself; Archive::readGrid drops it from the grid too.
        if ((*grid)[openvdb::GridBase::META_FILE_DELAYED_LOAD]) {
            grid->removeMeta(openvdb::GridBase::META_FILE_DELAYED_LOAD);
        }
        deferred.meta->gridMetadata() = static_cast<openvdb::MetaMap&>(*grid);
        openvdb::io::setGridClass(is, grid->getGridClass());
        grid->readTransform(is);
        grid->readTopology(is);  // also points the stream's background at the tree's
        if (int64_t(is.tellg()) != gd.getBlockPos()) {
            corrupt("the topology of grid '" + gd.gridName() + "' does not end where its "
                    "voxel data begins");
        }
        return grid;
    }

    /// Where grid `i`'s stored data ends (to check the located buffers against).
    int64_t grid_end(size_t i) const { return descriptors_[i].getEndPos(); }

private:
    [[noreturn]] void corrupt(const std::string& why) const { throw std::runtime_error(why); }

    /// Checks the length fields of grid `gd`'s metadata before OpenVDB reads it.
    void check_grid_metadata(const openvdb::io::GridDescriptor& gd) {
        gd.seekToGrid(is_);
        if (fileVersion() >= openvdb::OPENVDB_FILE_VERSION_NODE_MASK_COMPRESSION) pod<uint32_t>();
        check_meta_map(gd.getEndPos(), "the metadata of grid '" + gd.gridName() + "'");
        gd.seekToGrid(is_);
    }

    template <typename T>
    T pod() {
        T v;
        is_.read(reinterpret_cast<char*>(&v), sizeof v);
        return v;
    }

    /// Skips `n` bytes, which must end at or before byte `limit`.
    void skip(uint64_t n, int64_t limit, const std::string& what) {
        const int64_t here = int64_t(is_.tellg());
        if (here > limit || n > uint64_t(limit - here)) corrupt(what + " runs past its end");
        is_.seekg(int64_t(n), std::ios::cur);
    }

    void skip_string(int64_t limit, const std::string& what) { skip(pod<uint32_t>(), limit, what); }

    /// Checks the length fields of a serialized MetaMap (count, then per entry: name, type name,
    /// byte count + value), leaving the stream where it was.
    void check_meta_map(int64_t limit, const std::string& what) {
        const auto start = is_.tellg();
        const auto count = pod<uint32_t>();
        if (uint64_t(count) * 12 > uint64_t(std::max<int64_t>(0, limit - int64_t(is_.tellg())))) {
            corrupt(what + " declares " + std::to_string(count) + " entries, more than fit");
        }
        for (uint32_t i = 0; i < count; ++i) {
            skip_string(limit, what);
            skip_string(limit, what);
            skip(pod<uint32_t>(), limit, what);
        }
        is_.seekg(start);
    }

    /// Checks the string lengths of grid descriptor `i`, leaving the stream where it was.
    void check_descriptor(int32_t i) {
        const auto start = is_.tellg();
        const std::string what = "the descriptor of grid " + std::to_string(i);
        skip_string(file_size_, what);  // unique name
        skip_string(file_size_, what);  // grid type
        if (fileVersion() >= openvdb::OPENVDB_FILE_VERSION_GRID_INSTANCING) {
            skip_string(file_size_, what);  // instance parent
        }
        skip(3 * sizeof(int64_t), file_size_, what);
        is_.seekg(start);
    }

    std::string path_;
    int64_t file_size_ = 0;
    std::ifstream is_;
    openvdb::io::StreamMetadata::Ptr stream_meta_;
    openvdb::MetaMap file_meta_;
    std::vector<openvdb::io::GridDescriptor> descriptors_;
    std::vector<openvdb::GridBase::Ptr> streamed_;
};

inline std::string corrupt_context(const std::string& path) {
    return quoted(path) + " is not a valid VDB file (truncated or corrupt)";
}

/// Opens a VDB file for reading, with plain errors for missing / corrupt files.
inline std::unique_ptr<VdbArchive> open_vdb(const std::string& path) {
    init_openvdb();
    check_readable(path);
    return with_context(corrupt_context(path), [&] { return std::make_unique<VdbArchive>(path); });
}

inline openvdb::GridBase::Ptr read_grid_checked(VdbArchive& vdb, size_t i) {
    return with_context(corrupt_context(vdb.path()), [&] { return vdb.read_grid(i); });
}
}  // namespace volgrad
