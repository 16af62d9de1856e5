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
  int letter = -1;   // with {n}{a}: the letter after the number, 0 = 'a' .. 25 = 'z'; else -1
  // Colour slices only: the slice's place along z in colour slice spacings from the stack's first
  // file, from its file number (and letter): slice_z.h place_colour_slices, set by stack_slices
  // (work_layout.h). z = slot · spacing_mm[2]. −1 where nothing placed it (list_slices).
  int slot = -1;
};

// Files of a SliceSource whose names match its pattern ({n} = one or more decimal digits),
// sorted by that number (so rgb_2 comes before rgb_10). A pattern may follow {n} with {a}: one
// letter a..z (either case) after the number, ordering the files of one number (the NLM female's
// avf1001a, avf1001b, avf1001c: pattern "avf{n}{a}.raw"; sorted by number, then letter).
// Sub-folders and non-matching names are ignored. Throws ConfigError naming the folder and the
// pattern when the folder is missing, the pattern has no {n} (or an {a} not right after it), or
// nothing matches; ConfigError naming both files when two files carry the same number (and
// letter) (e.g. rgb_7.png and rgb_007.png).
std::vector<SliceFile> list_slices(const SliceSource& source);

}  // namespace vispack::pipeline
