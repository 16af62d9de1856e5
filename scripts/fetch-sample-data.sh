#!/usr/bin/env bash
# Fetches real sample data that nobody on this project made, from Debian packages (downloaded with
# `apt-get download` and unpacked with `dpkg -x`: nothing is installed), and converts it into vispack
# slice folders with configs under data/samples/ (git-ignored). See docs/SAMPLES.md.
#
#   head-ct        invesalius-examples       head CT, 256x256x108, 16-bit PNG (stored = HU + 1024)
#   aal            mricron-data              Colin27 T1 + AAL atlas as colour-coded segmentation
#   visible-woman  insighttoolkit5-examples  Visible Woman head cryosection in blue gel
#
# Idempotent: a sample whose stamp matches the converter and its config is skipped (a few seconds
# when everything is present). Non-interactive. `apt-get update` runs only when a download fails
# because the package lists are missing or stale.
set -euo pipefail

usage() {
  cat <<'EOF'
Usage: scripts/fetch-sample-data.sh [--out DIR] [--cache DIR] [--force] [SAMPLE...]

Fetches and converts the real sample data into DIR (default: data/samples in the checkout).
SAMPLE is any of: head-ct aal visible-woman (default: all).
  --out DIR    where the converted sample folders go (default: <repo>/data/samples)
  --cache DIR  where the downloaded .deb files are kept (default: <repo>/data/cache/debs)
  --force      convert again even when a sample is up to date
  -h, --help   this text
EOF
}

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
out="$root/data/samples"
cache="$root/data/cache/debs"
force=0
wanted=()
while [[ $# -gt 0 ]]; do
  case "$1" in
    --out) [[ $# -ge 2 ]] || { echo "fetch-sample-data: error: --out needs a folder" >&2; exit 2; }
           out="$2"; shift 2 ;;
    --cache) [[ $# -ge 2 ]] || { echo "fetch-sample-data: error: --cache needs a folder" >&2; exit 2; }
             cache="$2"; shift 2 ;;
    --force) force=1; shift ;;
    -h|--help) usage; exit 0 ;;
    head-ct|aal|visible-woman) wanted+=("$1"); shift ;;
    *) echo "fetch-sample-data: error: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
[[ ${#wanted[@]} -gt 0 ]] || wanted=(head-ct aal visible-woman)

declare -A package=(
  [head-ct]=invesalius-examples
  [aal]=mricron-data
  [visible-woman]=insighttoolkit5-examples
)

say() { echo "fetch-sample-data: $*"; }
die() { echo "fetch-sample-data: error: $*" >&2; exit 1; }

python=/usr/bin/python3
[[ -x "$python" ]] || die "$python not found (install python3 and python3-numpy: scripts/install-deps.sh)"
"$python" -c 'import numpy' 2>/dev/null ||
  die "$python cannot import numpy (install python3-numpy: scripts/install-deps.sh)"

converter="$root/scripts/samples/convert.py"

# Stamp of a sample: hash of the code its conversion depends on (a config change does not
# reconvert; install_config refreshes the config alone).
stamp_of() {
  cat "$converter" "$root/scripts/samples/pngio.py" | sha256sum | cut -d' ' -f1
}

# Writes DIR/config.json from configs/samples/NAME.json with its paths made local to DIR
# ("../../data/samples/NAME/" dropped, "../../out/samples/NAME/" -> "out/"); only when it changed.
install_config() {
  local name=$1 dir=$2 src="$root/configs/samples/$1.json"
  [[ -f "$src" ]] || die "$src is missing"
  sed -e "s|\.\./\.\./data/samples/$name/||g" -e "s|\.\./\.\./out/samples/$name/|out/|g" \
    "$src" >"$dir/config.json.tmp"
  if cmp -s "$dir/config.json.tmp" "$dir/config.json"; then
    rm -f "$dir/config.json.tmp"
  else
    mv "$dir/config.json.tmp" "$dir/config.json"
    return 0
  fi
  return 1
}

sudo_cmd=()
if [[ $(id -u) -ne 0 ]]; then
  if command -v sudo >/dev/null && sudo -n true 2>/dev/null; then sudo_cmd=(sudo -n); fi
fi

# Downloads PKG's .deb into $cache (once); prints its path.
fetch_deb() {
  local pkg=$1 deb log
  deb=$(find "$cache" -maxdepth 1 -name "${pkg}_*.deb" 2>/dev/null | sort | tail -n 1 || true)
  if [[ -n "$deb" ]]; then echo "$deb"; return; fi
  mkdir -p "$cache"
  local apt_opts=(-q)
  # As root, apt drops to the _apt user for downloads; keep it root so it can write the cache.
  [[ $(id -u) -eq 0 ]] && apt_opts+=(-o APT::Sandbox::User=root)
  say "downloading $pkg (apt-get download) into ${cache#"$root"/}" >&2
  if ! log=$(cd "$cache" && apt-get download "${apt_opts[@]}" "$pkg" 2>&1); then
    if grep -qiE "unable to locate|no installation candidate|can't select|failed to fetch|404" \
      <<<"$log"; then
      say "package lists are missing or stale; running apt-get update" >&2
      if [[ $(id -u) -ne 0 && ${#sudo_cmd[@]} -eq 0 ]]; then
        die "cannot download $pkg and cannot run apt-get update without root; run 'sudo apt-get update' and retry"
      fi
      "${sudo_cmd[@]}" apt-get update -q >&2 || die "apt-get update failed"
      log=$(cd "$cache" && apt-get download "${apt_opts[@]}" "$pkg" 2>&1) ||
        die "apt-get download $pkg failed: $(tail -n 1 <<<"$log")"
    else
      die "apt-get download $pkg failed: $(tail -n 1 <<<"$log")"
    fi
  fi
  deb=$(find "$cache" -maxdepth 1 -name "${pkg}_*.deb" 2>/dev/null | sort | tail -n 1 || true)
  [[ -n "$deb" ]] || die "apt-get download $pkg left no .deb in $cache"
  echo "$deb"
}

mkdir -p "$out"
tmp_root=$(mktemp -d "${TMPDIR:-/tmp}/vispack-samples.XXXXXX")
trap 'rm -rf "$tmp_root" "$out"/.tmp-* 2>/dev/null || true' EXIT

converted=0
for name in "${wanted[@]}"; do
  pkg=${package[$name]}
  dest="$out/$name"
  stamp=$(stamp_of "$name")
  if [[ $force -eq 0 && -f "$dest/.stamp" && "$(head -n 1 "$dest/.stamp")" == "$stamp" ]]; then
    if install_config "$name" "$dest"; then
      say "$name: up to date, config.json refreshed from configs/samples/$name.json"
    else
      say "$name: up to date ($dest)"
    fi
    continue
  fi
  deb=$(fetch_deb "$pkg")
  say "$name: unpacking $(basename "$deb")"
  rm -rf "${tmp_root:?}/$pkg"
  dpkg -x "$deb" "$tmp_root/$pkg" || die "dpkg -x $deb failed (is the file complete? delete it and retry)"
  say "$name: converting into $dest"
  rm -rf "$out/.tmp-$name"
  "$python" "$converter" "$name" "$tmp_root/$pkg" "$out/.tmp-$name" || die "$name: conversion failed"
  install_config "$name" "$out/.tmp-$name" || true
  printf '%s\n%s\n' "$stamp" "$(basename "$deb")" >"$out/.tmp-$name/.stamp"
  rm -rf "$dest"
  mv "$out/.tmp-$name" "$dest"
  rm -rf "${tmp_root:?}/$pkg"
  converted=$((converted + 1))
  say "$name: done ($(du -sh "$dest" | cut -f1))"
done
say "$converted converted, $((${#wanted[@]} - converted)) already up to date; samples in $out"
