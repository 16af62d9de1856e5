// vispack-extract FILE --channel NAME [--level L] (--z Z -o OUT.png|OUT.tif [--window C:W |
// --preview] | -o OUT.nrrd)
#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <iostream>
#include <optional>
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

// A CT display window in HU: grey 0 at centre - width / 2, 255 at centre + width / 2.
struct Window {
  double centre = 40.0;  // soft tissue (the default of --preview)
  double width = 400.0;
};

// "C:W" (HU); the width must be > 0.
Window parse_window(const std::string& text) {
  const std::size_t colon = text.find(':');
  Window w;
  try {
    if (colon == std::string::npos) throw std::invalid_argument(text);
    std::size_t used = 0;
    const std::string c = text.substr(0, colon), width = text.substr(colon + 1);
    w.centre = std::stod(c, &used);
    if (used != c.size()) throw std::invalid_argument(text);
    w.width = std::stod(width, &used);
    if (used != width.size()) throw std::invalid_argument(text);
  } catch (const std::exception&) {
    throw UsageError(cat("--window \"", text, "\" is not CENTRE:WIDTH in HU (e.g. 40:400)"));
  }
  if (!(w.width > 0) || !std::isfinite(w.centre) || !std::isfinite(w.width))
    throw UsageError(cat("--window \"", text, "\": the width must be a number > 0"));
  return w;
}

// One slice as an 8- or 16-bit image through the project's one image writer (common's
// image_io.h: encoded in memory, written atomically through AtomicFile). CT: 16-bit HU + 32768
// (exact), or with `window` 8-bit grey through that window (a preview). Returns what was written,
// for the confirmation line.
std::string write_slice_image(const std::string& out, const std::vector<std::uint8_t>& voxels,
                              ChannelType type, std::int64_t w, std::int64_t h,
                              const std::optional<Window>& window) {
#ifdef VISPACK_HAVE_IMAGE_IO
  ImageView view;
  view.width = int(w);
  view.height = int(h);
  view.channels = channel_type_components(type);
  view.bits = type == ChannelType::kInt16 || type == ChannelType::kUint16 ? 16 : 8;
  std::vector<std::uint8_t> pixels;
  std::string what;
  const std::size_t n = std::size_t(w * h);
  if (type == ChannelType::kInt16 && window) {
    pixels.resize(n);
    const double low = window->centre - window->width / 2;
    for (std::size_t i = 0; i < n; ++i) {
      std::int16_t hu;
      std::memcpy(&hu, voxels.data() + 2 * i, 2);
      const double grey = (double(hu) - low) / window->width * 255.0;
      pixels[i] = std::uint8_t(std::lround(std::clamp(grey, 0.0, 255.0)));
    }
    view.bits = 8;
    what = cat("8-bit grey, window ", window->centre, ":", window->width, " HU");
  } else if (type == ChannelType::kInt16) {
    // CT: 16-bit unsigned grey = HU + 32768 (so -1024 HU is 31744, 0 HU is 32768).
    pixels.resize(voxels.size());
    for (std::size_t i = 0; i < n; ++i) {
      std::int16_t hu;
      std::memcpy(&hu, voxels.data() + 2 * i, 2);
      std::uint16_t v = std::uint16_t(std::int32_t(hu) + 32768);
      std::memcpy(pixels.data() + 2 * i, &v, 2);
    }
    what = "16-bit grey = HU + 32768";
  } else if (type == ChannelType::kRgba8) {
    what = "8-bit RGBA";
  } else {
    what = cat(view.bits, "-bit grey");
  }
  view.pixels = pixels.empty() ? voxels.data() : pixels.data();
  write_image_file(out, view);
  return what;
#else
  throw UsageError(
      cat(out, ": this build has no OpenImageIO; extract a whole channel with -o OUT.nrrd"));
#endif
}

}  // namespace

int main(int argc, char** argv) {
  return run_main("vispack-extract", argc, argv, [](Args& args) {
    args.describe(
        "FILE --channel NAME [--level L] (--z Z -o OUT.png|OUT.tif [--window C:W | --preview] "
        "| -o OUT.nrrd)",
        "Extracts one z slice of a channel as an image (PNG/TIFF; CT as 16-bit HU+32768, exact "
        "but grey in an image viewer, or with --window/--preview as an 8-bit picture through a "
        "display window; uint16 labels as 16-bit, rgba as 8-bit RGBA), or a whole channel as "
        "NRRD with spacing and origin in mm (opens in 3D Slicer, ITK, numpy). Prints one line "
        "naming the file written.");
    const std::string channel =
        args.option("--channel", "NAME", "channel to extract (rgba, ct, labels)").value_or("");
    const long long level =
        args.option_int("--level", "L", "pyramid level (default 0)").value_or(0);
    const auto z = args.option_int("--z", "Z", "slice index for an image output");
    const std::string out =
        args.option("--output", "OUT", "output file (.png, .tif, .tiff or .nrrd)").value_or("");
    const std::string out_short = args.option("-o", "OUT", "same as --output").value_or("");
    const auto window_text = args.option(
        "--window", "C:W",
        "ct image: an 8-bit preview through the window CENTRE:WIDTH in HU (40:400 soft "
        "tissue, 400:1800 bone, -600:1500 lung); without it the exact 16-bit HU + 32768");
    const bool preview = args.flag("--preview", "ct image: an 8-bit preview, window 40:400");
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
    if (window_text && preview) throw UsageError("--preview is --window 40:400: give one of them");
    std::optional<Window> window;
    if (window_text) window = parse_window(*window_text);
    if (preview) window = Window{};
    if (window && channel != "ct")
      throw UsageError(cat("--window and --preview are for the ct channel, not \"", channel, "\""));
    if (window && nrrd)
      throw UsageError("--window and --preview make an 8-bit image; a .nrrd keeps the HU");

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
      std::cout << "wrote " << output << " (" << channel << ", level " << level << ", "
                << li.dims[0] << " x " << li.dims[1] << " x " << li.dims[2] << " voxels)\n";
      return 0;
    }
    if (*z < 0 || *z >= li.dims[2]) {
      throw UsageError(
          cat("--z ", *z, " is outside [0, ", li.dims[2] - 1, "] at level ", level, " of ", file));
    }
    std::vector<std::uint8_t> slice(std::size_t(li.dims[0] * li.dims[1]) *
                                    channel_type_bytes(type));
    r.read_region(*c, int(level), 0, 0, *z, li.dims[0], li.dims[1], 1, slice.data());
    const std::string what = write_slice_image(output, slice, type, li.dims[0], li.dims[1], window);
    std::cout << "wrote " << output << " (" << channel << ", level " << level << ", z " << *z
              << ": " << li.dims[0] << " x " << li.dims[1] << ", " << what << ")\n";
    return 0;
  });
}
