#include "vispack/pipeline/imaging/slice_io.h"

#ifdef VISPACK_HAVE_OPENIMAGEIO
#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#endif

#include <algorithm>
#include <cctype>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <memory>
#include <system_error>
#include <utility>
#include <vector>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"
#include "vispack/common/image_io.h"
#include "vispack/pipeline/imaging/genesis.h"
#include "vispack/pipeline/imaging/png_decode.h"

namespace vispack::pipeline {
namespace {

namespace fs = std::filesystem;

// Size guard shared by the OIIO and raw readers.
void check_size(const std::string& path, std::int64_t width, std::int64_t height,
                std::int64_t channels, std::int64_t bytes_per_sample) {
  if (width <= 0 || height <= 0) {
    throw InputError(cat(path, ": invalid image size ", width, "x", height));
  }
  if (width > kMaxImageEdge || height > kMaxImageEdge) {
    throw InputError(cat(path, ": image of ", width, "x", height, " pixels exceeds the limit of ",
                         kMaxImageEdge, " pixels a side"));
  }
  const auto bytes = std::uint64_t(width) * std::uint64_t(height) * std::uint64_t(channels) *
                     std::uint64_t(bytes_per_sample);
  if (bytes > kMaxImageBytes) {
    throw InputError(cat(path, ": image of ", width, "x", height, "x", channels, " needs ", bytes,
                         " bytes, over the limit of ", kMaxImageBytes, " bytes"));
  }
}

cv::Mat read_raw(const std::string& path, const RawLayout& raw, std::uint64_t file_size) {
  if (raw.channels != 1 && raw.channels != 3) {
    throw InputError(cat(path, ": raw layout with ", raw.channels, " channels (1 or 3 supported)"));
  }
  if (raw.bits != 8 && raw.bits != 16) {
    throw InputError(cat(path, ": raw layout with ", raw.bits, " bits (8 or 16 supported)"));
  }
  const int bytes_per_sample = raw.bits / 8;
  check_size(path, raw.width, raw.height, raw.channels, bytes_per_sample);
  const std::uint64_t pixels = std::uint64_t(raw.width) * std::uint64_t(raw.height);
  const std::uint64_t sample_bytes = pixels * raw.channels * bytes_per_sample;
  // Where the samples start: header_bytes, or with raw.header "genesis" the file's own header
  // (genesis.h), checked against the config before the size is.
  std::uint64_t header = raw.header_bytes;
  std::string bytes;
  if (raw.genesis) {
    if (file_size > sample_bytes + (std::uint64_t(1) << 20))
      throw InputError(cat(path, ": raw slice has ", file_size, " bytes, over the ", sample_bytes,
                           " of its samples plus 1 MiB of GE Genesis header"));
    bytes = read_file(path, std::size_t(file_size) + 1);
    const GenesisHeader g = parse_genesis_header(path, bytes, bytes.size());
    auto disagree = [&](const char* field, std::int64_t value, const char* key, int configured) {
      if (value != configured)
        throw InputError(cat(path, ": GE Genesis header field ", field, " is ", value,
                             ", the config's raw.", key, " is ", configured));
    };
    disagree("width", g.width, "width", raw.width);
    disagree("height", g.height, "height", raw.height);
    disagree("depth", g.bits, "bits", raw.bits);
    if (raw.genesis_pixel_mm) check_genesis_pixel_size(path, bytes, g, *raw.genesis_pixel_mm);
    header = std::uint64_t(g.pixel_offset);
  } else if (file_size == header + sample_bytes) {
    bytes = read_file(path, std::size_t(file_size) + 1);
  } else if (file_size >= kGenesisFixedBytes) {
    bytes.assign(kGenesisFixedBytes, '\0');  // the size check below refuses it: the head alone
    std::ifstream in(path, std::ios::binary);
    if (!in.read(bytes.data(), std::streamsize(bytes.size()))) bytes.clear();
  }
  if (!raw.genesis) {
    // A GE Genesis image read with a fixed header_bytes: its own header says where the samples
    // start; a header_bytes that differs would read header bytes as pixels (or skip pixels).
    if (raw.channels == 1 && raw.bits == 16 && bytes.size() >= kGenesisFixedBytes &&
        has_genesis_magic(bytes)) {
      const GenesisHeader g = parse_genesis_header(path, bytes, file_size);
      if (std::uint64_t(g.pixel_offset) != raw.header_bytes)
        throw InputError(cat(path,
                             ": a GE Genesis image (magic IMGF) whose header puts the "
                             "pixels at byte ",
                             g.pixel_offset, ", but raw.header_bytes is ", raw.header_bytes,
                             "; set raw.header to \"genesis\""));
    }
  }
  const std::uint64_t expected = header + sample_bytes;
  if (file_size != expected) {
    throw InputError(cat(path, ": raw slice has ", file_size, " bytes, expected ", expected, " (",
                         raw.width, "x", raw.height, "x", raw.channels, " at ", raw.bits,
                         " bit, header ", header, " bytes",
                         raw.genesis ? " by its GE Genesis header" : "", ")"));
  }
  if (bytes.size() != expected) {
    throw InputError(cat(path, ": raw slice changed size while reading (", bytes.size(),
                         " bytes, expected ", expected, ")"));
  }
  const auto* data = reinterpret_cast<const std::uint8_t*>(bytes.data()) + header;
  const int type = CV_MAKETYPE(raw.bits == 8 ? CV_8U : CV_16U, raw.channels);
  cv::Mat image(raw.height, raw.width, type);
  const int channels = raw.channels;
  if (bytes_per_sample == 1) {
    // 8 bit (NLM's planar colour): whole planes, no per-sample work.
    if (channels == 1 || !raw.planar) {
      std::memcpy(image.data, data, pixels * channels);
    } else {
      std::vector<cv::Mat> planes;
      for (int c = 0; c < channels; ++c)
        planes.emplace_back(raw.height, raw.width, CV_8UC1,
                            const_cast<std::uint8_t*>(data) + c * pixels);
      cv::merge(planes, image);
    }
    return image;
  }
  const bool swap = raw.bits == 16 && raw.big_endian;
  auto sample = [&](std::uint64_t i) -> std::uint16_t {
    if (bytes_per_sample == 1) return data[i];
    const std::uint8_t lo = data[2 * i], hi = data[2 * i + 1];
    return swap ? std::uint16_t(lo << 8 | hi) : std::uint16_t(hi << 8 | lo);
  };
  for (int y = 0; y < raw.height; ++y) {
    for (int x = 0; x < raw.width; ++x) {
      const std::uint64_t pixel = std::uint64_t(y) * raw.width + x;
      for (int c = 0; c < channels; ++c) {
        const std::uint64_t i = raw.planar ? c * pixels + pixel : pixel * channels + c;
        const std::uint16_t v = sample(i);
        if (bytes_per_sample == 1) {
          image.ptr<std::uint8_t>(y)[x * channels + c] = static_cast<std::uint8_t>(v);
        } else {
          image.ptr<std::uint16_t>(y)[x * channels + c] = v;
        }
      }
    }
  }
  return image;
}

#ifdef VISPACK_HAVE_OPENIMAGEIO
// OpenImageIO error texts span several lines ("Read error...\nPNG library error"); errors are
// one line (docs/RELIABILITY.md), so the lines are joined with "; ".
std::string one_line(std::string text) {
  while (!text.empty() && (text.back() == '\n' || text.back() == '\r'))
    text.pop_back();
  std::string out;
  for (char c : text) {
    if (c == '\n') {
      out += "; ";
    } else if (c != '\r') {
      out += c;
    }
  }
  return out;
}
#endif

// A PNG must hold its chunks up to IEND within the file. Checked before libpng sees the file:
// libpng reports a truncated stream by printing "libpng error: ..." to stderr itself, which
// would break the one-line error rule (docs/RELIABILITY.md). Reads 8 bytes per chunk.
void check_png_complete(const std::string& path, std::uint64_t size) {
  std::ifstream in(path, std::ios::binary);
  unsigned char head[8];
  if (!in.read(reinterpret_cast<char*>(head), 8)) return;
  static const unsigned char kSignature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  if (std::memcmp(head, kSignature, 8) != 0) return;  // not a PNG
  std::uint64_t at = 8;
  while (at + 12 <= size) {
    in.seekg(std::streamoff(at));
    if (!in.read(reinterpret_cast<char*>(head), 8)) break;
    const std::uint64_t length = (std::uint64_t(head[0]) << 24) | (std::uint64_t(head[1]) << 16) |
                                 (std::uint64_t(head[2]) << 8) | head[3];
    if (std::memcmp(head + 4, "IEND", 4) == 0) return;
    at += 12 + length;
  }
  throw InputError(cat(path, ": PNG is truncated (", size, " bytes, chunks end without IEND)"));
}

#ifdef VISPACK_HAVE_OPENIMAGEIO
// A BMP's header, checked before OpenImageIO opens the file. OpenImageIO 2.4's BMP reader trusts
// its header (both found by fuzz_raw_slice):
// - it decodes a run-length-encoded image inside open(), sized by the header's width and height,
//   so a hostile header made it allocate (or throw std::length_error out of) gigabytes before any
//   size could be checked;
// - it runs a run-length-encoded image through the colour table whatever the header's bits per
//   pixel, so run-length encoding at 24 bits per pixel (no colour table) read from an empty table:
//   a segmentation fault.
// So the size must fit the limits, the bits per pixel must be one BMP defines, and a compression
// must be one BMP defines for those bits (RLE8 at 8, RLE4 at 4, bit fields at 16 or 32); JPEG or
// PNG inside a BMP are refused too (the reader would show their bytes as pixels). Reads 34 bytes.
void check_bmp_header(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  unsigned char h[34] = {};
  in.read(reinterpret_cast<char*>(h), sizeof h);
  const std::streamsize got = in.gcount();
  if (got < 2 || h[0] != 'B' || h[1] != 'M') return;  // not a BMP
  auto truncated = [&] {
    return InputError(cat(path, ": BMP header is truncated (", got, " bytes)"));
  };
  if (got < 26) throw truncated();
  auto u16 = [&](int at) { return std::uint32_t(h[at]) | std::uint32_t(h[at + 1]) << 8; };
  auto u32 = [&](int at) { return u16(at) | u16(at + 2) << 16; };
  const std::uint32_t dib = u32(14);
  std::int64_t width = 0, height = 0;
  std::uint32_t bits = 0, compression = 0;
  if (dib == 12) {  // BITMAPCOREHEADER: 16-bit sizes, no compression
    width = u16(18);
    height = u16(20);
    bits = u16(24);
  } else {
    if (got < 34) throw truncated();
    width = std::int32_t(u32(18));
    height = std::int32_t(u32(22));
    if (height < 0) height = -height;  // top-down rows
    bits = u16(28);
    compression = u32(30);
  }
  check_size(path, width, height, 4, 1);
  if (bits != 1 && bits != 4 && bits != 8 && bits != 16 && bits != 24 && bits != 32) {
    throw InputError(
        cat(path, ": BMP with ", bits, " bits per pixel (1, 4, 8, 16, 24 or 32 supported)"));
  }
  const bool fits = compression == 0 || (compression == 1 && bits == 8) ||
                    (compression == 2 && bits == 4) ||
                    (compression == 3 && (bits == 16 || bits == 32));
  if (!fits) {
    static const char* const kNames[] = {"none", "RLE8", "RLE4", "bit fields", "JPEG", "PNG"};
    const std::string name = compression < 6 ? kNames[compression] : "unknown";
    throw InputError(cat(path, ": BMP compression ", compression, " (", name, ") at ", bits,
                         " bits per pixel is not supported (none; RLE8 at 8, RLE4 at 4 or bit "
                         "fields at 16 or 32 bits per pixel)"));
  }
}

// OpenImageIO's readers can throw C++ exceptions of their own (std::length_error, bad_alloc)
// on hostile files; they become InputError naming the file (docs/RELIABILITY.md: one line, the file
// named).
template <class F>
auto guard_decoder(const std::string& path, F&& f) -> decltype(f()) {
  try {
    return f();
  } catch (const Error&) {
    throw;
  } catch (const std::exception& e) {
    throw InputError(cat(path, ": cannot read image (the decoder failed: ", e.what(), ")"));
  }
}
#endif

// The image formats a slice may be in, told by the file's first bytes (the name may say anything).
// OpenImageIO, asked to open a file, tries every reader it has when the one the name points to
// refuses it (Targa, PSD, RLA, DDS, ... about thirty, by content): each one more decoder for a
// corrupt or hostile file to reach. vispack opens a slice with the one reader its bytes name.
struct SliceFormat {
  const char* reader;  // OpenImageIO's format name
  const char* name;    // for messages
  bool is(const char* other) const { return std::strcmp(reader, other) == 0; }
};

SliceFormat sniff_format(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(cat(path, ": cannot read slice: cannot open the file"));
  unsigned char h[8] = {};
  in.read(reinterpret_cast<char*>(h), sizeof h);
  const std::streamsize got = in.gcount();
  if (got == 0) throw InputError(cat(path, ": slice file is empty (0 bytes)"));
  auto starts = [&](std::initializer_list<unsigned char> magic) {
    return got >= std::streamsize(magic.size()) && std::equal(magic.begin(), magic.end(), h);
  };
  if (starts({0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'})) return {"png", "PNG"};
  if (starts({'I', 'I', 42, 0}) || starts({'M', 'M', 0, 42}) || starts({'I', 'I', 43, 0}) ||
      starts({'M', 'M', 0, 43}))
    return {"tiff", "TIFF"};
  if (starts({0xff, 0xd8, 0xff})) return {"jpeg", "JPEG"};
  if (starts({'B', 'M'})) return {"bmp", "BMP"};
  if (got >= 2 && h[0] == 'P' && h[1] >= '1' && h[1] <= '6') return {"pnm", "PNM"};
  std::string first;
  for (std::streamsize i = 0; i < got; ++i) {
    static const char* const kHex = "0123456789abcdef";
    first += cat(i ? " " : "", kHex[h[i] >> 4], kHex[h[i] & 15]);
  }
  throw InputError(cat(path, ": cannot read slice: not a PNG, TIFF, JPEG, BMP or PNM image (first ",
                       "bytes ", first, "); header-less slices need the config's \"raw\" layout"));
}

#ifdef VISPACK_HAVE_OPENIMAGEIO
std::unique_ptr<OIIO::ImageInput> open_oiio(const std::string& path, const SliceFormat& format,
                                            bool bmp_grey_as_rgb) {
  OIIO::ImageSpec config;
  config.attribute("oiio:UnassociatedAlpha", 1);  // keep colour as stored next to an alpha
  if (bmp_grey_as_rgb) config.attribute("bmp:monochrome_detect", 0);
  auto input = OIIO::ImageInput::create(format.reader);
  if (!input) {
    throw InputError(cat(path, ": cannot read ", format.name,
                         " images: OpenImageIO has no reader for them (",
                         one_line(OIIO::geterror()), ")"));
  }
  OIIO::ImageSpec spec;
  if (!input->open(path, spec, config)) {
    std::string why = one_line(input->geterror());
    if (why.empty()) why = one_line(OIIO::geterror());
    if (why.empty()) why = "the reader refused it";
    throw InputError(cat(path, ": cannot read ", format.name, " image: ", why));
  }
  return input;
}

// OpenImageIO 2.4 shows an 8-bit BMP whose colour table is all grey as one channel, but for a
// run-length-encoded one it still writes three bytes per pixel: past the end of the caller's
// buffer (a heap overflow, found while checking fuzz_raw_slice's BMP finding). Such a file is
// opened again as RGB and its first channel kept: the same grey image, in the caller's bounds.
bool is_grey_run_length_bmp(OIIO::ImageInput& input) {
  if (std::strcmp(input.format_name(), "bmp") != 0 || input.spec().nchannels != 1) return false;
  const std::string compression = input.spec().get_string_attribute("compression");
  return compression == "rle8" || compression == "rle4";
}

cv::Mat read_oiio_unguarded(const std::string& path, const SliceFormat& format) {
  auto input = open_oiio(path, format, false);
  bool keep_first_channel = false;
  if (is_grey_run_length_bmp(*input)) {
    input->close();
    input = open_oiio(path, format, true);
    keep_first_channel = true;
  }
  const OIIO::ImageSpec& spec = input->spec();
  if (spec.depth > 1) {
    throw InputError(cat(path, ": volume images (depth ", spec.depth, ") are not slices"));
  }
  const int file_channels = spec.nchannels;
  int channels = 0;
  if (file_channels == 1 || file_channels == 2 || keep_first_channel) {
    channels = 1;  // grey (+ alpha, dropped; or a grey BMP read as RGB)
  } else if (file_channels == 3 || file_channels == 4) {
    channels = 3;  // RGB (+ alpha, dropped)
  } else {
    throw InputError(cat(path, ": image with ", file_channels, " channels (1 to 4 supported)"));
  }
  const bool eight_bit =
      spec.format.basetype == OIIO::TypeDesc::UINT8 || spec.format.basetype == OIIO::TypeDesc::INT8;
  const OIIO::TypeDesc want = eight_bit ? OIIO::TypeDesc::UINT8 : OIIO::TypeDesc::UINT16;
  check_size(path, spec.width, spec.height, file_channels, 4);
  cv::Mat image(spec.height, spec.width, CV_MAKETYPE(eight_bit ? CV_8U : CV_16U, channels));
  // Scanline files whose samples are already what we keep are read straight into `image` (or,
  // with an alpha to drop, into a same-type buffer of every channel): OpenImageIO 2.4's
  // read_image stages them through a ~64 MB buffer of its own, allocated and freed (mmap'd,
  // above glibc's mmap threshold) for every slice, so each slice faulted in fresh pages.
  const bool native = spec.format == want && spec.channelformats.empty() && spec.tile_width == 0;
  bool ok = false;
  if (native && file_channels == channels) {
    ok = input->read_native_scanlines(0, 0, spec.y, spec.y + spec.height, 0, image.data);
  } else if (native) {
    cv::Mat all(spec.height, spec.width, CV_MAKETYPE(image.depth(), file_channels));
    ok = input->read_native_scanlines(0, 0, spec.y, spec.y + spec.height, 0, all.data);
    if (ok) {
      const int pairs[] = {0, 0, 1, 1, 2, 2};  // colour (or grey) kept, alpha dropped
      cv::mixChannels(&all, 1, &image, 1, pairs, std::size_t(channels));
    }
  } else {
    ok = input->read_image(0, 0, 0, channels, want, image.data);
  }
  if (!ok) {
    std::string why = one_line(input->geterror());
    if (why.empty()) why = "read failed";
    throw InputError(cat(path, ": cannot read image (truncated or corrupt?): ", why));
  }
  // Some decoders report a truncated stream only through the error buffer.
  if (input->has_error()) {
    throw InputError(cat(path, ": image is truncated or corrupt: ", one_line(input->geterror())));
  }
  input->close();
  return image;
}
#else
// The lean build (VISPACK_WITH_OPENIMAGEIO=OFF, docs/ARCHITECTURE.md "The lean build"): a slice
// the own PNG decoder cannot read.
[[noreturn]] void refuse_without_oiio(const std::string& path, const SliceFormat& format) {
  if (format.is("png"))
    throw InputError(cat(path,
                         ": cannot read PNG slice: this build has no OpenImageIO "
                         "(VISPACK_WITH_OPENIMAGEIO=OFF) and its own PNG decoder reads only "
                         "well-formed 8/16-bit grey, grey+alpha, RGB or RGBA PNGs, not "
                         "interlaced, without a tRNS chunk, within ",
                         kMaxImageEdge, " pixels a side and ", kMaxImageBytes, " bytes"));
  throw InputError(cat(path, ": cannot read ", format.name,
                       " slice: this build has no OpenImageIO (VISPACK_WITH_OPENIMAGEIO=OFF); it "
                       "reads PNG and raw slices only"));
}

// The size in a PNG's IHDR chunk (the first chunk: bytes 8..32 of the file).
cv::Size png_header_size(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  unsigned char h[24] = {};
  if (!in.read(reinterpret_cast<char*>(h), sizeof h) || std::memcmp(h + 12, "IHDR", 4) != 0)
    throw InputError(cat(path, ": PNG does not start with its IHDR chunk"));
  auto be32 = [&](int at) {
    return std::uint32_t(h[at]) << 24 | std::uint32_t(h[at + 1]) << 16 |
           std::uint32_t(h[at + 2]) << 8 | std::uint32_t(h[at + 3]);
  };
  const std::uint32_t width = be32(16), height = be32(20);
  if (width == 0 || height == 0 || width > std::uint32_t(kMaxImageEdge) ||
      height > std::uint32_t(kMaxImageEdge))
    throw InputError(cat(path, ": PNG header gives ", width, "x", height, " pixels (1 to ",
                         kMaxImageEdge, " a side)"));
  return {int(width), int(height)};
}
#endif

}  // namespace

cv::Mat read_slice(const std::string& path, const std::optional<RawLayout>& raw) {
  std::error_code ec;
  const auto status = fs::status(path, ec);
  if (ec || !fs::exists(status)) {
    throw InputError(cat(path, ": cannot read slice: file does not exist"));
  }
  if (!fs::is_regular_file(status)) {
    throw InputError(cat(path, ": cannot read slice: not a regular file"));
  }
  const std::uint64_t size = fs::file_size(path, ec);
  if (ec) throw InputError(cat(path, ": cannot read slice: ", ec.message()));
  if (size == 0) throw InputError(cat(path, ": slice file is empty (0 bytes)"));
  if (raw) return read_raw(path, *raw, size);
  const SliceFormat format = sniff_format(path);
  if (format.is("png")) {
    check_png_complete(path, size);
    // Plain PNGs (colour and CT slices) by libdeflate; the rest, and any file it declines as
    // not well formed, through OpenImageIO (png_decode.h).
    if (size <= kMaxImageBytes) {
      if (auto image = decode_plain_png(read_file(path), kMaxImageEdge, kMaxImageBytes))
        return std::move(*image);
    }
  }
#ifdef VISPACK_HAVE_OPENIMAGEIO
  if (format.is("bmp")) check_bmp_header(path);
  return guard_decoder(path, [&] { return read_oiio_unguarded(path, format); });
#else
  refuse_without_oiio(path, format);
#endif
}

cv::Size read_slice_size(const std::string& path, const std::optional<RawLayout>& raw) {
  if (raw) return {raw->width, raw->height};
  const SliceFormat format = sniff_format(path);
#ifdef VISPACK_HAVE_OPENIMAGEIO
  if (format.is("bmp")) check_bmp_header(path);
  return guard_decoder(path, [&] {
    auto input = open_oiio(path, format, false);
    const cv::Size size(input->spec().width, input->spec().height);
    input->close();
    return size;
  });
#else
  if (format.is("png")) return png_header_size(path);
  refuse_without_oiio(path, format);
#endif
}

namespace {

ImageView view_of(const std::string& path, const cv::Mat& image) {
  if (image.empty() || image.dims != 2) throw IoError(cat(path, ": cannot write an empty image"));
  const int depth = image.depth();
  if (depth != CV_8U && depth != CV_16U) {
    throw IoError(
        cat(path, ": cannot write image: pixel type must be 8 or 16 bit (got depth ", depth, ")"));
  }
  ImageView view;
  view.width = image.cols;
  view.height = image.rows;
  view.channels = image.channels();
  view.bits = depth == CV_8U ? 8 : 16;
  view.pixels = image.data;
  view.row_bytes = image.step[0];
  return view;
}

}  // namespace

void write_work_image(const std::string& path, const cv::Mat& image, WorkImageContent content) {
  ImageWriteOptions options;
  options.png_level = 1;
  options.png_encoding =
      content == WorkImageContent::kPicture ? PngEncoding::kUpHuffman : PngEncoding::kUpRuns;
  write_image_file(path, view_of(path, image), options);
}

void write_image(const std::string& path, const cv::Mat& image, int jpeg_quality, int png_level) {
  ImageWriteOptions options;
  options.jpeg_quality = jpeg_quality;
  options.png_level = png_level;
  write_image_file(path, view_of(path, image), options);
}

void write_raw_slice(const std::string& path, const cv::Mat& image, const RawLayout& layout) {
  if (image.cols != layout.width || image.rows != layout.height ||
      image.channels() != layout.channels) {
    throw IoError(cat(path, ": cannot write raw slice: image is ", image.cols, "x", image.rows, "x",
                      image.channels(), ", layout says ", layout.width, "x", layout.height, "x",
                      layout.channels));
  }
  const int want_depth = layout.bits == 8 ? CV_8U : layout.bits == 16 ? CV_16U : -1;
  if (image.depth() != want_depth) {
    throw IoError(
        cat(path, ": cannot write raw slice: image depth does not match ", layout.bits, " bit"));
  }
  const int bytes_per_sample = layout.bits / 8;
  const int channels = layout.channels;
  const std::uint64_t pixels = std::uint64_t(layout.width) * std::uint64_t(layout.height);
  std::vector<std::uint8_t> bytes(layout.header_bytes + pixels * channels * bytes_per_sample, 0);
  std::uint8_t* data = bytes.data() + layout.header_bytes;
  for (int y = 0; y < layout.height; ++y) {
    for (int x = 0; x < layout.width; ++x) {
      const std::uint64_t pixel = std::uint64_t(y) * layout.width + x;
      for (int c = 0; c < channels; ++c) {
        const std::uint64_t i = layout.planar ? c * pixels + pixel : pixel * channels + c;
        if (bytes_per_sample == 1) {
          data[i] = image.ptr<std::uint8_t>(y)[x * channels + c];
        } else {
          const std::uint16_t v = image.ptr<std::uint16_t>(y)[x * channels + c];
          const std::uint8_t hi = std::uint8_t(v >> 8), lo = std::uint8_t(v & 0xff);
          data[2 * i] = layout.big_endian ? hi : lo;
          data[2 * i + 1] = layout.big_endian ? lo : hi;
        }
      }
    }
  }
  write_file_atomic(path, bytes.data(), bytes.size());
}

}  // namespace vispack::pipeline
