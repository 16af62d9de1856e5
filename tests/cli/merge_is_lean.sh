#!/bin/bash
# vispack-merge must link no image or OpenVDB library: it is the serial step of a cluster run
# between the pack shards and the OpenVDB export, and vispack-pack's start-up (the dynamic loader
# resolving OpenImageIO's ~250 libraries) was 0.4 s of a 0.4-0.9 s merge on a small volume
# (docs/BENCHMARKS.md). Fails naming the library and the object file of libvispack_pipeline.a
# that pulled it in, if an edit makes the merge's code reach an image reader again.
# Usage: merge_is_lean.sh BIN_DIR
set -euo pipefail
tool="$1/vispack-merge"
[[ -x $tool ]] || { echo "no $tool" >&2; exit 1; }
libs=$(ldd "$tool")
bad=$(grep -E -o 'lib(OpenImageIO[^ ]*|opencv_imgcodecs[^ ]*|openvdb[^ ]*)' <<<"$libs" | sort -u || true)
if [[ -n $bad ]]; then
  echo "vispack-merge links $(echo $bad): something in the merge's closure reads images or" \
    "writes OpenVDB; find it with -Wl,-Map (\"Archive member included to satisfy reference\")" >&2
  exit 1
fi
count=$(grep -c '=>' <<<"$libs" || true)
echo "vispack-merge: $count shared libraries, none of OpenImageIO, imgcodecs, OpenVDB"
