// The OME-Zarr export's driver (ome_zarr.h): metadata first, then each channel's bricks level by
// level, encoded in batches on worker threads and written in order by this thread.
#include "vispack/format/ome_zarr.h"

#include <zstd.h>

#include <algorithm>
#include <chrono>
#include <memory>

#include "ome_zarr_chunks.h"
#include "ome_zarr_metadata.h"
#include "ome_zarr_plan.h"
#include "ome_zarr_store.h"
#include "vispack/common/error.h"
#include "vispack/common/parallel.h"
#include "vispack/common/progress.h"

namespace vispack::format {

using namespace ome_zarr;
using nlohmann::json;

NgffVersion parse_ngff_version(const std::string& text) {
  if (text == "0.4") return NgffVersion::k04;
  if (text == "0.5") return NgffVersion::k05;
  throw UsageError(cat("unknown NGFF version \"", text, "\" (use 0.4 or 0.5)"));
}

const char* ngff_version_name(NgffVersion version) {
  return version == NgffVersion::k04 ? "0.4" : "0.5";
}

namespace {

// A group: .zgroup + .zattrs (Zarr v2) or zarr.json (v3). `ngff` goes under "ome" in v3.
void write_group(OutputFolder& folder, const ExportPlan& plan, const std::string& path,
                 const json& ngff, const json& plain) {
  const std::string prefix = path.empty() ? "" : path + "/";
  if (plan.version == NgffVersion::k05) {
    folder.write_json(prefix + "zarr.json", zarr_v3_group(ngff, plain));
    return;
  }
  json attributes = plain.is_object() ? plain : json::object();
  if (ngff.is_object()) attributes.update(ngff);
  folder.write_json(prefix + ".zgroup", {{"zarr_format", 2}});
  folder.write_json(prefix + ".zattrs", attributes);
}

void write_metadata(OutputFolder& folder, const Reader& reader, const ExportPlan& plan,
                    const OmeZarrOptions& options) {
  write_group(folder, plan, "", nullptr, root_attributes(reader, plan));
  for (const ExportImage& image : plan.images) {
    write_group(folder, plan, image.path, image_attributes(reader, plan, image), nullptr);
    for (int level : plan.levels) {
      const std::string array = image.path + "/" + std::to_string(level);
      if (plan.version == NgffVersion::k05) {
        folder.write_json(
            array + "/zarr.json",
            zarr_v3_array(reader, image, level, options.zstd_level, options.shard_bricks));
      } else {
        folder.write_json(array + "/.zarray",
                          zarr_v2_array(reader, image, level, options.zstd_level));
      }
    }
  }
  if (!plan.label_host.empty() && !plan.label_names.empty())
    write_group(folder, plan, plan.label_host + "/labels", labels_group_attributes(plan), nullptr);
}

void check_options(const OmeZarrOptions& o) {
  if (o.zstd_level < 1 || o.zstd_level > ZSTD_maxCLevel())
    throw UsageError(cat("--zstd-level ", o.zstd_level, " is outside [1, ", ZSTD_maxCLevel(), "]"));
  if (o.shard_bricks < 1 || o.shard_bricks > 64)
    throw UsageError(cat("--shard-bricks ", o.shard_bricks, " is outside [1, 64]"));
}

}  // namespace

namespace {

using ImageRun = std::vector<const ExportImage*>;

// Images of one channel are adjacent in the plan: each run shares its bricks.
std::vector<ImageRun> channel_runs(const ExportPlan& plan) {
  std::vector<ImageRun> runs;
  for (const ExportImage& image : plan.images) {
    if (runs.empty() || runs.back().front()->channel != image.channel) runs.emplace_back();
    runs.back().push_back(&image);
  }
  return runs;
}

// The chunk writing of one export: batches of bricks encoded on `threads` threads, written in
// order, each brick's mapped pages released once written (memory: a few bricks).
class ChunkExport {
 public:
  ChunkExport(const Reader& reader, OutputFolder& folder, const OmeZarrOptions& options,
              bool sharded, Progress& progress, OmeZarrStats& stats)
      : reader_(reader),
        folder_(folder),
        options_(options),
        sharded_(sharded),
        threads_(resolve_threads(options.threads)),
        batch_(std::size_t(std::max(4, 4 * threads_))),
        progress_(progress),
        stats_(stats) {
    for (std::size_t i = 0; i < batch_; ++i) {
      encoders_.push_back(
          std::make_unique<ChunkEncoder>(reader, options.zstd_level, options.copy_stored_bricks));
    }
    results_.resize(batch_);
  }

  // Every chunk of the run's images at `level`.
  void level(const ImageRun& run, int level) {
    const int channel = run.front()->channel;
    const auto order = chunk_order(reader_.brick_grid(level), sharded_ ? options_.shard_bricks : 0);
    std::vector<std::unique_ptr<ChunkWriter>> writers;
    std::vector<ShardWriter*> shard_writers;
    for (const ExportImage* image : run) {
      const std::string array = image->path + "/" + std::to_string(level);
      const bool channel_axis = image->kind == ImageKind::kColour;
      if (sharded_) {
        auto w = std::make_unique<ShardWriter>(folder_, array, channel_axis, options_.shard_bricks);
        shard_writers.push_back(w.get());
        writers.push_back(std::move(w));
      } else {
        writers.push_back(std::make_unique<V2ChunkWriter>(folder_, array, channel_axis));
      }
    }
    for (auto& r : results_)
      r.resize(run.size());
    for (std::size_t first = 0; first < order.size(); first += batch_) {
      const std::size_t n = std::min(batch_, order.size() - first);
      parallel_for(std::int64_t(n), threads_, [&](std::int64_t i) {
        const auto& b = order[first + std::size_t(i)];
        const BrickInfo& brick = reader_.brick(channel, level, b[0], b[1], b[2]);
        for (std::size_t k = 0; k < run.size(); ++k)
          encoders_[std::size_t(i)]->encode(brick, *run[k], results_[std::size_t(i)][k]);
      });
      for (std::size_t i = 0; i < n; ++i)
        write_brick(channel, level, order[first + i], run.size(), results_[i], writers);
      stats_.bricks += n;
      progress_.advance(std::int64_t(n));
    }
    for (auto& w : writers)
      w->finish();
    for (const ShardWriter* w : shard_writers)
      stats_.shards += w->shards();
  }

 private:
  void write_brick(int channel, int level, const std::array<std::int64_t, 3>& b, std::size_t images,
                   const std::vector<EncodedChunk>& chunks,
                   std::vector<std::unique_ptr<ChunkWriter>>& writers) {
    const BrickInfo& brick = reader_.brick(channel, level, b[0], b[1], b[2]);
    for (std::size_t k = 0; k < images; ++k) {
      const EncodedChunk& c = chunks[k];
      writers[k]->put(b, c.data(), c.size());
      stats_.chunks_copied += c.how == EncodedChunk::How::kCopied;
      stats_.chunks_encoded += c.how == EncodedChunk::How::kEncoded;
      stats_.chunks_skipped += c.how == EncodedChunk::How::kSkipped;
    }
    reader_.release_payload_pages(brick);  // written: the memory stays at a few bricks
  }

  const Reader& reader_;
  OutputFolder& folder_;
  const OmeZarrOptions& options_;
  bool sharded_;
  int threads_;
  std::size_t batch_;
  Progress& progress_;
  OmeZarrStats& stats_;
  std::vector<std::unique_ptr<ChunkEncoder>> encoders_;
  std::vector<std::vector<EncodedChunk>> results_;
};

}  // namespace

OmeZarrStats export_ome_zarr(const Reader& reader, const std::string& out_path,
                             const OmeZarrOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  check_options(options);
  const ExportPlan plan = make_export_plan(reader, options);
  OutputFolder folder(out_path, options.overwrite);
  write_metadata(folder, reader, plan, options);

  const std::vector<ImageRun> runs = channel_runs(plan);
  std::int64_t total = 0;
  for (std::size_t r = 0; r < runs.size(); ++r)
    for (int level : plan.levels) {
      const auto g = reader.brick_grid(level);
      total += g[0] * g[1] * g[2];
    }
  OmeZarrStats stats;
  Progress progress(cat("export ", folder.final_path()), total, "bricks", options.quiet);
  ChunkExport chunks(reader, folder, options, plan.version == NgffVersion::k05, progress, stats);
  for (const ImageRun& run : runs)
    for (int level : plan.levels)
      chunks.level(run, level);
  progress.finish();
  folder.commit();
  stats.files = folder.files();
  stats.bytes = folder.bytes();
  stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return stats;
}

}  // namespace vispack::format
