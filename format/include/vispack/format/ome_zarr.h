// Export of a packed volume as OME-Zarr (OME-NGFF 0.4 on Zarr v2, or 0.5 on Zarr v3 with the
// sharding codec), for napari, neuroglancer, Fiji/BigDataViewer/MoBIE and web viewers. Reads the
// file through Reader alone (no image library). docs/OME_ZARR.md describes the layout written.
//
// Data model (one multiscale image per exported picture, each level of the .vpk one dataset):
//   OUT/                 root group; attributes "vispack" list the images and the source file
//   OUT/rgb              colour of an rgba8 channel called "rgba" (else "<name>_rgb"):
//                        uint8, axes (c, z, y, x), c = 3 (r, g, b), chunks (3, E, E, E)
//   OUT/alpha            its alpha (body coverage, 0 = gel, 255 = tissue) ("<name>_alpha"):
//                        uint8 (z, y, x)
//   OUT/ct               an int16 channel (CT in HU): int16 (z, y, x), omero window W400/L40
//   OUT/rgb/labels/NAME  a label channel as an NGFF image-label (uint8 or uint16 (z, y, x)) with
//                        the label table's colours and names; under the first image written
//                        ("rgb", else "ct"...), or at OUT/NAME when only labels are exported
// Every dataset L is the .vpk level L (paths "0", "1", ...: the level number), with a scale
// transform spacing_mm(L) and a translation origin_mm(L) in millimetres (z, y, x order), so the
// centre of voxel i of each level lands where the packed file puts it (the mean pyramid's
// half-voxel shift included). One chunk (0.4) or one inner chunk of a shard (0.5) per brick of
// the packed file, zstd compressed; a brick equal to the array's fill value everywhere is not
// written (readers return the fill value). A brick already stored as a zstd frame of exactly
// the chunk's bytes (scalar channels) is copied without decoding.
//
// Streaming: bricks are encoded in batches of a few per thread and written in order, so memory
// is bounded by a few bricks per thread whatever the volume's size. Atomic: everything is written
// under "OUT.partial-XXXXXX" beside OUT, synced (syncfs) and renamed onto OUT at the end; an
// error or an interruption leaves no OUT (the partial folder is removed on an error; one left by
// a killed process can be deleted).
//
// Thread-safety: export_ome_zarr uses its own threads; the Reader is only read.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "vispack/format/reader.h"

namespace vispack::format {

enum class NgffVersion {
  k04,  // OME-NGFF 0.4, Zarr v2 (.zgroup/.zattrs/.zarray, one file per chunk)
  k05,  // OME-NGFF 0.5, Zarr v3 (zarr.json, sharding_indexed: one file per shard)
};

// "0.4" / "0.5" <-> NgffVersion; the parser throws UsageError naming the bad value.
NgffVersion parse_ngff_version(const std::string& text);
const char* ngff_version_name(NgffVersion version);

struct OmeZarrOptions {
  NgffVersion version = NgffVersion::k04;
  std::vector<std::string> channels;  // packed-file channel names to export; empty = all
  std::vector<int> levels;            // levels to export (ascending, unique); empty = all
  int zstd_level = 3;                 // for the chunks that are encoded (not copied)
  int shard_bricks = 8;               // 0.5: bricks per shard edge (a shard holds up to S^3)
  int threads = 0;                    // 0 = resolve_threads()
  bool copy_stored_bricks = true;     // false: decode and re-encode every chunk (for measuring)
  bool overwrite = false;             // replace an existing OUT (only once the new one is done)
  bool quiet = false;                 // no progress output
};

// What an export did (counts over every array and level written).
struct OmeZarrStats {
  std::uint64_t bricks = 0;          // packed bricks read
  std::uint64_t chunks_copied = 0;   // chunks whose bytes are the brick's stored zstd frame
  std::uint64_t chunks_encoded = 0;  // chunks decoded (if needed) and compressed here
  std::uint64_t chunks_skipped = 0;  // chunks equal to the fill value, not written
  std::uint64_t files = 0;           // files written (chunks or shards, plus metadata)
  std::uint64_t shards = 0;          // 0.5: shard files written
  std::uint64_t bytes = 0;           // bytes written
  double seconds = 0;
};

// Writes `reader`'s volume as OME-Zarr at `out_path`. Throws UsageError (unknown channel or
// level, OUT exists without overwrite, bad option), IoError (naming the file) or FormatError
// (a brick that does not decode, naming it); OUT is then left as it was.
OmeZarrStats export_ome_zarr(const Reader& reader, const std::string& out_path,
                             const OmeZarrOptions& options);

}  // namespace vispack::format
