# Sourced by the benchmark scripts that need the `vhp` phantom at the real slice size:
#   vhp_phantom BIN_DIR WORK_DIR SLICES  -> prints WORK_DIR/vhp-SLICES, generating it first
#   (vispack-phantom --preset vhp --slices SLICES --rgb-raw --seed 1: 2048x1216 colour as planar
#   .raw) unless a complete one is there (the `.complete` marker is written last).
vhp_phantom() {
  local bin=$1 work=$2 slices=$3
  local dir=$work/vhp-$slices
  if [[ ! -f $dir/.complete ]]; then
    rm -rf "$dir"
    "$bin/vispack-phantom" --out "$dir" --preset vhp --slices "$slices" --rgb-raw --seed 1 --quiet >&2
    touch "$dir/.complete"
  fi
  echo "$dir"
}
