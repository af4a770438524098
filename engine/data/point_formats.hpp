// Point files of other sensors and tools, read into the engine's Scan (x, y, z, reflectance as
// stored, float32): KITTI .bin (16-byte records), PCD (ascii, binary, binary_compressed), PLY
// (ascii, binary little or big endian), NumPy .npy (float32/float64, N x 3, 4 or 5, C order) and
// nuScenes .pcd.bin (N x 5 float32: x y z intensity ring). The format comes from the file name or
// is named; it is never guessed from a size, and a file whose content does not fit its format is
// an Error naming the file and what does not fit. docs/formats.md says what is read from each.
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "core/point.hpp"

namespace pillarseg {

enum class PointFormat { FromExtension, Kitti, Pcd, Ply, Npy, Nuscenes };

// "kitti", "pcd", "ply", "npy", "nuscenes", or "auto" (FromExtension); else an Error naming
// `option` and the choices.
PointFormat parse_point_format(std::string_view name, std::string_view option = "--format");
const char* point_format_name(PointFormat format);

// The point-file suffixes, longest first: ".pcd.bin" (nuScenes), ".bin" (KITTI), ".pcd", ".ply",
// ".npy" (matched without regard to case).
std::span<const std::string_view> point_file_suffixes();
// The suffix of point_file_suffixes() that `path`'s file name ends with, or empty.
std::string_view point_file_suffix(const std::filesystem::path& path);
// The format of a file name's suffix; an Error naming the file when it has none of them.
PointFormat point_format_of(const std::filesystem::path& path);

// Reads a point file. Points with a non-finite coordinate or reflectance are dropped (counted in
// Scan::dropped_nonfinite, logged as a warning); with label_path, the label count must equal the
// file's point count, and the labels of dropped points are dropped with them.
Scan read_points(const std::filesystem::path& path, PointFormat format = PointFormat::FromExtension,
                 const std::optional<std::filesystem::path>& label_path = std::nullopt);

// The records of a file's bytes in `format` (not FromExtension), non-finite ones included, in
// file order; `name` names the file in errors.
std::vector<Point> decode_points(std::span<const char> bytes, PointFormat format, const std::string& name);

// Checks a file of fixed-size records before it is read, its size known: the record count against
// the 32-bit point indices, and the `bytes_in_memory` each record takes while it is read against
// the host's memory. A file that cannot be stat'ed passes: reading it says why.
void require_records(const std::filesystem::path& path, size_t record_bytes, uint64_t bytes_in_memory,
                     const char* records);

// liblzf's decompression (PCD binary_compressed): `compressed` must expand to exactly
// `expanded_size` bytes; an Error saying what is wrong otherwise.
std::vector<char> lzf_decompress(std::span<const char> compressed, size_t expanded_size, const std::string& name);

}  // namespace pillarseg
