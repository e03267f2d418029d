// Reading VDB files for the cxx bridge declared in src/io/bridge.rs (list_grids, read_float_grid):
// OpenVDB (10.x) behind plain-data functions. Nothing OpenVDB-typed crosses the bridge.
// A level set can be converted to a fog volume on the way (OpenVDB's own sdfToFogVolume), because
// that conversion needs the tree's inactive interior tiles, which the plain data does not carry.
//
// Conventions (see the doc comments in src/io/bridge.rs):
//  * index_to_world is column-vector convention, row-major: the TRANSPOSE of OpenVDB's Mat4d, which
//    is row-vector convention (world = index * M).
//  * Leaves cross as origin + the whole 512-value buffer + 8 active-mask words; active tiles as min
//    corner + edge length + value.
//  * Every error is a C++ exception whose what() names the file and the reason; cxx turns it into
//    the Rust Err.
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
//    the file mapped into memory (OpenVDB's reader decodes one leaf after another: most of a large
//    grid's load). Other grids, and level sets to be converted to fog, go through readGrid.
//    Known limit: a file whose compressed voxel payload is corrupted in place (not truncated) can
//    still crash inside OpenVDB 10 (io::bloscFromStream reads an uncompressed chunk into its buffer
//    before checking the chunk's length); nothing outside OpenVDB can check that cheaply.

#include "volgrad/cpp/bridge.h"
#include "volgrad/cpp/internal.h"
#include "volgrad/src/io/bridge.rs.h"

#include <openvdb/Grid.h>
#include <openvdb/Metadata.h>
#include <openvdb/io/Archive.h>
#include <openvdb/io/Compression.h>
#include <openvdb/io/GridDescriptor.h>
#include <openvdb/io/io.h>
#include <openvdb/math/Maps.h>
#include <openvdb/math/Transform.h>
#include <openvdb/openvdb.h>
#include <openvdb/tools/LevelSetUtil.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>
#include <vector>

#include <fcntl.h>
#include <sys/mman.h>
#include <unistd.h>

namespace fs = std::filesystem;

namespace volgrad {
namespace {

// ------------------------------------------------------------------------------------------------
// Text forms of metadata values (shortest round-trip form for floating point)

template <typename T>
std::string num_text(T v) {
    if constexpr (std::is_same_v<T, bool>) {
        return v ? "true" : "false";
    } else if constexpr (std::is_floating_point_v<T>) {
        if (std::isnan(v)) return "nan";
        if (std::isinf(v)) return v > 0 ? "inf" : "-inf";
        char buf[64];
        const auto r = std::to_chars(buf, buf + sizeof buf, v);
        return std::string(buf, r.ptr);
    } else {
        return std::to_string(v);
    }
}

template <typename V>
std::string vec_text(const V& v, int n) {
    std::string s = "[";
    for (int i = 0; i < n; ++i) {
        if (i) s += ", ";
        s += num_text(v[i]);
    }
    return s + "]";
}

std::string meta_text(const openvdb::Metadata& m) {
    using namespace openvdb;
    if (auto p = dynamic_cast<const StringMetadata*>(&m)) return p->value();
    if (auto p = dynamic_cast<const FloatMetadata*>(&m)) return num_text(p->value());
    if (auto p = dynamic_cast<const DoubleMetadata*>(&m)) return num_text(p->value());
    if (auto p = dynamic_cast<const BoolMetadata*>(&m)) return num_text(p->value());
    if (auto p = dynamic_cast<const Int32Metadata*>(&m)) return num_text(p->value());
    if (auto p = dynamic_cast<const Int64Metadata*>(&m)) return num_text(p->value());
    if (auto p = dynamic_cast<const Vec3IMetadata*>(&m)) return vec_text(p->value(), 3);
    if (auto p = dynamic_cast<const Vec3SMetadata*>(&m)) return vec_text(p->value(), 3);
    if (auto p = dynamic_cast<const Vec3DMetadata*>(&m)) return vec_text(p->value(), 3);
    if (auto p = dynamic_cast<const Vec2IMetadata*>(&m)) return vec_text(p->value(), 2);
    if (auto p = dynamic_cast<const Vec2SMetadata*>(&m)) return vec_text(p->value(), 2);
    if (auto p = dynamic_cast<const Vec2DMetadata*>(&m)) return vec_text(p->value(), 2);
    return m.str();
}

rust::Vec<MetaEntry> meta_entries(const openvdb::MetaMap& meta) {
    rust::Vec<MetaEntry> out;
    for (auto it = meta.beginMeta(); it != meta.endMeta(); ++it) {
        if (!it->second) continue;
        MetaEntry e;
        e.name = rust::String(it->first);
        e.type_name = rust::String(it->second->typeName());
        e.value = rust::String(meta_text(*it->second));
        out.push_back(std::move(e));
    }
    return out;
}

// ------------------------------------------------------------------------------------------------
// Transforms

std::array<double, 16> column_major_affine(const openvdb::math::Transform& xf, bool& linear) {
    std::array<double, 16> out;
    const auto map = xf.baseMap();
    linear = map->isLinear();
    if (!linear) {
        out.fill(std::numeric_limits<double>::quiet_NaN());
        return out;
    }
    // OpenVDB: world_j = sum_i index_i * M(i, j) + M(3, j). Ours: world_i = sum_j C[i][j] index_j.
    const openvdb::Mat4d m = map->getAffineMap()->getMat4();
    for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) out[4 * i + j] = m(j, i);
    return out;
}

bool is_axis_aligned(const std::array<double, 16>& c, bool linear) {
    if (!linear) return false;
    double diag = 0.0;
    for (int i = 0; i < 3; ++i) diag = std::max(diag, std::abs(c[4 * i + i]));
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            if (i != j && std::abs(c[4 * i + j]) > 1e-9 * diag) return false;
    return true;
}

// ------------------------------------------------------------------------------------------------
// Reading VDB files

/// A whole file mapped read-only into memory, so that several threads can read it at once without
/// a system call per seek.
class MappedFile {
public:
    explicit MappedFile(const std::string& path) {
        const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
        if (fd < 0) fail("cannot open " + quoted(path) + ": " + errno_text(errno));
        size_ = size_t(fs::file_size(path));
        void* p = ::mmap(nullptr, size_, PROT_READ, MAP_PRIVATE, fd, 0);
        const int err = errno;
        ::close(fd);
        if (p == MAP_FAILED) fail("cannot map " + quoted(path) + ": " + errno_text(err));
        data_ = static_cast<const char*>(p);
    }
    MappedFile(const MappedFile&) = delete;
    MappedFile& operator=(const MappedFile&) = delete;
    ~MappedFile() { ::munmap(const_cast<char*>(data_), size_); }
    const char* data() const { return data_; }
    size_t size() const { return size_; }

private:
    const char* data_ = nullptr;
    size_t size_ = 0;
};

/// A seekable stream buffer over bytes in memory: OpenVDB's decoders read std::istreams, and each
/// thread that decodes leaves needs a stream of its own over the same mapped file.
class MemoryBuffer : public std::streambuf {
public:
    explicit MemoryBuffer(const MappedFile& file) {
        char* begin = const_cast<char*>(file.data());  // only ever read: the get area
        setg(begin, begin, begin + file.size());
    }

protected:
    pos_type seekoff(off_type off, std::ios_base::seekdir dir, std::ios_base::openmode) override {
        const char* base = dir == std::ios_base::beg   ? eback()
                           : dir == std::ios_base::cur ? gptr()
                                                       : egptr();
        if (off < eback() - base || off > egptr() - base) return pos_type(off_type(-1));
        setg(eback(), const_cast<char*>(base) + off, egptr());
        return pos_type(gptr() - eback());
    }
    pos_type seekpos(pos_type pos, std::ios_base::openmode mode) override {
        return seekoff(off_type(pos), std::ios_base::beg, mode);
    }
};

/// What decoding a grid's voxel buffers needs after `VdbArchive::read_topology`: the mapped file,
/// a stream whose OpenVDB state (format version, compression, half floats, background) is the
/// grid's, and where each leaf's buffer starts, in leaf-iteration order (the order they are
/// stored in).
struct DeferredBuffers {
    std::unique_ptr<MappedFile> file;
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
    /// but from the mapped file and without its voxel buffers: the leaves are created with their
    /// masks and no values. `deferred` receives the stream state to decode the buffers with,
    /// which `find_leaf_buffers` then locates. Only for grids that `can_defer_buffers`.
    openvdb::GridBase::Ptr read_topology(size_t i, DeferredBuffers& deferred) {
        const openvdb::io::GridDescriptor& gd = descriptors_[i];
        check_grid_metadata(gd);
        deferred.file = std::make_unique<MappedFile>(path_);
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

std::string corrupt_context(const std::string& path) {
    return quoted(path) + " is not a valid VDB file (truncated or corrupt)";
}

/// Opens a VDB file for reading, with plain errors for missing / corrupt files.
std::unique_ptr<VdbArchive> open_vdb(const std::string& path) {
    init_openvdb();
    check_readable(path);
    return with_context(corrupt_context(path), [&] { return std::make_unique<VdbArchive>(path); });
}

openvdb::GridBase::Ptr read_grid_checked(VdbArchive& vdb, size_t i) {
    return with_context(corrupt_context(vdb.path()), [&] { return vdb.read_grid(i); });
}

GridSummary summarize(const openvdb::GridBase& grid) {
    GridSummary s;
    s.name = rust::String(grid.getName());
    s.value_type = rust::String(grid.valueType());
    s.grid_class = rust::String(openvdb::GridBase::gridClassToString(grid.getGridClass()));

    const openvdb::math::Transform& xf = grid.constTransform();
    bool linear = false;
    const auto m = column_major_affine(xf, linear);
    std::copy(m.begin(), m.end(), s.index_to_world.begin());
    s.linear = linear;
    s.axis_aligned = is_axis_aligned(m, linear);
    const openvdb::Vec3d vs = xf.voxelSize();
    for (int i = 0; i < 3; ++i) s.voxel_size[i] = vs[i];

    s.active_voxels = grid.activeVoxelCount();
    s.leaf_count = grid.baseTree().leafCount();
    s.active_tiles = grid.baseTree().activeTileCount();

    const openvdb::CoordBBox bbox = grid.evalActiveVoxelBoundingBox();
    for (int i = 0; i < 3; ++i) {
        s.index_min[i] = bbox.min()[i];
        s.index_max[i] = bbox.max()[i];
        s.world_min[i] = std::numeric_limits<double>::infinity();
        s.world_max[i] = -std::numeric_limits<double>::infinity();
    }
    if (!bbox.empty()) {
        const openvdb::Vec3d lo = bbox.min().asVec3d() - 0.5, hi = bbox.max().asVec3d() + 0.5;
        for (int c = 0; c < 8; ++c) {
            const openvdb::Vec3d corner((c & 1) ? hi.x() : lo.x(), (c & 2) ? hi.y() : lo.y(),
                                        (c & 4) ? hi.z() : lo.z());
            const openvdb::Vec3d w = xf.indexToWorld(corner);
            for (int i = 0; i < 3; ++i) {
                s.world_min[i] = std::min(s.world_min[i], w[i]);
                s.world_max[i] = std::max(s.world_max[i], w[i]);
            }
        }
    }
    s.saved_as_half = grid.saveFloatAsHalf();
    s.metadata = meta_entries(grid);
    return s;
}

/// Copies a float (or double, converted) grid into FloatGridData. The leaves' values come from
/// `fill_values(nodes, begin, end, out)`, which writes the values of leaf l to out[l].values for
/// the leaves [begin, end) of `nodes` (leaf-iteration order); it runs on `threads` threads.
template <typename GridT, typename FillValues>
FloatGridData copy_grid(const GridT& grid, uint32_t threads, FillValues&& fill_values) {
    using TreeT = typename GridT::TreeType;
    using LeafT = typename TreeT::LeafNodeType;
    static_assert(LeafT::SIZE == 512, "volgrad expects 8^3 leaves");
    const TreeT& tree = grid.tree();

    FloatGridData d;
    d.name = rust::String(grid.getName());
    d.grid_class = rust::String(openvdb::GridBase::gridClassToString(grid.getGridClass()));
    bool linear = false;
    const auto m = column_major_affine(grid.constTransform(), linear);
    std::copy(m.begin(), m.end(), d.index_to_world.begin());
    d.background = static_cast<float>(tree.background());
    d.saved_as_half = grid.saveFloatAsHalf();

    // Sized once by Rust and filled through data(): push_back would call into Rust per leaf.
    const size_t leaves = tree.leafCount();
    resize_leaves(d.leaves, leaves);
    LeafData* out = d.leaves.data();
    std::vector<const LeafT*> nodes;
    nodes.reserve(leaves);
    for (auto leaf = tree.cbeginLeaf(); leaf; ++leaf) nodes.push_back(leaf.getLeaf());
    if (nodes.size() != leaves) fail("the tree's leaf count changed while it was copied");
    // On `threads` threads: one thread copying 100 MiB of leaves was a third of a large grid's
    // load.
    tbb::task_arena arena(int(std::max<uint32_t>(threads, 1)));
    arena.execute([&] {
        tbb::parallel_for(tbb::blocked_range<size_t>(0, leaves, 64), [&](const auto& range) {
            for (size_t l = range.begin(); l != range.end(); ++l) {
                const LeafT& leaf = *nodes[l];
                const openvdb::Coord o = leaf.origin();
                for (int i = 0; i < 3; ++i) out[l].origin[i] = o[i];
                const auto& mask = leaf.getValueMask();
                for (openvdb::Index w = 0; w < LeafT::NodeMaskType::WORD_COUNT; ++w) {
                    out[l].active[w] = mask.template getWord<openvdb::Index64>(w);
                }
            }
            fill_values(nodes.data(), range.begin(), range.end(), out);
        });
    });

    // Active tiles only: stop the value iterator above the leaf level.
    auto it = tree.cbeginValueOn();
    it.setMaxDepth(TreeT::ValueOnCIter::LEAF_DEPTH - 1);
    for (; it; ++it) {
        if (it.isVoxelValue()) continue;
        openvdb::CoordBBox bb;
        it.getBoundingBox(bb);
        for (int i = 0; i < 3; ++i) d.tile_origins.push_back(bb.min()[i]);
        d.tile_sizes.push_back(static_cast<uint32_t>(bb.dim().x()));
        d.tile_values.push_back(static_cast<float>(*it));
    }
    // Inactive tiles are not copied (the brick map reads 0 there), so count those that OpenVDB
    // would read as something other than the background: the caller decides whether that matters.
    auto off = tree.cbeginValueOff();
    off.setMaxDepth(TreeT::ValueOffCIter::LEAF_DEPTH - 1);
    for (; off; ++off) {
        if (!off.isVoxelValue() && *off != tree.background()) ++d.inactive_tiles_off_background;
    }
    d.metadata = meta_entries(grid);
    return d;
}

/// Values from the leaves' own buffers: a grid OpenVDB read completely.
template <typename LeafT>
void copy_leaf_values(const LeafT* const* nodes, size_t begin, size_t end, LeafData* out) {
    for (size_t l = begin; l != end; ++l) {
        const auto* buffer = nodes[l]->buffer().data();
        std::transform(buffer, buffer + LeafT::SIZE, out[l].values.begin(),
                       [](auto v) { return static_cast<float>(v); });
    }
}

/// Finds where each leaf's stored buffer starts by walking the buffers in storage order (which is
/// leaf-iteration order) through OpenVDB's own decoder in its seek mode (no destination: it reads
/// each buffer's header and skips its payload), and checks that they end where the grid does.
template <typename GridT>
void find_leaf_buffers(const GridT& grid, int64_t grid_end, DeferredBuffers& deferred) {
    using TreeT = typename GridT::TreeType;
    using LeafT = typename TreeT::LeafNodeType;
    const TreeT& tree = grid.tree();
    std::istream& is = *deferred.state;
    deferred.offsets.reserve(tree.leafCount());
    for (auto leaf = tree.cbeginLeaf(); leaf; ++leaf) {
        deferred.offsets.push_back(is.tellg());
        const auto& mask = leaf->getValueMask();
        mask.seek(is);  // stored again before each buffer; the topology already holds it
        openvdb::io::readCompressedValues<typename TreeT::ValueType, typename LeafT::NodeMaskType>(
            is, nullptr, LeafT::SIZE, mask, deferred.from_half);
    }
    if (int64_t(is.tellg()) != grid_end) {
        throw std::runtime_error("the voxel data of grid '" + grid.getName() +
                                 "' does not end where the file says");
    }
}

/// Decodes the stored buffers of leaves [begin, end) into out[l].values, through a stream of its
/// own over the mapped file (so that threads decode at once) with the grid's stream state.
template <typename LeafT>
void decode_leaf_values(DeferredBuffers& deferred, const LeafT* const* nodes, size_t begin,
                        size_t end, LeafData* out) {
    using ValueT = typename LeafT::ValueType;
    MemoryBuffer buffer(*deferred.file);
    std::istream is(&buffer);
    {
        const std::lock_guard<std::mutex> lock(deferred.copying_state);
        is.copyfmt(*deferred.state);
    }
    [[maybe_unused]] std::array<ValueT, LeafT::SIZE> decoded;
    for (size_t l = begin; l != end; ++l) {
        is.seekg(deferred.offsets[l]);
        const auto& mask = nodes[l]->getValueMask();
        mask.seek(is);
        float* dest = out[l].values.data();
        if constexpr (std::is_same_v<ValueT, float>) {
            openvdb::io::readCompressedValues(is, dest, LeafT::SIZE, mask, deferred.from_half);
        } else {
            openvdb::io::readCompressedValues(is, decoded.data(), LeafT::SIZE, mask,
                                              deferred.from_half);
            std::transform(decoded.begin(), decoded.end(), dest,
                           [](ValueT v) { return static_cast<float>(v); });
        }
    }
}

/// A grid read by `VdbArchive::read_topology`, its buffers decoded on `threads` threads straight
/// into the bridge's arrays: OpenVDB's reader decodes them one after another, which was most of a
/// large grid's load, and then they were copied once more.
template <typename GridT>
FloatGridData copy_deferred(const GridT& grid, int64_t grid_end, DeferredBuffers& deferred,
                            uint32_t threads) {
    using LeafT = typename GridT::TreeType::LeafNodeType;
    find_leaf_buffers(grid, grid_end, deferred);
    return copy_grid(grid, threads, [&](const LeafT* const* nodes, size_t begin, size_t end,
                                        LeafData* out) {
        decode_leaf_values(deferred, nodes, begin, end, out);
    });
}

/// OpenVDB's own copy of the grid, values from its leaves' buffers.
template <typename GridT>
FloatGridData copy_read_grid(const GridT& grid, uint32_t threads) {
    return copy_grid(grid, threads, copy_leaf_values<typename GridT::TreeType::LeafNodeType>);
}

/// Index of the grid selected by `index` (>= 0) or else by `name`.
size_t select_grid(const VdbArchive& vdb, const std::string& path, const std::string& name,
                   int32_t index) {
    const size_t n = vdb.size();
    if (n == 0) fail(quoted(path) + " holds no grids");
    if (index >= 0) {
        if (size_t(index) >= n) {
            fail("grid index " + std::to_string(index) + " out of range: " + quoted(path) +
                 " has " + std::to_string(n) + (n == 1 ? " grid" : " grids"));
        }
        return size_t(index);
    }
    for (size_t i = 0; i < n; ++i)
        if (vdb.name(i) == name) return i;
    std::string names;
    for (size_t i = 0; i < n; ++i) names += (i ? ", " : "") + vdb.name(i);
    fail("no grid named '" + name + "' in " + quoted(path) + " (grids: " + names + ")");
}

}  // namespace

// Declared in cpp/internal.h: writing (cpp/vdb_write.cpp) needs OpenVDB initialised too.
void init_openvdb() {
    static std::once_flag once;
    std::call_once(once, [] { openvdb::initialize(); });
}

// ------------------------------------------------------------------------------------------------
// The bridge functions

rust::Vec<GridSummary> list_grids(rust::Str path_str) {
    const std::string path = to_std(path_str);
    auto vdb = open_vdb(path);
    rust::Vec<GridSummary> out;
    for (size_t i = 0; i < vdb->size(); ++i) {
        const openvdb::GridBase::Ptr grid = read_grid_checked(*vdb, i);
        out.push_back(with_context("cannot summarize grid '" + vdb->name(i) + "' in " + quoted(path),
                                   [&] { return summarize(*grid); }));
    }
    return out;
}

rust::Vec<rust::String> list_grid_names(rust::Str path_str) {
    auto vdb = open_vdb(to_std(path_str));
    rust::Vec<rust::String> out;
    for (size_t i = 0; i < vdb->size(); ++i) out.push_back(rust::String(vdb->name(i)));
    return out;
}

namespace {

/// Fails unless `grid` has a linear transform (the only kind volgrad renders).
void check_linear(const openvdb::GridBase& grid, const std::string& what) {
    if (!grid.constTransform().baseMap()->isLinear()) {
        fail(what + " has a non-linear (" + grid.constTransform().mapType() +
             ") transform, which volgrad cannot render");
    }
}

FloatGridData read_float_grid_with(rust::Str path_str, rust::Str name_str, int32_t index,
                                   bool level_set_to_fog_volume, uint32_t threads,
                                   bool decode_in_parallel) {
    const std::string path = to_std(path_str);
    const std::string name = to_std(name_str);
    auto vdb = open_vdb(path);
    const size_t i = select_grid(*vdb, path, name, index);
    if (decode_in_parallel && vdb->can_defer_buffers(i)) {
        DeferredBuffers deferred;
        const openvdb::GridBase::Ptr base = with_context(
            corrupt_context(path), [&] { return vdb->read_topology(i, deferred); });
        // sdfToFogVolume needs the values in the tree: such a grid is read the usual way below.
        if (!(level_set_to_fog_volume && base->getGridClass() == openvdb::GRID_LEVEL_SET)) {
            check_linear(*base, "grid '" + base->getName() + "' in " + quoted(path));
            return with_context(corrupt_context(path), [&] {
                const int64_t end = vdb->grid_end(i);
                if (auto g = openvdb::gridConstPtrCast<openvdb::FloatGrid>(base)) {
                    return copy_deferred(*g, end, deferred, threads);
                }
                return copy_deferred(*openvdb::gridConstPtrCast<openvdb::DoubleGrid>(base), end,
                                     deferred, threads);
            });
        }
    }
    const openvdb::GridBase::Ptr base = read_grid_checked(*vdb, i);
    const std::string what = "grid '" + base->getName() + "' in " + quoted(path);
    check_linear(*base, what);
    // sdfToFogVolume: the interior half of the narrow band becomes a 0 -> 1 ramp (0 at the
    // surface, 1 at the band's inner edge), the inside 1, the outside 0; background 0, class fog.
    if (level_set_to_fog_volume && base->getGridClass() == openvdb::GRID_LEVEL_SET) {
        with_context("cannot convert the level set " + what + " to a fog volume", [&] {
            if (auto g = openvdb::gridPtrCast<openvdb::FloatGrid>(base)) {
                openvdb::tools::sdfToFogVolume(*g);
            } else if (auto g = openvdb::gridPtrCast<openvdb::DoubleGrid>(base)) {
                openvdb::tools::sdfToFogVolume(*g);
            }
        });
    }
    return with_context("cannot copy " + what, [&] {
        if (auto g = openvdb::gridConstPtrCast<openvdb::FloatGrid>(base)) {
            return copy_read_grid(*g, threads);
        }
        if (auto g = openvdb::gridConstPtrCast<openvdb::DoubleGrid>(base)) {
            return copy_read_grid(*g, threads);
        }
        fail(what + " has value type " + base->valueType() + ", not float");
    });
}

}  // namespace

FloatGridData read_float_grid(rust::Str path, rust::Str name, int32_t index,
                              bool level_set_to_fog_volume, uint32_t threads) {
    return read_float_grid_with(path, name, index, level_set_to_fog_volume, threads, true);
}

FloatGridData read_float_grid_through_openvdb(rust::Str path, rust::Str name, int32_t index,
                                              bool level_set_to_fog_volume, uint32_t threads) {
    return read_float_grid_with(path, name, index, level_set_to_fog_volume, threads, false);
}

}  // namespace volgrad
