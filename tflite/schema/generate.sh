#!/usr/bin/env bash
# Regenerates tflite/src/schema.rs from tflite/schema/tflite.fbs with planus-cli 1.3.0 (the
# version of the `planus` runtime crate in Cargo.toml): `cargo install planus-cli --version
# 1.3.0 --locked` once, then run this from anywhere.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
mkdir -p "$here/../src"
planus rust -o "$here/../src/schema.rs" "$here/tflite.fbs"
rustfmt --edition 2024 "$here/../src/schema.rs"
