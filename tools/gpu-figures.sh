#!/usr/bin/env bash
# GPU figures on a lent machine with an NVIDIA card (BENCHMARKS.md, "On a GPU"), in ONE call.
#
# Run from the repository root, with release binaries built on the development machine copied
# into $BIN (the lent machine has no Rust toolchain) and the Vulkan loader's and glvnd's Debian
# packages in .gl/ (the lent machine's image has the NVIDIA driver and its Vulkan ICD, but no
# loader; with libvulkan1 alone the ICD finds no adapter):
#
#   (cd .gl && apt-get download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
#
#   cargo build --release --workspace --locked   # on the dev machine
#   BIN=gpu-bin BIN_BEFORE="gpu-bin-before gpu-bin-wgsl" OUT=/tmp/gpu-out bash tools/gpu-figures.sh
#
# Every figure is one JSON line from a benchmark binary (recon-bench, train-bench, render-bench),
# appended to $OUT/figures.jsonl with the step's name. On wgpu the lines carry
# `kernel_launches` and `top_kernels` (lifegom_cli::launches). The set took 4 min 34 s on an
# H200 on 2026-11-28 (84f90d8; without before binaries and test binaries):
#   1. the quickstart training step and the paper-setting reconstruction on wgpu, alternated
#      with the same commands from the binaries of each folder in $BIN_BEFORE (a space-separated
#      list; a folder may hold only some of the binaries) when it is set: before/after pairs
#      from one machine, since figures move between machines of the same kind;
#      then the same two from $BIN with Burn's kernel fusion off (LIFEGOM_FUSION=off), and the
#      training step (quickstart here, the paper preset in 3.) with the weight gradients as one
#      product each (`--split-k-rows 0`), and the paper reconstruction (and in 3. the paper
#      training step) with Burn's direct convolutions (LIFEGOM_CONV=direct) and with the Point
#      Transformer's levels planned inline (LIFEGOM_HIERARCHY=inline);
#   2. the paper network's reconstruction at 256² (the size the issue records launches at);
#   3. per-kernel device times (`--kernel-times`; also per `tracing` span, where the launching
#      thread has one open: Burn's own ops launch on its stream's thread) of the
#      paper-setting reconstruction, of a quickstart training step and of a training step at the
#      paper preset (configs/paper-bench.toml);
#   4. the rasterizer's headline (1024², 2 subdivisions) and test binaries named `test-*` in $BIN
#      (run with LIFEGOM_REQUIRE_WGPU=1: the CubeCL kernels' parity with the CPU reference on the
#      card);
#   4b. `matmul-bench`, when $BIN has it: Burn's matmul for the training step's shapes, and
#      `relu(x·W + b)` as Burn's kernels beside the shared layer's product kernel (`layer`
#      lines), and the same layer through three passes forward and backward, Burn's autodiff
#      beside the shared layer's masked products and gradient kernel (`layer_backward` lines),
#      with fusion on and off (every line kept, one per shape and form);
#   5. with AUTOTUNE_BIN set, the kernels Burn's autotune picks at the paper setting;
#   6. with CUDA_BIN set (binaries built with `--features lifegom-cli/cuda`), the quickstart
#      step and the paper reconstruction on `--device cuda` beside wgpu. CubeCL's CUDA runtime
#      compiles kernels with NVRTC: put the CUDA toolkit's libnvrtc*.so* in $CUDA_LIBS (default
#      .cuda/) when the machine lacks them.
# Each step has its own time limit, so one that hangs cannot eat the others' time.
set -uo pipefail
BIN=${BIN:?BIN: folder of release binaries}
BIN_BEFORE=${BIN_BEFORE:-}
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

# Binaries travel compressed (`strip --strip-all`, then `xz -9`: ≈ 12 MB each). A call carries
# at most 64 MiB, the repository's tracked files included (53 MB on 2026-11-28), so a folder's
# binaries travel best as ONE solid archive, `bins.tar.xz`: the binaries share most of their
# code (Burn, CubeCL, wgpu), and one xz stream with a dictionary as large as a binary stores
# that code once (tools/pack-gpu-bins.sh makes it). Single `NAME.xz` files still work.
for dir in "$BIN" $BIN_BEFORE ${AUTOTUNE_BIN:-} ${CUDA_BIN:-}; do
    if [ -e "$dir/bins.tar.xz" ]; then
        python3 -c 'import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2])' "$dir/bins.tar.xz" "$dir"
    fi
    for f in "$dir"/*.xz; do
        [ -e "$f" ] || continue
        case "$f" in *.tar.xz) continue ;; esac
        python3 -c 'import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.argv[1]), open(sys.argv[2], "wb"))' "$f" "${f%.xz}"
        chmod +x "${f%.xz}"
    done
done

step() {
    # step NAME LIMIT_S COMMAND...: one benchmark, its output kept in $LOGS/NAME.log and its
    # last JSON line (every line with STEP_LINES=all) in $OUT/figures.jsonl under the step's name.
    local name=$1 limit=$2 keep=${STEP_LINES:-1}
    shift 2
    echo "== $name ($(date +%T)): $*"
    local t0=$SECONDS
    timeout "$limit" "$@" >"$LOGS/$name.log" 2>&1
    local rc=$?
    echo "   rc $rc in $((SECONDS - t0)) s"
    grep -h '^{' "$LOGS/$name.log" | { if [ "$keep" = all ]; then cat; else tail -n 1; fi; } |
        python3 -c 'import json, sys
for line in sys.stdin:
    d = json.loads(line); d["step"] = sys.argv[1]; print(json.dumps(d))' "$name" |
        tee -a "$OUT/figures.jsonl" | cut -c 1-400
    [ "$rc" -eq 0 ] || tail -n 5 "$LOGS/$name.log"
    tar -czf "$OUT/logs.tar.gz" -C "$LOGS" .
}

nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv | tee "$OUT/gpu.txt"
nproc | sed 's/^/host cores: /' | tee -a "$OUT/gpu.txt"

QUICK=(--config configs/quickstart.toml --steps 10 --warmup 2)
PAPER=(--config paper --size 1024 --subdiv 2 --runs 3 --json --template "$TEMPLATE")

# 1. wgpu, after/before/after. Which device ran it: nvidia-smi lists the bench on the card.
"$BIN/recon-bench" --device wgpu --config tiny --runs 1 --json >/dev/null 2>&1 &
sleep 5
nvidia-smi --query-compute-apps=process_name,used_memory --format=csv | tee -a "$OUT/gpu.txt"
wait
compare() {
    # compare NAME LIMIT BINARY ARGS...: the step from $BIN, then from each $BIN_BEFORE folder that
    # holds BINARY (step NAME prefixed with the folder's name), then from $BIN again, so that a
    # drift of the card during the call shows.
    local name=$1 limit=$2 exe=$3
    shift 3
    step "$name" "$limit" "$BIN/$exe" "$@"
    local others=0 dir
    for dir in $BIN_BEFORE; do
        [ -x "$dir/$exe" ] || continue
        step "$(basename "$dir")-$name" "$limit" "$dir/$exe" "$@"
        others=1
    done
    if [ "$others" = 1 ]; then
        step "$name-2" "$limit" "$BIN/$exe" "$@"
    fi
}
compare train-wgpu-quickstart 90 train-bench --device wgpu "${QUICK[@]}"
compare recon-wgpu-paper-1024-s2 90 recon-bench --device wgpu "${PAPER[@]}"

# 1b. The same binaries with Burn's kernel fusion off (LIFEGOM_FUSION=off: every op its own
#     kernel), to see what fusion gains or costs at each size (design.md §1.4).
step fusion-off-train-wgpu-quickstart 90 env LIFEGOM_FUSION=off "$BIN/train-bench" --device wgpu "${QUICK[@]}"
step fusion-off-recon-wgpu-paper-1024-s2 90 env LIFEGOM_FUSION=off "$BIN/recon-bench" --device wgpu "${PAPER[@]}"

# 1c. The training steps with the shared layers' weight gradients as one product each
#     (`--split-k-rows 0`, as before f6dd65c, 2026-11-28) beside the default split-k (design.md
#     §1.4).
step split-k-off-train-wgpu-quickstart 90 "$BIN/train-bench" --device wgpu "${QUICK[@]}" --split-k-rows 0
# 1d. The encoder's convolutions with Burn's direct kernel (LIFEGOM_CONV=direct, as before
#     84f90d8, 2026-11-28) beside each convolution and its BatchNorm as one implicit-GEMM product
#     (ops/src/conv_norm.rs, since b406b80; patch columns and Burn's matmul from 84f90d8 to it).
step conv-direct-recon-wgpu-paper-1024-s2 90 env LIFEGOM_CONV=direct "$BIN/recon-bench" --device wgpu "${PAPER[@]}"
# 1e. The Point Transformer's FPS and kNN planned inline, after a read-back that drains the
#     queue (LIFEGOM_HIERARCHY=inline, as before ad62627, 2026-11-28), beside planned ahead on a
#     thread.
step hierarchy-inline-recon-wgpu-paper-1024-s2 90 env LIFEGOM_HIERARCHY=inline "$BIN/recon-bench" --device wgpu "${PAPER[@]}"

GPU_DEVICE=wgpu

step recon-wgpu-paper-256 60 "$BIN/recon-bench" --device wgpu --config paper --size 256 --subdiv 1 --runs 3 --json --template "$TEMPLATE"

# 3. Where the device time goes at the paper's setting, kernel by kernel.
compare profile-recon-paper-1024-s2 90 recon-bench --device "$GPU_DEVICE" --config paper --size 1024 --subdiv 2 --runs 1 --json --template "$TEMPLATE" --kernel-times --top-kernels 25
step profile-train-wgpu-quickstart 60 "$BIN/train-bench" --device "$GPU_DEVICE" --config configs/quickstart.toml --steps 3 --warmup 1 --kernel-times --top-kernels 25
step train-paper-bench 150 "$BIN/train-bench" --device "$GPU_DEVICE" --config configs/paper-bench.toml --steps 3 --warmup 1
step split-k-off-train-paper-bench 150 "$BIN/train-bench" --device "$GPU_DEVICE" --config configs/paper-bench.toml --steps 3 --warmup 1 --split-k-rows 0
step conv-direct-train-paper-bench 150 env LIFEGOM_CONV=direct "$BIN/train-bench" --device "$GPU_DEVICE" --config configs/paper-bench.toml --steps 3 --warmup 1
step hierarchy-inline-train-paper-bench 150 env LIFEGOM_HIERARCHY=inline "$BIN/train-bench" --device "$GPU_DEVICE" --config configs/paper-bench.toml --steps 3 --warmup 1
step profile-train-paper-bench 120 "$BIN/train-bench" --device "$GPU_DEVICE" --config configs/paper-bench.toml --steps 2 --warmup 1 --kernel-times --top-kernels 25

# 4. The rasterizer's headline and the parity tests on the card.
if [ -x "$BIN/render-bench" ]; then
    step render-wgpu-1024-s2 60 "$BIN/render-bench" --device wgpu --size 1024 --subdiv 2 --runs 5 --json --template "$TEMPLATE"
fi
if [ -x "$BIN/matmul-bench" ]; then
    for fusion in on off; do
        STEP_LINES=all step matmul-bench-fusion-$fusion 120 env LIFEGOM_FUSION=$fusion \
            "$BIN/matmul-bench" --device wgpu --runs 20
    done
fi
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
# 5. Optional: which matmul and convolution kernels Burn's autotune picks at the paper setting,
#    from binaries built with "autotune" in the workspace's `burn` and `burn-cubecl` features
#    (folder $AUTOTUNE_BIN): CubeCL's autotune log, read from a cubecl.toml in the working
#    folder, to choose those kernels without tuning at run time (BENCHMARKS.md, "On a
#    GPU (NVIDIA H200, 2026-11-27)": tuning costs minutes per process).
if [ -n "${AUTOTUNE_BIN:-}" ] && [ -x "$AUTOTUNE_BIN/recon-bench" ]; then
    tune_dir=$(mktemp -d)
    printf '[autotune]\nlevel = "minimal"\n\n[autotune.logger]\nlevel = "minimal"\nfile = "%s"\n' \
        "$LOGS/autotune-decisions.log" >"$tune_dir/cubecl.toml"
    repo=$PWD
    (cd "$tune_dir" && step autotune-recon-paper-1024-s2 240 "$repo/$AUTOTUNE_BIN/recon-bench" \
        --device wgpu --config paper --size 1024 --subdiv 2 --runs 1 --json \
        --template "$repo/$TEMPLATE" --kernel-times --top-kernels 25)
fi
# 6. Optional: the CUDA runtime beside wgpu, same commands (issue: keep the faster as the
#    recommended GPU device).
if [ -n "${CUDA_BIN:-}" ] && [ -x "$CUDA_BIN/train-bench" ]; then
    CUDA_LIBS=${CUDA_LIBS:-.cuda}
    if [ -d "$CUDA_LIBS" ]; then
        export LD_LIBRARY_PATH="$PWD/$CUDA_LIBS${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    fi
    step cuda-train-quickstart 90 "$CUDA_BIN/train-bench" --device cuda "${QUICK[@]}"
    step cuda-recon-paper-1024-s2 90 "$CUDA_BIN/recon-bench" --device cuda "${PAPER[@]}"
    step cuda-wgpu-train-quickstart 90 "$CUDA_BIN/train-bench" --device wgpu "${QUICK[@]}"
fi
echo "== done ($(date +%T))"
