#!/usr/bin/env bash
# Packs release binaries for a lent GPU machine (tools/gpu-figures.sh) as one solid archive.
#
#   tools/pack-gpu-bins.sh DEST BINARY...
#
# Each binary is stripped (`strip --strip-all`: the debug line tables are most of its size) and
# all of them go into DEST/bins.tar.xz as ONE xz stream whose dictionary (256 MiB) spans several
# binaries, so the Burn, CubeCL and wgpu code they all link is stored once: three benchmark
# binaries pack to about what one does alone. The call that carries DEST is limited to 64 MiB
# with the repository's tracked files.
set -euo pipefail
dest=${1:?DEST folder}
shift
[ "$#" -gt 0 ] || { echo "no binaries named" >&2; exit 2; }
stage=$(mktemp -d)
trap 'rm -rf "$stage"' EXIT
for b in "$@"; do
    [ -x "$b" ] || { echo "not an executable: $b" >&2; exit 2; }
    cp "$b" "$stage/"
    strip --strip-all "$stage/$(basename "$b")"
done
mkdir -p "$dest"
tar -C "$stage" -cf - . | xz -9e --lzma2=preset=9e,dict=256MiB -T1 >"$dest/bins.tar.xz"
ls -l "$dest/bins.tar.xz" | awk '{printf "%s: %.1f MB\n", $NF, $5 / 1e6}'
