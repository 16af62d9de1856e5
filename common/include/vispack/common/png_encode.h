// A small PNG encoder with no image library: the rows filtered with PNG's Up filter, compressed
// into one zlib stream by libdeflate, and wrapped in the three chunks a PNG needs (IHDR, IDAT,
// IEND). Library `vispack_png_encode` (libdeflate only), built in every configuration: the lean
// build (VISPACK_WITH_OPENIMAGEIO=OFF, docs/ARCHITECTURE.md "The lean build") writes every PNG
// through it; the default build writes PNGs through OpenImageIO and tests this encoder against
// OpenImageIO's reader and the slice reader's own decoder (tests/pipeline/test_png_encode.cpp).
//
// What it writes: 8- or 16-bit samples, grey (colour type 0), RGB (2) or RGBA (6, straight
// alpha, the samples stored as given), not interlaced; 16-bit samples big-endian as PNG requires
// (the caller's are native endian). No other chunk: no time stamp, gamma or text, so the same
// image and level give the same bytes. Every row is stored with filter type 2 (Up: each byte
// minus the byte above it): one subtraction a byte, no per-row search, and on slices (photos,
// CT, masks, label slices), whose rows resemble the row above, it leaves long runs of zeros for
// the compressor. The IDAT data is split into chunks of at most 1 MiB.
// Pure and thread-safe (no shared state).
#pragma once

#include <vector>

#include "vispack/common/image_io.h"

namespace vispack {

// The PNG file of `image` (ImageView: width x height, 1, 3 or 4 channels of 8 or 16 bits in
// native byte order, rows row_bytes apart), its zlib stream at libdeflate's `level` (0: stored,
// no compression; 1 fastest .. 12 smallest). Throws std::invalid_argument for an image or level
// outside those (the caller, write_image_file, checks them first and names the file), and
// std::bad_alloc when the encoded image does not fit in memory.
std::vector<unsigned char> encode_png(const ImageView& image, int level);

}  // namespace vispack
