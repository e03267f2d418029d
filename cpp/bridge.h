// Declarations of the C++ side of the cxx bridge declared in src/io/bridge.rs.
//
// This header is included by the cxx-generated glue, so it deliberately pulls in no OpenVDB or
// OpenImageIO header: the shared structs are only forward-declared here (cxx defines them in the
// generated "volgrad/src/io/bridge.rs.h", which the .cpp files that use them include).
//
// Defined in cpp/vdb_read.cpp (list_grids, list_grid_names, read_float_grid[_through_openvdb],
// read_grid_components), cpp/vdb_write.cpp (write_float_grids,
// write_grids_with_colours)
// and cpp/images.cpp (read_image_size, read_image, write_image).
#pragma once

#include "rust/cxx.h"

#include <cstdint>

namespace volgrad {

struct MetaEntry;
struct GridSummary;
struct FloatGridData;
struct ImageData;
struct ImageSize;

rust::Vec<GridSummary> list_grids(rust::Str path);

rust::Vec<rust::String> list_grid_names(rust::Str path);

FloatGridData read_float_grid(rust::Str path, rust::Str name, std::int32_t index,
                              bool level_set_to_fog, std::uint32_t threads);

FloatGridData read_float_grid_through_openvdb(rust::Str path, rust::Str name, std::int32_t index,
                                              bool level_set_to_fog, std::uint32_t threads);

rust::Vec<FloatGridData> read_grid_components(rust::Str path, rust::Str name, std::int32_t index,
                                              std::uint32_t threads);

void write_float_grids(rust::Str path, rust::Slice<const FloatGridData> grids, bool save_half);

void write_grids_with_colours(rust::Str path, rust::Slice<const FloatGridData> grids,
                              rust::Slice<const FloatGridData> colours, bool save_half);

ImageSize read_image_size(rust::Str path);

ImageData read_image(rust::Str path);

void write_image(rust::Str path, const ImageData &image, rust::Str pixel_type);

}  // namespace volgrad
