// Slice folders and single slices: listing by file-name pattern, reading and writing images.
//
// Images are OpenCV matrices in RGB(A) channel order (NOT OpenCV's usual BGR): CV_8UC1/3/4 or
// CV_16UC1/3/4. Reading and writing go through OpenImageIO (PNG, TIFF, BMP, JPEG), or through the
// header-less raw layout of NLM Visible Human slices (RawLayout, config.h).
// The lean build (VISPACK_WITH_OPENIMAGEIO=OFF, docs/ARCHITECTURE.md "The lean build") has no
// OpenImageIO: it reads PNG through the own decoder (png_decode.h) and raw slices, and writes PNG
// through the built-in encoder (common/png_encode.h); a TIFF, JPEG, BMP or PNM slice, a PNG the
// own decoder declines, or a .tif/.jpg/.bmp output is refused with an error naming the file and
// saying this build has no OpenImageIO.
// All functions are thread-safe (no shared state); each call opens its own file.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "vispack/pipeline/core/config.h"

namespace vispack::pipeline {

// Largest image edge and byte size read_slice accepts (a guard against decompression bombs and
// hostile headers): images above either are refused with an InputError before any pixel is read
// (a BMP's header is checked before OpenImageIO opens it: its reader decodes RLE inside open()).
inline constexpr int kMaxImageEdge = 65536;
inline constexpr std::uint64_t kMaxImageBytes = std::uint64_t(1) << 31;

// Reads one slice. Colour comes back in RGB order as CV_8UC3 / CV_16UC3 (an alpha channel in the
// file is dropped), grey as CV_8UC1 / CV_16UC1. Images with other bit depths are converted: 1..8
// bit to 8, 9..16 bit (and float) to 16. Without `raw` the file is read through OpenImageIO's
// reader for the format its first bytes name (PNG, TIFF, JPEG, BMP or binary/ASCII PNM, whatever
// the file name says; no other of its readers is tried); with `raw` it is read as a
// header-less raw slice: `header_bytes` skipped, then width*height*channels samples of `bits`
// each, planar or interleaved, in the declared byte order; the file size must be exactly
// header_bytes + that many bytes. With raw.header "genesis" (RawLayout::genesis) the file is a GE
// Genesis image (genesis.h): the samples start where its own header says, and its width, height
// and depth must equal the layout's, else an InputError naming the file, the header field and the
// config key; the file size must be exactly that offset + the samples. Without it, a 16-bit grey
// file that starts with the Genesis magic "IMGF" and whose header puts the samples elsewhere than
// header_bytes is refused the same way (naming both offsets and raw.header).
// Throws InputError naming the file: unreadable, zero bytes, truncated or corrupt, unsupported
// channel count, not one of those formats, a BMP compression that does not fit its bits per pixel,
// raw size mismatch, or larger than kMaxImageEdge / kMaxImageBytes.
cv::Mat read_slice(const std::string& path, const std::optional<RawLayout>& raw = std::nullopt);

// The width and height of a slice from its header alone (no pixels decoded): the raw layout's
// size with `raw`, else the image file's header. Throws InputError naming the file when it
// cannot be opened or its format is not recognised. read_slice validates the rest.
cv::Size read_slice_size(const std::string& path,
                         const std::optional<RawLayout>& raw = std::nullopt);

// Writes an image as PNG, TIFF, JPEG or BMP (by the extension: .png, .tif/.tiff, .jpg/.jpeg, .bmp),
// atomically (temporary file + rename: the path holds the old content or the complete new one).
// `image`: CV_8U or CV_16U with 1, 3 or 4 channels in RGB(A) order (JPEG, BMP: 8-bit, 1 or 3
// channels).
// The bytes are deterministic for the same image and quality (no timestamps, fixed compression
// settings). `jpeg_quality` is 1..100, `png_level` the zlib level 0..9 of a PNG. Throws IoError
// naming the path (cannot write, unsupported extension or pixel type).
void write_image(const std::string& path, const cv::Mat& image, int jpeg_quality = 90,
                 int png_level = 4);

// What a work-folder image shows, which picks its PNG encoding (vispack::PngEncoding).
enum class WorkImageContent {
  kRegions,  // masks, label slices, resampled CT: long runs of one value (Up + run-length zlib)
  kPicture,  // pictures of the colour (mask overlays): few runs (Up + Huffman-only zlib)
};

// Writes a per-slice work-folder image (mask, overlay, label slice, resampled CT, QC picture;
// not the registered colour copy, which stays at write_image's level 4) encoded for speed: a PNG at
// zlib level 1 with the Up row filter and, by `content`, zlib's run-length strategy
// (PngEncoding::kUpRuns) or its Huffman-only one (kUpHuffman); other extensions as write_image.
// At 2048x1216 the run-length choice took the streaming pass (mask + labels + pack) from 0.181 to
// 0.131 CPU-s per slice, and the mask and label PNGs shrink to less than half (docs/PERF_HISTORY.md
// "Work-folder PNGs"); Huffman-only encodes a mask overlay faster at the same size
// (docs/BENCHMARKS.md "The streaming pass: overlay PNGs and CT slices decoded once"). Lossless;
// deterministic bytes; throws IoError naming the path.
void write_work_image(const std::string& path, const cv::Mat& image,
                      WorkImageContent content = WorkImageContent::kRegions);

// Writes a header-less raw slice in `layout` (planar or interleaved, 8 or 16 bit, byte order;
// `header_bytes` zero bytes first), atomically. The image must match layout.width/height/channels
// and its depth must match layout.bits (CV_8U for 8, CV_16U for 16). Throws IoError naming the
// path.
void write_raw_slice(const std::string& path, const cv::Mat& image, const RawLayout& layout);

}  // namespace vispack::pipeline
