// Writing VDB files for the cxx bridge declared in src/io/bridge.rs: write_float_grids validates
// each FloatGridData, builds the OpenVDB (10.x) grid and writes them all to a temporary file that
// replaces the target only once complete; write_grids_with_colours also writes vec3 grids (colours),
// each made of three float components. Nothing OpenVDB-typed crosses the bridge.
//
// Conventions (see the doc comments in src/io/bridge.rs and cpp/vdb_read.cpp): index_to_world is
// column-vector convention, row-major, the TRANSPOSE of OpenVDB's Mat4d; every error is a C++
// exception whose what() names the file and the reason.
//
// Writing goes through a small io::Archive subclass to an std::ofstream we own, so a failed write
// (disk full) is detected: io::File::write never checks the stream.

#include "volgrad/cpp/bridge.h"
#include "volgrad/cpp/internal.h"
#include "volgrad/src/io/bridge.rs.h"

#include <openvdb/Grid.h>
#include <openvdb/Metadata.h>
#include <openvdb/io/Archive.h>
#include <openvdb/math/Transform.h>
#include <openvdb/openvdb.h>
#include <openvdb/tools/Prune.h>
#include <openvdb/tools/SignedFloodFill.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <limits>
#include <set>
#include <sstream>
#include <string>
#include <system_error>
#include <tuple>

namespace fs = std::filesystem;

namespace volgrad {
namespace {

// ------------------------------------------------------------------------------------------------
// Metadata values parsed from their text form (the inverse of meta_text in cpp/vdb_read.cpp)

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
// Writing VDB files

/// Minimal io::Archive client for writing to a stream we own (Archive::write is protected).
class VdbWriter : public openvdb::io::Archive {
public:
    /// Writes `grids` to `os` (seekable), with the file-level metadata `meta`.
    void write_to(std::ostream& os, const openvdb::GridCPtrVec& grids,
                  const openvdb::MetaMap& meta) const {
        Archive::write(os, grids, /*seekable=*/true, meta);
    }
};

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

    // A level set's background is the half-width of its narrow band: the distance reported
    // everywhere outside the band, positive outside and (after the flood fill below) negative inside.
    if (!std::isfinite(d.background)) fail("the background value is not finite");
    if (gc == GRID_LEVEL_SET && !(d.background > 0.0f)) {
        fail("a level set's background is its narrow-band half-width and must be > 0 (got " +
             std::to_string(d.background) + ")");
    }

    // Shapes.
    const size_t nleaf = d.leaves.size();
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
        const int32_t* o = d.leaves[l].origin.data();
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
        const LeafData& data = d.leaves[l];
        const int32_t* o = data.origin.data();
        FloatTree::LeafNodeType* leaf = tree.touchLeaf(Coord(o[0], o[1], o[2]));
        for (Index i = 0; i < 512; ++i) leaf->setValueOnly(i, data.values[i]);
        auto& mask = leaf->getValueMask();
        for (Index w = 0; w < 8; ++w) mask.getWord<Index64>(w) = data.active[w];
    }

    for (const MetaEntry& e : d.metadata) {
        const std::string key(e.name);
        if (skip_on_write(key)) continue;
        grid->insertMeta(key, *make_metadata(e));
    }
    if (gc == GRID_LEVEL_SET) {
        // The plain data holds leaves and active tiles only: the inside of the surface away from
        // the band is empty, so give it (and inactive voxels) the sign of the distances around it.
        tools::signedFloodFill(tree);
        tools::pruneLevelSet(tree);
    } else {
        tools::prune(tree, 0.0f);
    }
    return grid;
}

}  // namespace

// ------------------------------------------------------------------------------------------------
// The bridge functions

namespace {

/// Writes `grids` to a temporary file beside `path` that then replaces it.
void write_archive(const std::string& path, const openvdb::GridCPtrVec& grids) {
    const fs::path tmp = temporary_beside(path, "");
    std::ofstream os(tmp, std::ios::out | std::ios::binary | std::ios::trunc);
    if (!os) {
        fail("cannot write " + quoted(path) + ": cannot create " + quoted(tmp.string()) + ": " +
             errno_text(errno));
    }
    openvdb::MetaMap file_meta;
    file_meta.insertMeta("creator", openvdb::StringMetadata("volgrad"));
    try {
        with_context("cannot write " + quoted(path), [&] {
            VdbWriter().write_to(os, grids, file_meta);
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
    commit_file(tmp, path);
}

/// `build_grid` with errors that name the file and the grid.
openvdb::FloatGrid::Ptr build_grid_for(const std::string& path, const FloatGridData& d, size_t i) {
    try {
        return build_grid(d);
    } catch (const std::exception& e) {  // BridgeError or an OpenVDB exception
        fail("cannot write " + quoted(path) + ": grid " + std::to_string(i) + " ('" +
             std::string(d.name) + "'): " + e.what());
    }
}

/// One vec3s grid from three float components: every voxel active in any component is active
/// (one voxel at a time: a tile of one component may hold leaves of another), with the name,
/// transform and metadata of the first.
openvdb::Vec3SGrid::Ptr build_vec3_grid(const std::string& path, const FloatGridData* components,
                                        size_t first_index) {
    using namespace openvdb;
    std::array<FloatGrid::Ptr, 3> parts;
    for (size_t c = 0; c < 3; ++c) parts[c] = build_grid_for(path, components[c], first_index + c);
    const FloatGridData& first = components[0];
    Vec3SGrid::Ptr grid = Vec3SGrid::create(
        Vec3s(first.background, components[1].background, components[2].background));
    grid->setTransform(parts[0]->transform().copy());
    grid->setName(std::string(first.name));
    with_context("cannot write " + quoted(path), [&] {
        for (const auto& part : parts) grid->tree().topologyUnion(part->tree());
        // Written voxel by voxel: a large active tile would be billions of them.
        const Index64 tile_voxels = grid->tree().activeTileCount() == 0
                                        ? 0
                                        : grid->activeVoxelCount() - grid->tree().activeLeafVoxelCount();
        if (tile_voxels > (Index64(1) << 24)) {
            fail("a colour grid's components hold " + std::to_string(tile_voxels) +
                 " voxels in active tiles; at most 2^24 are written voxel by voxel");
        }
        grid->tree().voxelizeActiveTiles();
        std::array<FloatGrid::ConstAccessor, 3> values{parts[0]->getConstAccessor(),
                                                       parts[1]->getConstAccessor(),
                                                       parts[2]->getConstAccessor()};
        for (auto v = grid->beginValueOn(); v; ++v) {
            const Coord xyz = v.getCoord();
            v.setValue(Vec3s(values[0].getValue(xyz), values[1].getValue(xyz),
                             values[2].getValue(xyz)));
        }
        for (const MetaEntry& e : first.metadata) {
            const std::string key(e.name);
            if (!skip_on_write(key)) grid->insertMeta(key, *make_metadata(e));
        }
    });
    return grid;
}

}  // namespace

void write_grids_with_colours(rust::Str path_str, rust::Slice<const FloatGridData> grids,
                              rust::Slice<const FloatGridData> colours, bool save_half) {
    const std::string path = to_std(path_str);
    init_openvdb();
    check_writable_target(path);
    if (colours.size() % 3 != 0) {
        fail("cannot write " + quoted(path) + ": colour grids come as 3 components each, not " +
             std::to_string(colours.size()));
    }
    openvdb::GridCPtrVec vdb_grids;
    for (const FloatGridData& d : grids) {
        openvdb::FloatGrid::Ptr g = build_grid_for(path, d, vdb_grids.size());
        g->setSaveFloatAsHalf(save_half);
        vdb_grids.push_back(g);
    }
    for (size_t c = 0; c < colours.size(); c += 3) {
        auto g = build_vec3_grid(path, colours.data() + c, grids.size() + c);
        g->setSaveFloatAsHalf(save_half);
        vdb_grids.push_back(g);
    }
    write_archive(path, vdb_grids);
}

void write_float_grids(rust::Str path, rust::Slice<const FloatGridData> grids, bool save_half) {
    write_grids_with_colours(path, grids, {}, save_half);
}

}  // namespace volgrad
