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
// The archive reader itself (hardened against corrupt files) is in cpp/vdb_archive.h.

#include "volgrad/cpp/bridge.h"
#include "volgrad/cpp/internal.h"
#include "volgrad/cpp/vdb_archive.h"
#include "volgrad/src/io/bridge.rs.h"

#include <openvdb/math/Maps.h>
#include <openvdb/math/Transform.h>
#include <openvdb/tools/LevelSetUtil.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <limits>

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

/// The float a stored value becomes: a float or double as itself, converted; a vector's component
/// `component`.
struct ToFloat {
    int component = 0;
    template <typename T>
    float operator()(const T& v) const {
        if constexpr (openvdb::VecTraits<T>::IsVec) {
            return static_cast<float>(v[component]);
        } else {
            return static_cast<float>(v);
        }
    }
};

/// Copies a grid into FloatGridData, each value through `to_float` (a float or double grid's
/// values, or one component of a vector grid's). The leaves' values come from
/// `fill_values(nodes, begin, end, out)`, which writes the values of leaf l to out[l].values for
/// the leaves [begin, end) of `nodes` (leaf-iteration order); it runs on `threads` threads.
template <typename GridT, typename FillValues>
FloatGridData copy_grid(const GridT& grid, uint32_t threads, ToFloat to_float,
                        FillValues&& fill_values) {
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
    d.background = to_float(tree.background());
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
        d.tile_values.push_back(to_float(*it));
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

/// Values from the leaves' own buffers, through `to_float`: a grid OpenVDB read completely.
template <typename LeafT>
void copy_leaf_values(const LeafT* const* nodes, size_t begin, size_t end, LeafData* out,
                      ToFloat to_float) {
    for (size_t l = begin; l != end; ++l) {
        const auto* buffer = nodes[l]->buffer().data();
        std::transform(buffer, buffer + LeafT::SIZE, out[l].values.begin(), to_float);
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
/// own over the grid's bytes (so that threads decode at once) with the grid's stream state.
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
    return copy_grid(grid, threads, ToFloat{},
                     [&](const LeafT* const* nodes, size_t begin, size_t end, LeafData* out) {
                         decode_leaf_values(deferred, nodes, begin, end, out);
                     });
}

/// OpenVDB's own copy of the grid, values from its leaves' buffers through `to_float`.
template <typename GridT>
FloatGridData copy_read_grid(const GridT& grid, uint32_t threads, ToFloat to_float = {}) {
    using LeafT = typename GridT::TreeType::LeafNodeType;
    return copy_grid(grid, threads, to_float,
                     [&](const LeafT* const* nodes, size_t begin, size_t end, LeafData* out) {
                         copy_leaf_values(nodes, begin, end, out, to_float);
                     });
}

/// A vector grid's three components, each as a float grid's data.
template <typename GridT>
rust::Vec<FloatGridData> copy_components(const GridT& grid, uint32_t threads) {
    rust::Vec<FloatGridData> out;
    for (int c = 0; c < 3; ++c) out.push_back(copy_read_grid(grid, threads, ToFloat{c}));
    return out;
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

/// The value type a grid type names: "Tree_vec3s_5_4_3" is a grid of vec3s.
std::string value_type_of(const std::string& grid_type) {
    std::string t = grid_type.rfind("Tree_", 0) == 0 ? grid_type.substr(5) : grid_type;
    // The node sizes (three "_N") follow the value type.
    for (int level = 0; level < 3; ++level) {
        const size_t cut = t.rfind('_');
        if (cut == std::string::npos || cut + 1 == t.size() ||
            t.find_first_not_of("0123456789", cut + 1) != std::string::npos) {
            return grid_type;
        }
        t.resize(cut);
    }
    return t;
}

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
    // Refused from the file's table of grids, before the grid is read: a points cache or a large
    // vector grid would otherwise be read whole only to be turned away.
    const std::string type = vdb->grid_type(i);
    if (type != openvdb::FloatGrid::gridType() && type != openvdb::DoubleGrid::gridType()) {
        fail("grid '" + vdb->name(i) + "' in " + quoted(path) + " has value type " +
             value_type_of(type) + ", not float");
    }
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

rust::Vec<FloatGridData> read_grid_components(rust::Str path_str, rust::Str name_str, int32_t index,
                                              uint32_t threads) {
    const std::string path = to_std(path_str);
    {
        auto vdb = open_vdb(path);
        const size_t i = select_grid(*vdb, path, to_std(name_str), index);
        const std::string type = vdb->grid_type(i);
        if (type == openvdb::Vec3SGrid::gridType() || type == openvdb::Vec3DGrid::gridType()) {
            const openvdb::GridBase::Ptr base = read_grid_checked(*vdb, i);
            const std::string what = "grid '" + base->getName() + "' in " + quoted(path);
            check_linear(*base, what);
            return with_context("cannot copy " + what, [&] {
                if (auto g = openvdb::gridConstPtrCast<openvdb::Vec3SGrid>(base)) {
                    return copy_components(*g, threads);
                }
                return copy_components(*openvdb::gridConstPtrCast<openvdb::Vec3DGrid>(base),
                                       threads);
            });
        }
    }
    // Anything else is read as one float grid (which refuses other value types).
    rust::Vec<FloatGridData> out;
    out.push_back(read_float_grid_with(path_str, name_str, index, false, threads, true));
    return out;
}

FloatGridData read_float_grid(rust::Str path, rust::Str name, int32_t index,
                              bool level_set_to_fog_volume, uint32_t threads) {
    return read_float_grid_with(path, name, index, level_set_to_fog_volume, threads, true);
}

FloatGridData read_float_grid_through_openvdb(rust::Str path, rust::Str name, int32_t index,
                                              bool level_set_to_fog_volume, uint32_t threads) {
    return read_float_grid_with(path, name, index, level_set_to_fog_volume, threads, false);
}

}  // namespace volgrad
