// A fast decoder for the plain PNGs vispack reads most (colour and CT slices: 8- or 16-bit grey,
// grey + alpha, RGB or RGBA, not interlaced): the whole zlib stream inflated at once by libdeflate
// (about twice as fast as zlib's streaming inflate through libpng, which was a fifth of the
// register stage's CPU on PNG stacks: docs/BENCHMARKS.md "Register stage: CPU per slice"), then
// the rows unfiltered. Every other PNG (palette, 1/2/4-bit, interlaced), and every file that is
// not exactly well formed (a chunk CRC, the stream's Adler-32, its length, a filter type), is
// declined: the caller reads it through OpenImageIO, which decodes what it can and reports what is
// wrong as before (the lean build, which has no OpenImageIO, refuses it naming the file:
// slice_io.h). What it returns is what slice_io.h read_slice returns for the same file through
// OpenImageIO: the same type, the alpha channel dropped, 16-bit samples in native byte order
// (tests/pipeline/test_png_decode.cpp compares the two).
// Pure and thread-safe (no shared state).
#pragma once

#include <cstdint>
#include <optional>
#include <string_view>

#include <opencv2/core.hpp>

namespace vispack::pipeline {

// The image of the PNG file `bytes` (the whole file) as CV_8UC1 / CV_8UC3 / CV_16UC1 /
// CV_16UC3 in RGB order, or nullopt when the file is not one this decoder handles (above), not
// valid, or larger than `max_edge` pixels a side or `max_bytes` (counted as read_slice's guard
// counts them: 4 bytes a sample, alpha included).
std::optional<cv::Mat> decode_plain_png(std::string_view bytes, int max_edge,
                                        std::uint64_t max_bytes);

}  // namespace vispack::pipeline
