#include "vispack/format/findings.h"

#include <utility>

namespace vispack::format {

const char* defect_title(DefectKind kind) {
  switch (kind) {
    case DefectKind::kNotVispack:
      return "not a vispack file";
    case DefectKind::kUnsupportedVersion:
      return "unsupported format version";
    case DefectKind::kSizeMismatch:
      return "truncated or extended file";
    case DefectKind::kHeaderField:
      return "invalid header field";
    case DefectKind::kTableChecksum:
      return "table checksum mismatch";
    case DefectKind::kMetadata:
      return "invalid metadata";
    case DefectKind::kIndexEntry:
      return "invalid index entry";
    case DefectKind::kPayloadChecksum:
      return "payload checksum mismatch";
    case DefectKind::kPayloadDecode:
      return "payload does not decode";
    case DefectKind::kBrickRange:
      return "brick min/max differ from the index";
    case DefectKind::kBrickLabels:
      return "brick label set differs from the index";
    case DefectKind::kPadding:
      return "non-zero padding";
  }
  return "unknown defect";
}

std::string Finding::where() const {
  if (!has_brick) return "";
  return cat("level ", level, " channel ", channel_name, " brick (", brick[0], ",", brick[1], ",",
             brick[2], "): ");
}

std::string Finding::text() const {
  return cat("finding ", number(), ": ", where(), detail);
}

FileDefect::FileDefect(const std::string& path, Finding finding)
    : FormatError(cat(path, ": ", finding.where(), finding.detail)), finding_(std::move(finding)) {}

}  // namespace vispack::format
