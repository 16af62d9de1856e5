// vispack-pack --merge and vispack-merge (pipeline/pack/pack.h "Sharding"): the packed file from
// the shards' slab files. Kept apart from the rest of the pack so that vispack-merge links no image
// library: nothing here reads a slice (pack_plan.h).
#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>
#include <set>

#include <nlohmann/json.hpp>

#include "pack_plan.h"
#include "pack_slab.h"
#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/hash.h"
#include "vispack/format/writer.h"
#include "vispack/pipeline/pack/pack_merge.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;
using nlohmann::json;
using namespace detail;  // pack_plan.h, pack_slab.h

namespace {

// A slab file opened for the merge, checked against what the merge expects (`expected_header` =
// the JSON it would write, input fingerprint aside; `level1_bytes`: the size of each channel's
// level-1 slices; `slices`: the slab's stack slices, for messages). Nothing of it is held whole:
// its trailing checksum is checked reading it once through a small buffer, its bricks' stored
// bytes stay in the file (take_bricks() gives their offsets; the format Writer copies them from
// payload_file() into the packed file, file to file), and its level-1 slices are decoded one
// slice at a time (read_level1). A 64-slice slab of 2048x1216 slices is ~130 MB, which a merge
// that read it into memory paid for in fresh pages (and zeroing) before copying it out again.
// Owns the open file (RAII); payload_file() is valid while this object lives. Throws
// FormatError / InputError / IoError naming the file.
class SlabFile {
 public:
  SlabFile(const std::string& path, const std::string& expected_header,
           const std::string& expected_input, std::pair<int, int> slices,
           const std::vector<std::size_t>& level1_bytes)
      : path_(path), file_(std::fopen(path.c_str(), "rb"), &std::fclose) {
    if (!file_) throw IoError(cat(path, ": cannot open: ", std::strerror(errno)));
    std::error_code ec;
    const std::uint64_t file_size = fs::file_size(path, ec);
    if (ec) throw IoError(cat(path, ": cannot read its size: ", ec.message()));
    check_magic_and_checksum(file_size);
    pos_ = 8;
    end_ = file_size - 8;
    const json expected = read_header(expected_header, expected_input, slices);
    read_bricks(expected["bricks"].get<std::size_t>());
    read_level1_frames(level1_bytes);
    if (pos_ != end_) throw bad("trailing bytes after the level-1 slices");
    payload_file_.fd = fileno(file_.get());
    payload_file_.name = path;
  }

  // The bricks (index order within the slab), their stored bytes at file_offset in
  // payload_file(); once.
  std::vector<format::EncodedBrick> take_bricks() { return std::move(bricks_); }
  const format::PayloadFile& payload_file() const { return payload_file_; }
  // The next `n` bytes of channel c's level-1 slices into out.
  void read_level1(std::size_t c, std::uint8_t* out, std::size_t n) { readers_[c]->read(out, n); }
  // Checks that every channel's level-1 frame ended exactly after what was read.
  void finish_level1() {
    for (auto& r : readers_)
      r->finish();
  }

 private:
  // The magic, then the trailing checksum over everything before it, read once through a small
  // buffer; leaves the file positioned after the magic.
  void check_magic_and_checksum(std::uint64_t file_size) {
    char magic[8] = {};
    if (file_size < 8 + 4 + 8) throw bad("not a vispack slab file (bad magic or truncated)");
    read_exactly(magic, 8);
    if (std::memcmp(magic, kSlabMagic, 8) != 0)
      throw bad("not a vispack slab file (bad magic or truncated)");
    Xxh64Stream hash;
    hash.update(magic, 8);
    std::vector<char> buffer(std::size_t(1) << 20);
    for (std::uint64_t left = file_size - 16; left > 0;) {
      const std::size_t n = std::size_t(std::min<std::uint64_t>(left, buffer.size()));
      read_exactly(buffer.data(), n);
      hash.update(buffer.data(), n);
      left -= n;
    }
    std::uint64_t sum = 0;
    read_exactly(&sum, 8);
    if (hash.digest() != sum) throw bad("checksum mismatch (corrupt or truncated)");
    if (std::fseek(file_.get(), 8, SEEK_SET) != 0) throw IoError(cat(path_, ": seek failed"));
  }

  // The JSON header, checked against the expected one (version, pack options and stack shape,
  // then the input fingerprint). Returns the expected header.
  json read_header(const std::string& expected_header, const std::string& expected_input,
                   std::pair<int, int> slices) {
    std::uint32_t header_size = 0;
    take(&header_size, 4);
    if (header_size > end_ - pos_) throw bad("truncated header");
    std::string header_text(header_size, '\0');
    take(header_text.data(), header_size);
    json header = json::parse(header_text, nullptr, false);
    if (!header.is_object() || !header.contains("input")) throw bad("bad header");
    if (header.value("version", 0) != kSlabVersion) {
      throw InputError(cat(path_, ": slab file version ", header.value("version", 0),
                           " (another vispack-pack); this merge reads version ", kSlabVersion,
                           ": rerun vispack-pack --slices ", slices.first, ":", slices.second));
    }
    const std::string input = header["input"].is_string() ? header["input"].get<std::string>() : "";
    json expected = json::parse(expected_header);
    header["input"] = expected["input"];
    if (header != expected) {
      throw InputError(cat(path_,
                           ": written with other pack options or another stack shape; rerun "
                           "vispack-pack --slices ",
                           slices.first, ":", slices.second));
    }
    if (input != expected_input) {
      throw InputError(cat(path_, ": out of date: slices ", slices.first, ":", slices.second,
                           " changed since it was written; rerun vispack-pack --slices ",
                           slices.first, ":", slices.second));
    }
    return expected;
  }

  // `count` brick records: codec, range, checksum, label set; the stored bytes stay in the file.
  void read_bricks(std::size_t count) {
    bricks_.resize(count);
    for (auto& b : bricks_) {
      std::uint8_t rec[kSlabRecordSize];
      take(rec, kSlabRecordSize);
      if (rec[0] > 2) throw bad(cat("unknown codec ", int(rec[0])));
      b.codec = format::Codec(rec[0]);
      std::memcpy(b.min.data(), rec + 8, 8);
      std::memcpy(b.max.data(), rec + 16, 8);
      std::uint64_t size = 0;
      std::uint32_t labels = 0;
      std::memcpy(&b.checksum, rec + 24, 8);
      std::memcpy(&size, rec + 32, 8);
      std::memcpy(&labels, rec + 40, 4);
      if (std::uint64_t(labels) * 4 > end_ - pos_) throw bad("truncated label set");
      b.labels.resize(labels);
      take(b.labels.data(), std::size_t(labels) * 4);
      if (size > end_ - pos_) throw bad("truncated payload");
      // Left in the file: where it is.
      b.file_offset = pos_;
      b.file_bytes = size;
      skip(size);
    }
  }

  // Each channel's level-1 slices: one zstd frame, held compressed and decoded on demand.
  void read_level1_frames(const std::vector<std::size_t>& level1_bytes) {
    for (std::size_t c = 0; c < level1_bytes.size(); ++c) {
      std::uint64_t raw = 0, size = 0;
      take(&raw, 8);
      take(&size, 8);
      if (raw != level1_bytes[c])
        throw bad(
            cat("level-1 slices of channel ", c, ": ", raw, " bytes, expected ", level1_bytes[c]));
      if (size > end_ - pos_) throw bad("truncated level-1 slices");
      frames_.emplace_back(new std::uint8_t[std::size_t(size)]);
      take(frames_.back().get(), size);
      readers_.push_back(std::make_unique<format::ZstdFrameReader>(
          frames_.back().get(), std::size_t(size), cat(path_, ": level-1 slices of channel ", c)));
    }
  }

  FormatError bad(const std::string& what) const { return FormatError(cat(path_, ": ", what)); }
  void read_exactly(void* dst, std::size_t n) {
    if (n > 0 && std::fread(dst, 1, n, file_.get()) != n) {
      if (std::ferror(file_.get())) throw IoError(cat(path_, ": read failed"));
      throw bad("truncated (the file shrank while being read)");
    }
  }
  void take(void* dst, std::uint64_t n) {
    if (n > end_ - pos_) throw bad("truncated");
    read_exactly(dst, std::size_t(n));  // an empty label set: no bytes (its data() may be null)
    pos_ += n;
  }
  void skip(std::uint64_t n) {
    if (n == 0) return;
    if (std::fseek(file_.get(), long(n), SEEK_CUR) != 0) throw IoError(cat(path_, ": seek failed"));
    pos_ += n;
  }

  std::string path_;
  std::unique_ptr<std::FILE, int (*)(std::FILE*)> file_;
  std::uint64_t pos_ = 0, end_ = 0;
  std::vector<format::EncodedBrick> bricks_;
  std::vector<std::unique_ptr<std::uint8_t[]>> frames_;
  std::vector<std::unique_ptr<format::ZstdFrameReader>> readers_;
  format::PayloadFile payload_file_;
};

// The bricks of channel c in a slab's brick list (channel, then by, then bx).
struct BrickSpan {
  const format::EncodedBrick* first;
  const format::EncodedBrick* last;
  const format::EncodedBrick* begin() const { return first; }
  const format::EncodedBrick* end() const { return last; }
};
BrickSpan bricks_of_channel(const std::vector<format::EncodedBrick>& bricks, std::size_t c,
                            std::int64_t per_channel) {
  const format::EncodedBrick* first = bricks.data() + c * std::size_t(per_channel);
  return {first, first + per_channel};
}

// The stack slices [A, B) whose files lie in slab bz (what --slices names; an empty slot has none).
std::pair<int, int> slab_stack_slices(const PackPlan& plan, std::int64_t bz) {
  const auto [first, last] = slab_slices(plan, bz);
  const SliceRange r = stack_range_of_output_z(plan, {first, last});
  // A slab of empty slots only: the shard of the file before it packs it.
  return {r.first == r.last ? std::max(0, r.first - 1) : r.first, r.last};
}

// The error for slab file `path` (of stack slices `slices`) not being there.
InputError missing_slab(const std::string& path, std::pair<int, int> slices) {
  return InputError(cat(path, ": missing: the pack shard holding slices ", slices.first, ":",
                        slices.second, " has not run (vispack-pack --slices ", slices.first, ":",
                        slices.second, ")"));
}

// The body bounds a cropped pack's shards recorded in slab file `path` (header crop_body_px),
// read from its header alone (the merge checks the whole file later). `slices`: the slab's stack
// slices, for messages. Throws InputError (missing, another version, no bounds recorded: names
// the shard to rerun), FormatError (not a slab file), IoError.
cv::Rect slab_body_bounds(const std::string& path, std::pair<int, int> slices) {
  const std::string rerun = cat("vispack-pack --slices ", slices.first, ":", slices.second);
  if (!fs::exists(path)) throw missing_slab(path, slices);
  std::unique_ptr<std::FILE, int (*)(std::FILE*)> file(std::fopen(path.c_str(), "rb"),
                                                       &std::fclose);
  if (!file) throw IoError(cat(path, ": cannot open: ", std::strerror(errno)));
  char magic[8] = {};
  std::uint32_t header_size = 0;
  if (std::fread(magic, 1, 8, file.get()) != 8 || std::memcmp(magic, kSlabMagic, 8) != 0 ||
      std::fread(&header_size, 4, 1, file.get()) != 1 || header_size > (1u << 26))
    throw FormatError(cat(path, ": not a vispack slab file (bad magic or truncated)"));
  std::string text(header_size, '\0');
  if (std::fread(text.data(), 1, header_size, file.get()) != header_size)
    throw FormatError(cat(path, ": truncated header"));
  const json header = json::parse(text, nullptr, false);
  if (!header.is_object()) throw FormatError(cat(path, ": bad header"));
  if (header.value("version", 0) != kSlabVersion)
    throw InputError(cat(path, ": slab file version ", header.value("version", 0),
                         " (another vispack-pack); this merge reads version ", kSlabVersion,
                         ": rerun ", rerun));
  const json& box = header.contains("crop_body_px") ? header["crop_body_px"] : json();
  if (!box.is_array() || box.size() != 4 ||
      !std::all_of(box.begin(), box.end(), [](const json& v) { return v.is_number_integer(); }))
    throw InputError(
        cat(path, ": written without pack.crop_margin_px (no body bounds); rerun ", rerun));
  return cv::Rect(box[0].get<int>(), box[1].get<int>(), box[2].get<int>(), box[3].get<int>());
}

}  // namespace

StageResult run_pack_merge(const Config& config, const StageOptions& options) {
  if (!options.slices.empty())
    throw UsageError("--merge builds the whole file from every shard; it takes no --slices");
  // A cropped pack's body bounds come from the first slab file's header (the shards read the
  // masks): the merge reads no image.
  PackPlan plan = plan_pack(config, options, [&](int slice_count, cv::Size) {
    return slab_body_bounds(slab_path(config, 0),
                            {0, std::min(slice_count, config.pack.brick_edge)});
  });
  StageOptions unit = options;
  StageRun run(config, "pack", 1, unit, kPackSections);
  run.remove_stale_temporaries_of(config.output);
  if (run.up_to_date(0, plan.input, {config.output})) {
    run.skip(0);
    return run.finish(config.output);
  }
  const auto slabs = format::level0_slab_count(plan.wo);
  // Every slab file must be there before anything is written.
  for (std::int64_t bz = 0; bz < slabs; ++bz) {
    const std::string path = slab_path(config, bz);
    if (!fs::exists(path)) throw missing_slab(path, slab_stack_slices(plan, bz));
  }
  make_directories(fs::path(config.output).parent_path().string());
  format::Writer writer(config.output, plan.wo);
  const std::vector<format::ChannelSpec> stored = writer.stored_channels();
  const std::int64_t e = plan.wo.brick_edge;
  const std::int64_t nx = plan.out_size.width, ny = plan.out_size.height;
  const std::int64_t gx = (nx + e - 1) / e, gy = (ny + e - 1) / e;
  const bool has_level1 = format::Writer::level_count_for(plan.wo.dims, int(e)) > 1;
  const std::size_t plane1 = std::size_t((nx + 1) / 2) * std::size_t((ny + 1) / 2);
  std::set<std::uint16_t> ids_seen;
  std::uint64_t bytes = 0;
  std::vector<std::vector<std::uint8_t>> level1_slices(stored.size());  // one slice each, reused
  std::unique_ptr<SlabFile> single_level_slab;
  for (std::int64_t bz = 0; bz < slabs; ++bz) {
    const std::string path = slab_path(config, bz);
    const auto slices = slab_slices(plan, bz);
    const std::string input = slab_input(config, plan, bz);
    const int nzv = slices.second - slices.first;
    const auto stack_slices = slab_stack_slices(plan, bz);
    const std::size_t n1 = has_level1 ? std::size_t(nzv + 1) / 2 : 0;
    std::vector<std::size_t> level1_bytes;
    if (has_level1)
      for (const auto& c : stored)
        level1_bytes.push_back(plane1 * n1 * format::channel_type_bytes(c.type));
    auto slab = std::make_unique<SlabFile>(
        path, slab_header_json(plan, stored, bz, std::size_t(gx * gy) * stored.size(), input),
        input, stack_slices, level1_bytes);
    bytes += fs::file_size(path);
    std::vector<format::EncodedBrick> bricks = slab->take_bricks();
    for (std::size_t c = 0; c < stored.size(); ++c)
      for (const auto& b : bricks_of_channel(bricks, c, gx * gy))
        for (std::uint32_t id : b.labels)
          if (id) ids_seen.insert(std::uint16_t(id));
    // Level 0 as stored by the shard (never decoded: copied from its file when the Writer writes
    // the slab, at the slab's last level-1 slice, or at finish() for a single-level volume); the
    // coarser levels from its level-1 slices, decoded one slice at a time.
    writer.provide_level0_slab(bz, std::move(bricks), &slab->payload_file());
    for (std::size_t k = 0; k < n1; ++k) {
      std::vector<const void*> slice;
      for (std::size_t c = 0; c < stored.size(); ++c) {
        const std::size_t n = level1_bytes[c] / n1;
        if (level1_slices[c].size() < n) level1_slices[c].resize(n);
        slab->read_level1(c, level1_slices[c].data(), n);
        slice.push_back(level1_slices[c].data());
      }
      writer.append_level1_slice(slice);
    }
    slab->finish_level1();
    if (!has_level1) single_level_slab = std::move(slab);  // its bytes are copied at finish()
    run.add_bytes(0);
  }
  writer.finish();
  run.done(0, plan.input, {config.output}, bytes);
  report_pack(run, config, plan, ids_seen, bytes);
  run.set_report("merged_slabs", slabs);
  return run.finish(config.output);
}

}  // namespace vispack::pipeline
