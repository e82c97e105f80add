#!/usr/bin/env bash
# GPU figures on a lent machine with an NVIDIA card (BENCHMARKS.md, "On a GPU").
#
# Run from the repository root, with release binaries built on the development machine copied
# into $BIN (the lent machine has no Rust toolchain) and the Vulkan loader's Debian packages in
# .gl/ (the lent machine's image has the NVIDIA driver and its Vulkan ICD, but no loader):
#
#   BIN=gpu-bin OUT=/tmp/gpu-out bash tools/gpu-figures.sh
#
# Every figure is one JSON line from a benchmark binary (render-bench, recon-bench, train-bench)
# on `--device wgpu`; the CPU backend of the same machine is run beside the headline case so the
# card's figure has a same-machine baseline. Test binaries found in $BIN (names starting with
# `test-`) run too, with LIFEGOM_REQUIRE_WGPU=1, so the CubeCL kernels' parity with the CPU
# reference is checked on a real GPU, not only on lavapipe. Each step has its own time limit, so
# one that hangs cannot eat the others' time.
set -uo pipefail
BIN=${BIN:?BIN: folder of release binaries}
OUT=${OUT:-/tmp/gpu-out}
# Few files come back from a lent machine: the logs go to LOGS and are packed into
# $OUT/logs.tar.gz after every step, so a run cut off at its time limit still returns them.
LOGS=${LOGS:-/tmp/gpu-logs}
mkdir -p "$OUT" "$LOGS"
TEMPLATE=assets/body/anny_neutral_tpose.glb
# The binaries find the body templates and configs through paths baked in at build time
# (CARGO_MANIFEST_DIR); point the build machine's checkout path at this copy.
BUILT_AT=${BUILT_AT:-/work/main}
if [ ! -e "$BUILT_AT" ]; then
    mkdir -p "$(dirname "$BUILT_AT")" && ln -s "$PWD" "$BUILT_AT"
fi

# The Vulkan loader, unpacked over / (only these small library packages: others can break /).
if ! ldconfig -p | grep -q 'libvulkan\.so\.1'; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
fi
if [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ]; then
    export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
fi
export RUST_LOG=warn

# Binaries travel compressed (a stripped release binary is ≈ 70 MB, the carry limit 64 MiB).
for f in "$BIN"/*.xz; do
    [ -e "$f" ] || continue
    python3 -c 'import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.argv[1]), open(sys.argv[2], "wb"))' "$f" "${f%.xz}"
    chmod +x "${f%.xz}"
done

step() {
    # step NAME LIMIT_S COMMAND...: one benchmark, its output kept in $LOGS/NAME.log.
    local name=$1 limit=$2
    shift 2
    echo "== $name ($(date +%T)): $*"
    local t0=$SECONDS
    timeout "$limit" "$@" >"$LOGS/$name.log" 2>&1
    local rc=$?
    echo "   rc $rc in $((SECONDS - t0)) s; $(grep -h -m1 'wgpu adapter' "$LOGS/$name.log")"
    grep -h '^{' "$LOGS/$name.log" | tail -n 1 | tee -a "$OUT/figures.jsonl"
    [ "$rc" -eq 0 ] || tail -n 5 "$LOGS/$name.log"
    tar -czf "$OUT/logs.tar.gz" -C "$LOGS" .
}

nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv | tee "$OUT/gpu.txt"
nproc | sed 's/^/host cores: /' | tee -a "$OUT/gpu.txt"

# SET=compare runs the GPU-against-CPU comparisons instead of the main set: the paper network at
# one subdivision (the size the 2-core VM measured) and the small presets on wgpu and on the
# machine's 16 CPU cores.
if [ "${SET:-main}" = compare ]; then
    step recon-wgpu-paper-1024-s1 120 "$BIN/recon-bench" --device wgpu --config paper --size 1024 --subdiv 1 --runs 3 --json --template "$TEMPLATE"
    step recon-flex-cpu-256 120 "$BIN/recon-bench" --device flex --config cpu --size 256 --runs 2 --json --template "$TEMPLATE"
    step recon-flex-tiny 60 "$BIN/recon-bench" --device flex --config tiny --runs 5 --json
    step train-flex-quickstart 100 "$BIN/train-bench" --device flex --config configs/quickstart.toml --steps 10 --warmup 2
    echo "== done ($(date +%T))"
    exit 0
fi

# The headline: the rasterizer at 1024² with 2 subdivisions (438,720 Gaussians). Which device
# ran it: nvidia-smi lists the bench while it holds the card.
"$BIN/render-bench" --device wgpu --size 1024 --subdiv 2 --runs 3 --json --template "$TEMPLATE" >/dev/null 2>&1 &
sleep 4
nvidia-smi --query-compute-apps=process_name,used_memory --format=csv | tee -a "$OUT/gpu.txt"
wait
step render-wgpu-1024-s2 75 "$BIN/render-bench" --device wgpu --size 1024 --subdiv 2 --runs 7 --json --template "$TEMPLATE"
# The reconstruction at the paper's setting (T = 3, 3 views, 1024², 2 subdivisions; the paper
# reports 907.92 ms on one A100).
step recon-wgpu-paper-1024-s2 150 "$BIN/recon-bench" --device wgpu --config paper --size 1024 --subdiv 2 --runs 3 --json --template "$TEMPLATE"
# A training step on the quickstart config (its data is generated on the fly).
step train-wgpu-quickstart 100 "$BIN/train-bench" --device wgpu --config configs/quickstart.toml --steps 10 --warmup 2
# Parity of the CubeCL kernels with the CPU reference, on the card.
for t in "$BIN"/test-*; do
    case "$t" in *.xz) continue ;; esac
    [ -x "$t" ] || continue
    name=$(basename "$t")
    echo "== $name ($(date +%T))"
    t0=$SECONDS
    LIFEGOM_REQUIRE_WGPU=1 timeout 120 "$t" wgpu >"$LOGS/$name.log" 2>&1
    echo "   rc $? in $((SECONDS - t0)) s: $(grep -E '^test result' "$LOGS/$name.log" | tail -n 1)"
    tar -czf "$OUT/logs.tar.gz" -C "$LOGS" .
done
step recon-wgpu-cpu-256 60 "$BIN/recon-bench" --device wgpu --config cpu --size 256 --runs 3 --json --template "$TEMPLATE"
step render-wgpu-512-s2 45 "$BIN/render-bench" --device wgpu --size 512 --subdiv 2 --runs 7 --json --template "$TEMPLATE"
step render-wgpu-256-s0 45 "$BIN/render-bench" --device wgpu --size 256 --subdiv 0 --runs 7 --json --template "$TEMPLATE"
step recon-wgpu-tiny 45 "$BIN/recon-bench" --device wgpu --config tiny --runs 5 --json
# The same machine's CPU (16 cores) through Flex, at the headline size.
step render-flex-1024-s2 45 "$BIN/render-bench" --device flex --size 1024 --subdiv 2 --runs 3 --json --template "$TEMPLATE"
echo "== done ($(date +%T))"
