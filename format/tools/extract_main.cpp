// vispack-extract FILE --channel NAME [--level L] (--z Z -o OUT.png|OUT.tif | -o OUT.nrrd)
#include <algorithm>
#include <cstring>
#include <filesystem>
#include <string>

#include "vispack/common/cli.h"
#include "vispack/common/error.h"
#include "vispack/common/nrrd.h"
#include "vispack/format/reader.h"

#ifdef VISPACK_HAVE_IMAGE_IO
#include "vispack/common/image_io.h"
#endif

using namespace vispack;
using namespace vispack::format;

namespace {

std::string lower_extension(const std::string& path) {
  std::string ext = std::filesystem::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return char(std::tolower(c)); });
  return ext;
}

NrrdType nrrd_type(ChannelType t) {
  switch (t) {
    case ChannelType::kRgba8:
      return NrrdType::kUint8;
    case ChannelType::kInt16:
      return NrrdType::kInt16;
    case ChannelType::kUint8:
      return NrrdType::kUint8;
    case ChannelType::kUint16:
      return NrrdType::kUint16;
  }
  return NrrdType::kUint8;
}

// One slice as an 8- or 16-bit image through the project's one image writer (common's
// image_io.h: encoded in memory, written atomically through AtomicFile).
void write_slice_image(const std::string& out, const std::vector<std::uint8_t>& voxels,
                       ChannelType type, std::int64_t w, std::int64_t h) {
#ifdef VISPACK_HAVE_IMAGE_IO
  ImageView view;
  view.width = int(w);
  view.height = int(h);
  view.channels = channel_type_components(type);
  view.bits = type == ChannelType::kInt16 || type == ChannelType::kUint16 ? 16 : 8;
  std::vector<std::uint8_t> pixels;
  if (type == ChannelType::kInt16) {
    // CT: 16-bit unsigned grey = HU + 32768 (so -1024 HU is 31744, 0 HU is 32768).
    pixels.resize(voxels.size());
    const std::size_t n = std::size_t(w * h);
    for (std::size_t i = 0; i < n; ++i) {
      std::int16_t hu;
      std::memcpy(&hu, voxels.data() + 2 * i, 2);
      std::uint16_t v = std::uint16_t(std::int32_t(hu) + 32768);
      std::memcpy(pixels.data() + 2 * i, &v, 2);
    }
  }
  view.pixels = pixels.empty() ? voxels.data() : pixels.data();
  write_image_file(out, view);
#else
  throw UsageError(
      cat(out, ": this build has no OpenImageIO; extract a whole channel with -o OUT.nrrd"));
#endif
}

}  // namespace

int main(int argc, char** argv) {
  return run_main("vispack-extract", argc, argv, [](Args& args) {
    args.describe(
        "FILE --channel NAME [--level L] (--z Z -o OUT.png|OUT.tif | -o OUT.nrrd)",
        "Extracts one z slice of a channel as an image (PNG/TIFF; CT as 16-bit HU+32768, "
        "uint16 labels as 16-bit, rgba as 8-bit RGBA), or a whole channel as NRRD with spacing "
        "and origin in mm (opens in 3D Slicer, ITK, numpy).");
    const std::string channel =
        args.option("--channel", "NAME", "channel to extract (rgba, ct, labels)").value_or("");
    const long long level =
        args.option_int("--level", "L", "pyramid level (default 0)").value_or(0);
    const auto z = args.option_int("--z", "Z", "slice index for an image output");
    const std::string out =
        args.option("--output", "OUT", "output file (.png, .tif, .tiff or .nrrd)").value_or("");
    const std::string out_short = args.option("-o", "OUT", "same as --output").value_or("");
    const std::string file = args.positional("FILE", "packed volume (.vpk)");
    args.done();
    const std::string output = out.empty() ? out_short : out;
    if (channel.empty()) throw UsageError("--channel NAME is required");
    if (output.empty()) throw UsageError("-o OUT is required");
    const std::string ext = lower_extension(output);
    const bool nrrd = ext == ".nrrd";
    const bool image = ext == ".png" || ext == ".tif" || ext == ".tiff";
    if (!nrrd && !image)
      throw UsageError(cat(output, ": unknown output extension (use .png, .tif, .tiff or .nrrd)"));
    if (image && !z) throw UsageError("an image output needs --z Z");
    if (nrrd && z) throw UsageError("--z is for image outputs; a .nrrd holds the whole channel");

    Reader r = Reader::open(file);
    auto c = r.find_channel(channel);
    if (!c) {
      std::string names;
      for (const auto& s : r.channels())
        names += (names.empty() ? "" : ", ") + s.name;
      throw UsageError(cat(file, ": no channel \"", channel, "\" (the file has: ", names, ")"));
    }
    if (level < 0 || level >= r.level_count()) {
      throw UsageError(
          cat("--level ", level, " is outside [0, ", r.level_count() - 1, "] for ", file));
    }
    const ChannelType type = r.channels()[std::size_t(*c)].type;
    const LevelInfo& li = r.level(int(level));
    if (nrrd) {
      NrrdVolume v;
      v.type = nrrd_type(type);
      v.components = channel_type_components(type);
      v.dims = li.dims;
      v.spacing_mm = li.spacing_mm;
      v.origin_mm = li.origin_mm;
      v.data = r.read_level(*c, int(level));
      write_nrrd(output, v);
      return 0;
    }
    if (*z < 0 || *z >= li.dims[2]) {
      throw UsageError(
          cat("--z ", *z, " is outside [0, ", li.dims[2] - 1, "] at level ", level, " of ", file));
    }
    std::vector<std::uint8_t> slice(std::size_t(li.dims[0] * li.dims[1]) *
                                    channel_type_bytes(type));
    r.read_region(*c, int(level), 0, 0, *z, li.dims[0], li.dims[1], 1, slice.data());
    write_slice_image(output, slice, type, li.dims[0], li.dims[1]);
    return 0;
  });
}
