// The C++ side of the cxx bridge declared in src/bridge.rs: OpenVDB (10.x) and OpenImageIO (2.4)
// behind plain-data functions. Nothing OpenVDB- or OIIO-typed crosses the bridge.
//
// Conventions (see the doc comments in src/bridge.rs):
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
//    Known limit: a file whose compressed voxel payload is corrupted in place (not truncated) can
//    still crash inside OpenVDB 10 (io::bloscFromStream reads an uncompressed chunk into its buffer
//    before checking the chunk's length); nothing outside OpenVDB can check that cheaply.
//  * Writing goes through the same class to an std::ofstream we own, so a failed write (disk full)
//    is detected: io::File::write never checks the stream.

#include "volgrad/cpp/bridge.h"
#include "volgrad/src/io/bridge.rs.h"

#include <openvdb/Grid.h>
#include <openvdb/Metadata.h>
#include <openvdb/io/Archive.h>
#include <openvdb/io/GridDescriptor.h>
#include <openvdb/io/io.h>
#include <openvdb/math/Maps.h>
#include <openvdb/math/Transform.h>
#include <openvdb/openvdb.h>
#include <openvdb/tools/Prune.h>

#include <OpenImageIO/imageio.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <memory>
#include <mutex>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <system_error>
#include <tuple>
#include <vector>

namespace fs = std::filesystem;

namespace volgrad {
namespace {

// ------------------------------------------------------------------------------------------------
// Errors

/// An error whose message already names the file and the reason: passed through unchanged.
struct BridgeError : std::runtime_error {
    using std::runtime_error::runtime_error;
};

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

/// Runs `body`, turning any exception that does not already carry context into a BridgeError
/// prefixed by `context` (e.g. "'x.vdb' is not a valid VDB file (truncated or corrupt)").
template <typename F>
auto with_context(const std::string& context, F&& body) -> decltype(body()) {
    try {
        return body();
    } catch (const BridgeError&) {
        throw;
    } catch (const openvdb::Exception& e) {
        fail(context + ": " + e.what());
    } catch (const std::ios_base::failure&) {
        fail(context + ": unexpected end of file");
    } catch (const std::bad_alloc&) {
        fail(context + ": out of memory (a size field in the file is probably corrupt)");
    } catch (const std::exception& e) {
        fail(context + ": " + e.what());
    }
}

void init_openvdb() {
    static std::once_flag once;
    std::call_once(once, [] { openvdb::initialize(); });
}

std::string to_std(rust::Str s) { return std::string(s.data(), s.size()); }

/// Fails with a plain message unless `path` names a readable regular file.
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

// Parsing (for writing)

std::string trim(const std::string& s) {
    size_t b = 0, e = s.size();
    while (b < e && std::isspace(static_cast<unsigned char>(s[b]))) ++b;
    while (e > b && std::isspace(static_cast<unsigned char>(s[e - 1]))) --e;
    return s.substr(b, e - b);
}

template <typename T>
bool parse_num(const std::string& text, T& out) {
    const std::string s = trim(text);
    if constexpr (std::is_same_v<T, bool>) {
        if (s == "true" || s == "1") return out = true, true;
        if (s == "false" || s == "0") return out = false, true;
        return false;
    } else if constexpr (std::is_floating_point_v<T>) {
        if (s == "nan") return out = std::numeric_limits<T>::quiet_NaN(), true;
        if (s == "inf" || s == "+inf") return out = std::numeric_limits<T>::infinity(), true;
        if (s == "-inf") return out = -std::numeric_limits<T>::infinity(), true;
        const char* b = s.data();
        if (!s.empty() && s[0] == '+') ++b;
        const auto r = std::from_chars(b, s.data() + s.size(), out);
        return r.ec == std::errc() && r.ptr == s.data() + s.size() && !s.empty();
    } else {
        const char* b = s.data();
        if (!s.empty() && s[0] == '+') ++b;
        const auto r = std::from_chars(b, s.data() + s.size(), out);
        return r.ec == std::errc() && r.ptr == s.data() + s.size() && !s.empty();
    }
}

/// Parses "[x, y, z]" (brackets optional, comma or space separated).
template <typename T>
bool parse_vec3(const std::string& text, T out[3]) {
    std::string s = trim(text);
    if (!s.empty() && s.front() == '[') {
        if (s.back() != ']') return false;
        s = s.substr(1, s.size() - 2);
    }
    std::replace(s.begin(), s.end(), ',', ' ');
    std::istringstream in(s);
    std::string tok;
    int n = 0;
    while (in >> tok) {
        if (n == 3 || !parse_num(tok, out[n])) return false;
        ++n;
    }
    return n == 3;
}

const char* const kWritableMetaTypes =
    "string, float, double, int (int32), int64, bool, vec3i, vec3s, vec3d";

openvdb::Metadata::Ptr make_metadata(const MetaEntry& e) {
    using namespace openvdb;
    const std::string type = to_std(rust::Str(e.type_name));
    const std::string value(e.value);
    const std::string name(e.name);
    auto bad_value = [&]() -> Metadata::Ptr {
        fail("metadata '" + name + "': '" + value + "' is not a valid " + type + " value");
    };
    if (type == "string") return std::make_shared<StringMetadata>(value);
    if (type == "float") {
        float v;
        return parse_num(value, v) ? std::make_shared<FloatMetadata>(v) : bad_value();
    }
    if (type == "double") {
        double v;
        return parse_num(value, v) ? std::make_shared<DoubleMetadata>(v) : bad_value();
    }
    if (type == "int" || type == "int32") {
        int32_t v;
        return parse_num(value, v) ? std::make_shared<Int32Metadata>(v) : bad_value();
    }
    if (type == "int64") {
        int64_t v;
        return parse_num(value, v) ? std::make_shared<Int64Metadata>(v) : bad_value();
    }
    if (type == "bool") {
        bool v;
        return parse_num(value, v) ? std::make_shared<BoolMetadata>(v) : bad_value();
    }
    if (type == "vec3i") {
        int32_t v[3];
        return parse_vec3(value, v) ? std::make_shared<Vec3IMetadata>(Vec3i(v[0], v[1], v[2]))
                                    : bad_value();
    }
    if (type == "vec3s") {
        float v[3];
        return parse_vec3(value, v) ? std::make_shared<Vec3SMetadata>(Vec3s(v[0], v[1], v[2]))
                                    : bad_value();
    }
    if (type == "vec3d") {
        double v[3];
        return parse_vec3(value, v) ? std::make_shared<Vec3DMetadata>(Vec3d(v[0], v[1], v[2]))
                                    : bad_value();
    }
    fail("metadata '" + name + "' has type '" + type + "', which cannot be written (supported: " +
         kWritableMetaTypes + ")");
}

/// Metadata that OpenVDB manages itself or that comes from FloatGridData's own fields.
bool skip_on_write(const std::string& name) {
    return name.rfind("file_", 0) == 0 || name == openvdb::GridBase::META_SAVE_HALF_FLOAT ||
           name == openvdb::GridBase::META_GRID_NAME || name == openvdb::GridBase::META_GRID_CLASS;
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
// Reading and writing VDB files

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
        gd.seekToGrid(is_);
        if (fileVersion() >= openvdb::OPENVDB_FILE_VERSION_NODE_MASK_COMPRESSION) pod<uint32_t>();
        check_meta_map(gd.getEndPos(), "the metadata of grid '" + gd.gridName() + "'");
        gd.seekToGrid(is_);
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

    /// Writes `grids` to `os` (seekable), with the file-level metadata `meta`.
    void write_to(std::ostream& os, const openvdb::GridCPtrVec& grids,
                  const openvdb::MetaMap& meta) const {
        Archive::write(os, grids, /*seekable=*/true, meta);
    }

    VdbArchive() = default;

private:
    [[noreturn]] void corrupt(const std::string& why) const { throw std::runtime_error(why); }

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

/// Copies a float (or double, converted) grid into FloatGridData.
template <typename GridT>
FloatGridData copy_grid(const GridT& grid) {
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

    const size_t leaves = tree.leafCount();
    d.leaf_origins.reserve(3 * leaves);
    d.leaf_values.reserve(512 * leaves);
    d.leaf_active.reserve(8 * leaves);
    for (auto leaf = tree.cbeginLeaf(); leaf; ++leaf) {
        const openvdb::Coord o = leaf->origin();
        for (int i = 0; i < 3; ++i) d.leaf_origins.push_back(o[i]);
        for (openvdb::Index i = 0; i < LeafT::SIZE; ++i) {
            d.leaf_values.push_back(static_cast<float>(leaf->getValue(i)));
        }
        const auto& mask = leaf->getValueMask();
        for (openvdb::Index w = 0; w < LeafT::NodeMaskType::WORD_COUNT; ++w) {
            d.leaf_active.push_back(mask.template getWord<openvdb::Index64>(w));
        }
    }

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
    d.metadata = meta_entries(grid);
    return d;
}

/// Index of the grid selected by `index` (>= 0) or else by `name`.
size_t select_grid(const VdbArchive& vdb, const std::string& path, const std::string& name,
                   int32_t index) {
    const size_t n = vdb.size();
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
    fail("no grid named '" + name + "' in " + quoted(path) +
         (n ? " (grids: " + names + ")" : " (the file has no grids)"));
}

/// Validates one FloatGridData and builds the OpenVDB grid.
openvdb::FloatGrid::Ptr build_grid(const FloatGridData& d) {
    using namespace openvdb;
    const std::string name(d.name);

    // Transform: ours is column-vector row-major; OpenVDB's Mat4d is its transpose.
    const auto& c = d.index_to_world;
    for (double v : c)
        if (!std::isfinite(v)) fail("index_to_world has a non-finite entry");
    if (c[12] != 0.0 || c[13] != 0.0 || c[14] != 0.0 || c[15] != 1.0) {
        fail("index_to_world is not affine (its last row must be [0, 0, 0, 1])");
    }
    Mat4d m;
    for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) m(j, i) = c[4 * i + j];
    const double det = m.getMat3().det();
    if (!(std::abs(det) > 0.0)) fail("index_to_world is singular (determinant 0)");

    const std::string cls(d.grid_class);
    GridClass gc = GRID_UNKNOWN;
    if (!cls.empty()) {
        gc = GridBase::stringToGridClass(cls);
        if (gc == GRID_UNKNOWN && cls != GridBase::gridClassToString(GRID_UNKNOWN)) {
            fail("unknown grid class '" + cls +
                 "' (expected 'fog volume', 'level set', 'staggered' or 'unknown')");
        }
    }

    // Shapes.
    const size_t nleaf = d.leaf_origins.size() / 3;
    if (d.leaf_origins.size() % 3 != 0) fail("leaf_origins length is not a multiple of 3");
    if (d.leaf_values.size() != 512 * nleaf) {
        fail("leaf_values has " + std::to_string(d.leaf_values.size()) + " values, expected 512 x " +
             std::to_string(nleaf) + " leaves");
    }
    if (d.leaf_active.size() != 8 * nleaf) {
        fail("leaf_active has " + std::to_string(d.leaf_active.size()) + " words, expected 8 x " +
             std::to_string(nleaf) + " leaves");
    }
    const size_t ntile = d.tile_values.size();
    if (d.tile_origins.size() != 3 * ntile || d.tile_sizes.size() != ntile) {
        fail("tile_origins / tile_sizes / tile_values lengths disagree (" +
             std::to_string(d.tile_origins.size()) + " / " + std::to_string(d.tile_sizes.size()) +
             " / " + std::to_string(ntile) + ")");
    }

    // Every region (leaf or tile) is aligned to its size; two regions of sizes s <= S overlap
    // exactly when the smaller one's origin rounded down to S is the larger one's origin.
    auto coord_text = [](const int32_t* p) {
        return "(" + std::to_string(p[0]) + ", " + std::to_string(p[1]) + ", " +
               std::to_string(p[2]) + ")";
    };
    auto align = [](int32_t v, int32_t s) { return int32_t(int64_t(v) & ~int64_t(s - 1)); };
    std::set<std::tuple<int32_t, int32_t, int32_t, int32_t>> regions;  // (size, x, y, z)
    auto add_region = [&](const int32_t* o, uint32_t size, const char* what) {
        for (int i = 0; i < 3; ++i) {
            if (align(o[i], int32_t(size)) != o[i]) {
                fail(std::string(what) + " origin " + coord_text(o) + " is not a multiple of " +
                     std::to_string(size));
            }
        }
        if (!regions.emplace(int32_t(size), o[0], o[1], o[2]).second) {
            fail(std::string("two ") + what + "s at " + coord_text(o));
        }
    };
    static const uint32_t kSizes[] = {8, 128, 4096};
    for (size_t t = 0; t < ntile; ++t) {
        const uint32_t s = d.tile_sizes[t];
        if (s != 8 && s != 128 && s != 4096) {
            fail("tile at " + coord_text(&d.tile_origins[3 * t]) + " has edge length " +
                 std::to_string(s) + " (must be 8, 128 or 4096)");
        }
        add_region(&d.tile_origins[3 * t], s, "tile");
    }
    for (size_t l = 0; l < nleaf; ++l) {
        const int32_t* o = &d.leaf_origins[3 * l];
        if (regions.count({8, o[0], o[1], o[2]})) {
            fail("leaf at " + coord_text(o) + " coincides with an 8-voxel tile");
        }
        add_region(o, 8, "leaf");
    }
    for (const auto& [size, x, y, z] : regions) {
        for (uint32_t big : kSizes) {
            if (big <= uint32_t(size)) continue;
            const int32_t b = int32_t(big);
            if (regions.count({b, align(x, b), align(y, b), align(z, b)})) {
                const int32_t o[3] = {x, y, z};
                fail("the region at " + coord_text(o) + " (edge " + std::to_string(size) +
                     ") lies inside the tile of edge " + std::to_string(big) + " at " +
                     coord_text(std::array<int32_t, 3>{align(x, b), align(y, b), align(z, b)}
                                    .data()));
            }
        }
    }

    // Build.
    FloatGrid::Ptr grid = FloatGrid::create(d.background);
    grid->setTransform(math::Transform::createLinearTransform(m));
    grid->setName(name);
    grid->setGridClass(gc);
    FloatTree& tree = grid->tree();
    for (size_t t = 0; t < ntile; ++t) {
        const uint32_t s = d.tile_sizes[t];
        const Index level = s == 8 ? 1 : s == 128 ? 2 : 3;
        const int32_t* o = &d.tile_origins[3 * t];
        tree.addTile(level, Coord(o[0], o[1], o[2]), d.tile_values[t], /*active=*/true);
    }
    for (size_t l = 0; l < nleaf; ++l) {
        const int32_t* o = &d.leaf_origins[3 * l];
        FloatTree::LeafNodeType* leaf = tree.touchLeaf(Coord(o[0], o[1], o[2]));
        const float* values = &d.leaf_values[512 * l];
        for (Index i = 0; i < 512; ++i) leaf->setValueOnly(i, values[i]);
        auto& mask = leaf->getValueMask();
        for (Index w = 0; w < 8; ++w) mask.getWord<Index64>(w) = d.leaf_active[8 * l + w];
    }

    for (const MetaEntry& e : d.metadata) {
        const std::string key(e.name);
        if (skip_on_write(key)) continue;
        grid->insertMeta(key, *make_metadata(e));
    }
    tools::prune(tree, 0.0f);
    return grid;
}

// ------------------------------------------------------------------------------------------------
// Images

OIIO::TypeDesc pixel_type_desc(const std::string& t) {
    if (t == "half") return OIIO::TypeDesc::HALF;
    if (t == "float") return OIIO::TypeDesc::FLOAT;
    if (t == "uint8") return OIIO::TypeDesc::UINT8;
    fail("unknown pixel type '" + t + "' (expected half, float or uint8)");
}

std::string oiio_error(const std::string& specific) {
    std::string e = specific.empty() ? OIIO::geterror() : specific;
    while (!e.empty() && (e.back() == '\n' || e.back() == ' ')) e.pop_back();
    return e.empty() ? "unknown OpenImageIO error" : e;
}

/// Renames `tmp` over `path`, removing `tmp` on failure.
void commit_file(const fs::path& tmp, const std::string& path) {
    std::error_code ec;
    fs::rename(tmp, path, ec);
    if (ec) {
        std::error_code ignored;
        fs::remove(tmp, ignored);
        fail("cannot write " + quoted(path) + ": cannot replace it: " + ec.message());
    }
}

/// Fails unless the directory that will hold `path` exists and `path` is not a directory.
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

}  // namespace

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

FloatGridData read_float_grid(rust::Str path_str, rust::Str name_str, int32_t index) {
    const std::string path = to_std(path_str);
    const std::string name = to_std(name_str);
    auto vdb = open_vdb(path);
    const size_t i = select_grid(*vdb, path, name, index);
    const openvdb::GridBase::Ptr base = read_grid_checked(*vdb, i);
    const std::string what = "grid '" + base->getName() + "' in " + quoted(path);
    if (!base->constTransform().baseMap()->isLinear()) {
        fail(what + " has a non-linear (" + base->constTransform().mapType() +
             ") transform, which volgrad cannot render");
    }
    return with_context("cannot copy " + what, [&] {
        if (auto g = openvdb::gridConstPtrCast<openvdb::FloatGrid>(base)) return copy_grid(*g);
        if (auto g = openvdb::gridConstPtrCast<openvdb::DoubleGrid>(base)) return copy_grid(*g);
        fail(what + " has value type " + base->valueType() + ", not float");
    });
}

void write_float_grids(rust::Str path_str, rust::Slice<const FloatGridData> grids, bool save_half) {
    const std::string path = to_std(path_str);
    init_openvdb();
    check_writable_target(path);

    openvdb::GridCPtrVec vdb_grids;
    size_t i = 0;
    for (const FloatGridData& d : grids) {
        const std::string ctx = "cannot write " + quoted(path) + ": grid " + std::to_string(i) +
                                " ('" + std::string(d.name) + "')";
        openvdb::FloatGrid::Ptr g;
        try {
            g = build_grid(d);
        } catch (const std::exception& e) {  // BridgeError or an OpenVDB exception
            fail(ctx + ": " + e.what());
        }
        with_context(ctx, [&] { g->setSaveFloatAsHalf(save_half); });
        vdb_grids.push_back(g);
        ++i;
    }

    const fs::path tmp = path + ".tmp";
    {
        std::ofstream os(tmp, std::ios::out | std::ios::binary | std::ios::trunc);
        if (!os) {
            fail("cannot write " + quoted(path) + ": cannot create " + quoted(tmp.string()) + ": " +
                 errno_text(errno));
        }
        openvdb::MetaMap file_meta;
        file_meta.insertMeta("creator", openvdb::StringMetadata("volgrad"));
        try {
            with_context("cannot write " + quoted(path), [&] {
                VdbArchive().write_to(os, vdb_grids, file_meta);
                os.flush();
                if (!os) fail("cannot write " + quoted(path) + ": " + errno_text(errno));
                os.close();
                if (os.fail()) fail("cannot write " + quoted(path) + ": " + errno_text(errno));
            });
        } catch (...) {
            os.close();
            std::error_code ignored;
            fs::remove(tmp, ignored);
            throw;
        }
    }
    commit_file(tmp, path);
}

ImageData read_image(rust::Str path_str) {
    const std::string path = to_std(path_str);
    check_readable(path);
    // Return what the file stores: no (un)premultiplication of alpha.
    OIIO::ImageSpec config;
    config.attribute("oiio:UnassociatedAlpha", 1);
    auto in = OIIO::ImageInput::open(path, &config);
    if (!in) fail("cannot read image " + quoted(path) + ": " + oiio_error(""));
    const OIIO::ImageSpec& spec = in->spec();
    if (spec.width <= 0 || spec.height <= 0 || spec.nchannels <= 0 || spec.depth > 1) {
        fail("cannot read image " + quoted(path) + ": unsupported size " +
             std::to_string(spec.width) + "x" + std::to_string(spec.height) + "x" +
             std::to_string(spec.depth) + " with " + std::to_string(spec.nchannels) + " channels");
    }
    ImageData img;
    img.width = uint32_t(spec.width);
    img.height = uint32_t(spec.height);
    img.channels = uint32_t(spec.nchannels);
    std::vector<float> data(size_t(spec.width) * size_t(spec.height) * size_t(spec.nchannels));
    if (!in->read_image(0, 0, 0, spec.nchannels, OIIO::TypeDesc::FLOAT, data.data())) {
        fail("cannot read image " + quoted(path) + ": " + oiio_error(in->geterror()));
    }
    in->close();
    img.pixels.reserve(data.size());
    for (float v : data) img.pixels.push_back(v);
    return img;
}

void write_image(rust::Str path_str, const ImageData& image, rust::Str pixel_type) {
    const std::string path = to_std(path_str);
    const std::string what = "cannot write image " + quoted(path);
    const OIIO::TypeDesc type = [&] {
        try {
            return pixel_type_desc(to_std(pixel_type));
        } catch (const BridgeError& e) {
            fail(what + ": " + e.what());
        }
    }();
    if (image.width == 0 || image.height == 0 || image.channels == 0) {
        fail(what + ": empty image (" + std::to_string(image.width) + "x" +
             std::to_string(image.height) + " with " + std::to_string(image.channels) +
             " channels)");
    }
    const size_t expected = size_t(image.width) * image.height * image.channels;
    if (image.pixels.size() != expected) {
        fail(what + ": " + std::to_string(image.pixels.size()) + " values for " +
             std::to_string(image.width) + "x" + std::to_string(image.height) + "x" +
             std::to_string(image.channels) + " (expected " + std::to_string(expected) + ")");
    }
    check_writable_target(path);
    const fs::path p(path);
    const std::string ext = p.extension().string();
    if (ext.empty()) fail(what + ": no file extension to choose the image format from");

    auto out = OIIO::ImageOutput::create(path);
    if (!out) fail(what + ": unknown image format '" + ext + "' (" + oiio_error("") + ")");
    OIIO::ImageSpec spec(int(image.width), int(image.height), int(image.channels), type);
    // The values are stored as given: no (un)premultiplication of alpha.
    spec.attribute("oiio:UnassociatedAlpha", 1);
    if (std::string(out->format_name()) == "openexr") spec.attribute("compression", "zip");

    // OIIO picks the format from the extension, so the temporary name keeps it.
    const fs::path tmp = p.parent_path() / ("." + p.stem().string() + ".tmp" + ext);
    auto cleanup = [&] {
        std::error_code ignored;
        fs::remove(tmp, ignored);
    };
    if (!out->open(tmp.string(), spec)) {
        const std::string err = oiio_error(out->geterror());
        cleanup();
        fail(what + ": " + err);
    }
    const OIIO::TypeDesc stored = out->spec().format;  // what the format actually stores
    if (!out->write_image(OIIO::TypeDesc::FLOAT, image.pixels.data())) {
        const std::string err = oiio_error(out->geterror());
        out->close();
        cleanup();
        fail(what + ": " + err);
    }
    if (!out->close()) {
        const std::string err = oiio_error(out->geterror());
        cleanup();
        fail(what + ": " + err);
    }
    // Formats that cannot store the requested type silently fall back to another (PNG: uint8 for
    // "float"); that would lose precision the caller asked for, so it is an error. (Checked after
    // closing: closing an unwritten PNG makes libpng print to stderr.)
    if (stored != type) {
        cleanup();
        fail(what + ": the " + out->format_name() + " format cannot store " +
             to_std(pixel_type) + " pixels (it would store " + stored.c_str() + ")");
    }
    commit_file(tmp, path);
}

}  // namespace volgrad
