// The one image writer of the project: PNG, TIFF, JPEG or BMP by the file's extension, through
// OpenImageIO, encoded in memory and written atomically (AtomicFile: the file appears complete
// or not at all). Used by the pipeline's intermediates (pipeline/imaging/slice_io.h wraps it for
// cv::Mat), vispack-extract and the viewer's screenshots. Library `vispack_image_io`, built
// where OpenImageIO is found; it does not pull OpenImageIO into vispack_common. In the lean
// build (VISPACK_WITH_OPENIMAGEIO=OFF, docs/ARCHITECTURE.md "The lean build") it is built
// without OpenImageIO and writes PNG only, through the built-in encoder (png_encode.h); a .tif,
// .jpg or .bmp path is refused with an IoError naming it.
// Thread-safe: no shared state (OpenImageIO's writers are independent objects).
#pragma once

#include <cstddef>
#include <string>

namespace vispack {

// Pixels to write: `channels` interleaved samples of `bits` (8 or 16, native endian) per pixel,
// row 0 at the top, rows `row_bytes` apart. Not owned.
struct ImageView {
  int width = 0, height = 0;
  int channels = 0;  // 1 (grey), 3 (RGB) or 4 (RGBA, straight alpha)
  int bits = 8;      // 8 or 16
  const void* pixels = nullptr;
  std::size_t row_bytes = 0;  // 0: width * channels * bits / 8
};

// How a PNG is encoded (fixed settings, so the bytes are deterministic).
enum class PngEncoding {
  kAdaptive,  // libpng's adaptive choice among five row filters, zlib's default strategy
  // One row filter (Up) and zlib's run-length strategy. For masks, label slices and CT copies
  // (long runs of one value) this encodes ~3x faster than kAdaptive and gives smaller files
  // (measured by hand at 2048x1216: mask 20 -> 8 kB, label slice 48 -> 22 kB; docs/PERF_HISTORY.md
  // "Work-folder PNGs").
  kUpRuns,
  // One row filter (Up) and zlib's Huffman-only strategy: no search for repeats. For pictures of
  // the colour (mask overlays), where a run-length search finds little: ~15 % less CPU at the
  // same size (1024x608 overlay: 757 -> 754 kB; docs/BENCHMARKS.md "The streaming pass: overlay
  // PNGs and CT slices decoded once"). A flat image gains nothing: a byte costs at least a bit.
  kUpHuffman,
};

struct ImageWriteOptions {
  int jpeg_quality = 90;  // 1..100, JPEG only
  int png_level = 4;      // zlib level 0..9, PNG only (fixed, so the bytes are deterministic)
  PngEncoding png_encoding = PngEncoding::kAdaptive;  // PNG only
};

// Writes `image` to `path`; the format follows the extension (.png, .tif/.tiff (zip), .jpg/.jpeg,
// .bmp; JPEG and BMP take 8-bit grey or RGB only). Throws IoError naming the path: unsupported
// extension or pixel layout, encoder failure, or the file cannot be written.
void write_image_file(const std::string& path, const ImageView& image,
                      const ImageWriteOptions& options = {});

}  // namespace vispack
