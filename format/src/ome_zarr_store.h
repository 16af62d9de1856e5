// Where an OME-Zarr export (ome_zarr.h) writes: the output folder, created as a partial folder
// beside the destination and published atomically, and the two ways chunks land in it (Zarr v2:
// one file per chunk; Zarr v3 with sharding_indexed: one file per shard, chunks appended as they
// come, the shard index with its crc32c at the end). Internal to vispack_format_export.
// Not thread-safe: one thread writes (the encoders run on others).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <set>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace vispack::format::ome_zarr {

// CRC-32C (Castagnoli, reflected polynomial 0x82F63B78), as Zarr v3's crc32c codec computes it.
std::uint32_t crc32c(const void* data, std::size_t size, std::uint32_t crc = 0);

// The destination folder, written under "<final>.partial-XXXXXX" until commit().
class OutputFolder {
 public:
  // Refuses (UsageError) an existing `final_path` unless `overwrite`; creates the partial
  // folder (IoError naming it when it cannot).
  OutputFolder(std::string final_path, bool overwrite);
  // Removes the partial folder when commit() was not reached.
  ~OutputFolder();
  OutputFolder(const OutputFolder&) = delete;
  OutputFolder& operator=(const OutputFolder&) = delete;

  // Writes a whole file at `relative` (parents created). Throws IoError naming the final path.
  void write_file(const std::string& relative, const void* data, std::size_t size);
  void write_json(const std::string& relative, const nlohmann::json& doc);
  // Creates the folder `relative` and its parents (remembered, so each is made once).
  void make_folder(const std::string& relative);
  // Syncs the file system holding the partial folder (syncfs), renames it onto the final path
  // (an existing one, with overwrite, is moved aside first and removed after), syncs the parent.
  void commit();

  // The partial folder while writing; the final path after commit().
  const std::string& root() const { return root_; }
  const std::string& final_path() const { return final_; }
  std::uint64_t files() const { return files_; }
  std::uint64_t bytes() const { return bytes_; }
  // Counts a file written by a writer of its own (ShardWriter).
  void count(std::uint64_t files, std::uint64_t bytes) { files_ += files, bytes_ += bytes; }

 private:
  std::string final_, root_;
  bool overwrite_ = false, committed_ = false;
  std::set<std::string> folders_;
  std::uint64_t files_ = 0, bytes_ = 0;
};

// One array's chunks. put() receives the bricks of one level in the order chunk_order() gives.
class ChunkWriter {
 public:
  virtual ~ChunkWriter() = default;
  // The chunk of brick (bx, by, bz); size 0 = not written (fill value).
  virtual void put(const std::array<std::int64_t, 3>& brick, const void* data,
                   std::size_t size) = 0;
  // Ends the array (writes the last shard).
  virtual void finish() = 0;
};

// Zarr v2, dimension_separator "/": the chunk of brick (bx, by, bz) is "<array>/[0/]bz/by/bx"
// (the leading 0 when the array has a channel axis, chunked whole).
class V2ChunkWriter : public ChunkWriter {
 public:
  V2ChunkWriter(OutputFolder& folder, std::string array, bool channel_axis);
  void put(const std::array<std::int64_t, 3>& brick, const void* data, std::size_t size) override;
  void finish() override {}

 private:
  OutputFolder& folder_;
  std::string prefix_;
};

// Zarr v3 sharding_indexed with index_location "end": shard (sx, sy, sz) of `shard_bricks`
// bricks per edge is the file "<array>/c/[0/]sz/sy/sx"; its inner chunks in the order they
// come, then the index (offset, size as u64 little-endian per inner chunk, C order over
// (z, y, x); 2^64-1 twice for an absent chunk) and its crc32c. A shard with no chunk is not
// written. Bricks must come shard by shard (chunk_order()).
class ShardWriter : public ChunkWriter {
 public:
  ShardWriter(OutputFolder& folder, std::string array, bool channel_axis, int shard_bricks);
  ~ShardWriter() override;
  void put(const std::array<std::int64_t, 3>& brick, const void* data, std::size_t size) override;
  void finish() override;
  std::uint64_t shards() const { return shards_; }

 private:
  void close_shard();
  OutputFolder& folder_;
  std::string prefix_;
  std::int64_t s_;
  std::array<std::int64_t, 3> shard_{-1, -1, -1};
  std::vector<std::uint64_t> index_;  // 2 per inner chunk
  int fd_ = -1;
  std::string path_;
  std::uint64_t offset_ = 0, shards_ = 0;
};

// The bricks of a grid in the order the writers want them: bz, by, bx (bx fastest) for one
// file per chunk; shard by shard (each shard's bricks in that order) for shards of
// `shard_bricks` (> 0).
std::vector<std::array<std::int64_t, 3>> chunk_order(const std::array<std::int64_t, 3>& grid,
                                                     int shard_bricks);

}  // namespace vispack::format::ome_zarr
