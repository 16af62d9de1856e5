#include "vispack/pipeline/vdb.h"

#include <unistd.h>

#include <cstdio>
#include <filesystem>

#include <openvdb/openvdb.h>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/pipeline/slice_io.h"
#include "vispack/pipeline/version.h"
#include "vispack/pipeline/work_layout.h"

namespace vispack::pipeline {

namespace fs = std::filesystem;

StageResult run_vdb_stage(const Config& config, const StageOptions& options) {
  if (!config.vdb.enabled || config.vdb_output.empty())
    throw ConfigError(cat(config.path, ": vdb.enabled is false: no OpenVDB export configured"));
  const StackInputs inputs = read_stack_inputs(config);
  const int n = int(inputs.rgb.size());
  require_whole_stack(options, n, "vispack-vdb");
  const cv::Size size = inputs.size();
  const bool has_ct = config.ct.has_value(), has_labels = config.seg.has_value();

  Fingerprint fp = intermediates_fingerprint(config, inputs);
  fp.text(config.vdb_output);
  StageOptions unit = options;
  unit.slices.clear();
  StageRun run(config, "vdb", 1, unit, {"vdb", "spacing_mm", "rgb", "ct", "seg"});
  run.remove_stale_temporaries_of(config.vdb_output);
  const std::string input = fp.str();
  if (run.up_to_date(0, input, {config.vdb_output})) {
    run.skip(0);
    return run.finish(config.vdb_output);
  }

  openvdb::initialize();
  auto ct_grid = openvdb::FloatGrid::create(-1024.0f);
  auto label_grid = openvdb::Int32Grid::create(0);
  auto rgb_grid = openvdb::Vec3SGrid::create(openvdb::Vec3s(0, 0, 0));
  openvdb::math::Mat4d scale = openvdb::math::Mat4d::identity();
  scale.setToScale(
      openvdb::Vec3d(config.spacing_mm[0], config.spacing_mm[1], config.spacing_mm[2]));
  auto xform = openvdb::math::Transform::createLinearTransform(scale);
  ct_grid->setTransform(xform);
  label_grid->setTransform(xform->copy());
  rgb_grid->setTransform(xform->copy());
  auto ct_acc = ct_grid->getAccessor();
  auto label_acc = label_grid->getAccessor();
  auto rgb_acc = rgb_grid->getAccessor();
  std::uint64_t active = 0, bytes = 0;
  for (int k = 0; k < n; ++k) {
    const Intermediates in = read_intermediates(config, inputs, k);
    const cv::Mat &mask = in.mask, &rgb = in.rgb, &ct = in.ct, &labels = in.labels;
    bytes += in.bytes;
    for (int y = 0; y < size.height; ++y) {
      const std::uint8_t* m = mask.ptr<std::uint8_t>(y);
      for (int x = 0; x < size.width; ++x) {
        if (!m[x]) continue;
        openvdb::Coord ijk(x, y, k);
        const cv::Vec3b& c = rgb.at<cv::Vec3b>(y, x);
        rgb_acc.setValue(ijk, openvdb::Vec3s(c[0] / 255.0f, c[1] / 255.0f, c[2] / 255.0f));
        if (has_ct) ct_acc.setValue(ijk, float(int(ct.at<std::uint16_t>(y, x)) - 32768));
        if (has_labels) label_acc.setValue(ijk, int(labels.at<std::uint16_t>(y, x)));
        ++active;
      }
    }
  }
  openvdb::GridPtrVec grids;
  auto name_grid = [&](openvdb::GridBase::Ptr g, const char* name, const char* units) {
    g->setName(name);
    g->insertMeta("vispack_version", openvdb::StringMetadata(version_string()));
    g->insertMeta("units", openvdb::StringMetadata(units));
    grids.push_back(g);
  };
  if (has_ct) name_grid(ct_grid, "ct", "HU");
  if (has_labels) name_grid(label_grid, "labels", "id");
  name_grid(rgb_grid, "rgb", "rgb01");

  make_directories(fs::path(config.vdb_output).parent_path().string());
  // OpenVDB writes by path: it writes the AtomicFile's temporary, which commit() then fsyncs and
  // renames into place (removed on any failure).
  AtomicFile out(config.vdb_output);
  try {
    openvdb::io::File file(out.temp_path());
    file.write(grids);  // default compression: Blosc if available, else zip
    file.close();
  } catch (const openvdb::Exception& e) {
    throw IoError(cat(config.vdb_output, ": cannot write: ", e.what()));
  }
  out.commit();
  run.done(0, input, {config.vdb_output}, bytes);
  run.set_report("output", config.vdb_output);
  run.set_report("output_bytes", std::uint64_t(fs::file_size(config.vdb_output)));
  nlohmann::json names = nlohmann::json::array();
  for (const auto& g : grids)
    names.push_back(g->getName());
  run.set_report("grids", names);
  run.set_quality("active_voxels", active);
  return run.finish(config.vdb_output);
}

}  // namespace vispack::pipeline
