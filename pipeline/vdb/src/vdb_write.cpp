#include "vispack/pipeline/vdb/vdb_write.h"

#include <ostream>

#include "vispack/common/atomic_file.h"
#include "vispack/common/background_writer.h"
#include "vispack/common/error.h"

namespace vispack::pipeline {

namespace {

// io::File::write opens its own std::ofstream; the archive's stream writer is protected, so a
// subclass hands it our stream (the same call io::File makes: seekable, with grid offsets).
class ArchiveToStream : public openvdb::io::Archive {
 public:
  void write_seekable(std::ostream& os, const openvdb::GridCPtrVec& grids,
                      const openvdb::MetaMap& meta) const {
    openvdb::io::Archive::write(os, grids, /*seekable=*/true, meta);
  }
};

}  // namespace

void write_vdb_grids(const std::string& path, const openvdb::GridCPtrVec& grids,
                     const openvdb::MetaMap& meta, bool background, std::size_t buffer_bytes) {
  AtomicFile out(path);
  {
    BackgroundWriter buffer(out, background, buffer_bytes);
    std::ostream stream(&buffer);
    try {
      ArchiveToStream().write_seekable(stream, grids, meta);
    } catch (const openvdb::Exception& e) {
      buffer.finish();  // a failed write (disk full) is the cause: its IoError names it
      throw IoError(cat(path, ": cannot write: ", e.what()));
    }
    buffer.finish();
    if (!stream) throw IoError(cat(path, ": cannot write: the OpenVDB stream failed"));
  }
  out.commit();
}

}  // namespace vispack::pipeline
