// NRRD (Nearly Raw Raster Data) volumes: the interchange format for truth volumes and
// whole-channel extracts. Opens in 3D Slicer, ITK, teem and numpy (pynrrd).
//
// Layout in memory: x fastest, then y, then z; components (e.g. RGB) interleaved per voxel,
// i.e. index = ((z * ny + y) * nx + x) * components + c. Little-endian, raw encoding.
// Spacing and origin are in millimetres in the volume's own frame: axis x = image columns,
// y = image rows (downwards), z = slice index. NRRD "space directions" are written as
// diag(spacing_mm) with space "left-posterior-superior" only if the caller says so; by default
// the file uses "space dimension: 3" with no anatomical claim.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace vispack {

enum class NrrdType { kUint8, kInt8, kUint16, kInt16, kUint32, kInt32, kFloat32, kFloat64 };

// Size in bytes of one scalar of `type`.
std::size_t nrrd_type_size(NrrdType type);
// NRRD type name ("uint8", "int16", ...).
const char* nrrd_type_name(NrrdType type);

struct NrrdVolume {
  NrrdType type = NrrdType::kUint8;
  int components = 1;                         // 1 (scalar) .. 4 (RGBA)
  std::array<std::int64_t, 3> dims{0, 0, 0};  // voxels along x, y, z
  std::array<double, 3> spacing_mm{1, 1, 1};
  std::array<double, 3> origin_mm{0, 0, 0};
  std::vector<std::uint8_t> data;  // dims product * components * type size bytes

  std::size_t voxel_count() const { return std::size_t(dims[0]) * dims[1] * dims[2]; }
  std::size_t byte_size() const { return voxel_count() * components * nrrd_type_size(type); }
  // Typed access to the data (no checks: the caller knows the type).
  template <class T>
  T* as() {
    return reinterpret_cast<T*>(data.data());
  }
  template <class T>
  const T* as() const {
    return reinterpret_cast<const T*>(data.data());
  }
};

// Writes a single-file NRRD (attached header, raw little-endian data) atomically.
// With gzip = true the data is gzip-encoded ("encoding: gzip"). Throws IoError.
void write_nrrd(const std::string& path, const NrrdVolume& volume, bool gzip = false);

// Reads a single-file NRRD written by write_nrrd or by another tool (raw or gzip encoding,
// little or big endian, 3-D scalar or 4-D with the components axis first).
// Throws FormatError naming the file and the bad field; IoError if unreadable.
NrrdVolume read_nrrd(const std::string& path);

}  // namespace vispack
