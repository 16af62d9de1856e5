// The two entry points every fuzz target source defines.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

// libFuzzer's entry point: must never crash, hang or read out of bounds, whatever `data` holds.
// Errors that the code reports (vispack::Error, std::out_of_range, std::invalid_argument) are fine.
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size);

// Writes the seed corpus (valid inputs and near-misses) into the existing folder `dir`.
void vispack_fuzz_write_seeds(const std::string& dir);
