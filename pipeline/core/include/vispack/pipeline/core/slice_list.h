// A slice folder's files by number: the listing every stage starts from. Reads no image (a tool
// that only lists folders, vispack-merge, links no image library).
// Thread-safe: no shared state; each call reads the directory once.
#pragma once

#include <string>
#include <vector>

#include "vispack/pipeline/core/config.h"

namespace vispack::pipeline {

struct SliceFile {
  int number;        // the number parsed from the file name where the pattern has {n}
  std::string path;  // absolute (source.dir + "/" + file name)
};

// Files of a SliceSource whose names match its pattern ({n} = one or more decimal digits),
// sorted by that number (so rgb_2 comes before rgb_10). Sub-folders and non-matching names are
// ignored. Throws ConfigError naming the folder and the pattern when the folder is missing, the
// pattern has no {n}, or nothing matches; ConfigError naming both files when two files carry the
// same number (e.g. rgb_7.png and rgb_007.png).
std::vector<SliceFile> list_slices(const SliceSource& source);

}  // namespace vispack::pipeline
