#!/bin/bash
# The executables that read no image must link no image library: vispack-merge (also no OpenVDB)
# and vispack-vdb, and vispack-export (OME-Zarr, over the format reader alone). The first two run as steps of a cluster chain (the merge alone between the shards and
# the export, the export once per shard), and vispack-pack's start-up (the dynamic loader
# resolving OpenImageIO's ~260 libraries) was 0.4 s of a 0.4-0.9 s merge on a small volume
# (docs/BENCHMARKS.md). Fails naming the library, if an edit makes either's code reach an image
# reader again (find the object that pulled it with -Wl,-Map: "Archive member included to
# satisfy reference by file").
# Usage: links_no_image_library.sh BIN_DIR
set -euo pipefail
status=0
check() {  # TOOL FORBIDDEN_REGEX
  local tool="$BIN/$1" libs bad
  [[ -x $tool ]] || { echo "no $tool" >&2; status=1; return; }
  libs=$(ldd "$tool")
  bad=$(grep -E -o "lib($2)[^ ]*" <<<"$libs" | sort -u || true)
  if [[ -n $bad ]]; then
    echo "$1 links $(echo $bad): something in its code reads images" >&2
    status=1
  else
    echo "$1: $(grep -c '=>' <<<"$libs" || true) shared libraries, none matching $2"
  fi
}
BIN=$1
check vispack-merge 'OpenImageIO|opencv_imgcodecs|openvdb'
check vispack-vdb 'OpenImageIO|opencv_imgcodecs'
# The OME-Zarr export reads the packed file through the format's reader alone.
check vispack-export 'OpenImageIO|opencv_imgcodecs|openvdb'
exit $status
