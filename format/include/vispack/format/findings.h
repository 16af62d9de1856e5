// Numbered findings of the packed-file verifier (format/FINDINGS.md holds the table; the
// numbers are stable: a number is never reused for another kind of defect).
//
// A finding is one defect of one kind at one place: the kind's number, the brick it concerns
// (level, channel, brick x/y/z) when there is one, and a one-line detail. Reader::open stops at
// the first structural defect (kinds 1..7: nothing after it can be trusted) and throws it as a
// FileDefect; Reader::check() lists every defect of kinds 8..12 of an opened file.
// Plain values; FileDefect is an exception type (thread-safe like any value).
#pragma once

#include <array>
#include <cstdint>
#include <string>

#include "vispack/common/error.h"

namespace vispack::format {

enum class DefectKind : int {
  kNotVispack = 1,          // bad or damaged magic
  kUnsupportedVersion = 2,  // version_major newer than the reader's, or 0
  kSizeMismatch = 3,        // file shorter or longer than the header says
  kHeaderField = 4,         // a header field out of range or inconsistent with the layout
  kTableChecksum = 5,       // table_checksum differs (header, metadata, index, label IDs)
  kMetadata = 6,            // metadata JSON malformed, a key missing or out of range
  kIndexEntry = 7,          // an index entry inconsistent (position, codec, bounds, overlap, ...)
  kPayloadChecksum = 8,     // a brick payload's xxh64 differs from the index
  kPayloadDecode = 9,       // a payload does not decode to exactly one brick (--deep)
  kBrickRange = 10,         // decoded min/max differ from the index (--deep)
  kBrickLabels = 11,        // decoded label set differs from the index (--deep)
  kPadding = 12,            // a padding byte is not zero
};

// Short stable title of a kind ("payload checksum mismatch"), as in FINDINGS.md.
const char* defect_title(DefectKind kind);

struct Finding {
  DefectKind kind = DefectKind::kHeaderField;
  bool has_brick = false;                      // the fields below name a brick
  int level = 0;                               // pyramid level
  int channel = 0;                             // channel index
  std::string channel_name;                    // its name ("#<index>" if unknown)
  std::array<std::int64_t, 3> brick{0, 0, 0};  // brick x, y, z in the level's grid
  std::string detail;                          // one line, no file name

  int number() const { return int(kind); }
  // "level 0 channel ct brick (1,0,2): " or "" when no brick is named.
  std::string where() const;
  // "finding 8: level 0 channel ct brick (1,0,2): payload checksum mismatch (stored ...)"
  std::string text() const;
};

// A structural defect found by Reader::open: a FormatError (exit code 4) whose what() is
// "<path>: <where><detail>", carrying the finding.
class FileDefect : public FormatError {
 public:
  FileDefect(const std::string& path, Finding finding);
  const Finding& finding() const { return finding_; }

 private:
  Finding finding_;
};

}  // namespace vispack::format
