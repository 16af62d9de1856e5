#!/bin/bash
# The pipeline's link graph (build/pipeline_link_graph.txt, written by pipeline/CMakeLists.txt:
# each pipeline library and tool with everything it links, directly or through others) keeps the
# libraries that read no image away from the image libraries: the core (config, paths, listing),
# the pack merge and the OpenVDB export, and their tools vispack-merge and vispack-vdb; the
# format's OME-Zarr export (vispack_format_export, vispack-export: the reader alone). Also
# checks that each stage tool links its own stage and no other stage (vispack-run links them
# all). links_no_image_library.sh checks the same on the built executables (ldd); this test
# says which CMake link brought an image library in.
# Usage: link_graph.sh BUILD_DIR
set -euo pipefail
graph="$1/pipeline_link_graph.txt"
[[ -s $graph ]] || { echo "link_graph: $graph is missing or empty (configure the build)" >&2; exit 1; }
status=0
links_of() {  # TARGET -> its closure, one per line
  local line
  line=$(grep -E "^$1: " "$graph" || true)
  [[ -n $line ]] || { echo "link_graph: $1 is not in $graph" >&2; status=1; return; }
  tr ' ;' '\n\n' <<<"${line#*: }" | grep -v '^$' || true
}
forbid() {  # TARGET REGEX WHY
  local bad
  bad=$(links_of "$1" | grep -E "$2" | tr '\n' ' ' || true)
  if [[ -n $bad ]]; then
    echo "$1 links $bad($3)" >&2
    status=1
  else
    echo "$1: $(links_of "$1" | wc -l) libraries, none matching $2"
  fi
}
require() {  # TARGET LIBRARY
  links_of "$1" | grep -qx "$2" || { echo "$1 does not link $2" >&2; status=1; }
}
image='OpenImageIO|opencv_imgcodecs|vispack_image_io|vispack_pipeline_imaging'
forbid vispack_pipeline_core "$image|opencv|openvdb|vispack_pipeline_(register|mask|labels|pack|vdb|run)" \
  "the core reads no image, links no OpenCV and depends on no stage"
forbid vispack_pipeline_pack_merge "$image|openvdb" "the merge reads slab files, no image"
forbid vispack-merge "$image|openvdb" "vispack-merge runs alone between cluster steps"
forbid vispack_pipeline_vdb "$image" "the export reads the packed file, no image"
forbid vispack-vdb "$image" "vispack-vdb runs once per shard"
forbid vispack_format_export "$image|openvdb|vispack_format_writer|vispack_pipeline" \
  "the OME-Zarr export reads the packed file through the reader alone"
forbid vispack-export "$image|openvdb|vispack_format_writer|vispack_pipeline" \
  "vispack-export is a reader tool, like vispack-extract without its image output"
require vispack-export vispack_format_reader
for stage in register mask labels pack vdb; do
  require "vispack-$stage" "vispack_pipeline_$stage"
  others=$(echo register mask labels pack vdb run | tr ' ' '\n' | grep -vx "$stage" | paste -sd'|')
  forbid "vispack-$stage" "^vispack_pipeline_($others)$" "a stage tool links its own stage only"
done
for stage in register mask labels pack vdb; do
  require vispack-run "vispack_pipeline_$stage"
done
exit $status
