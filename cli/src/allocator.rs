//! How the binaries' allocator treats freed memory.
//!
//! A training step allocates and frees the same large tensors again and again (op outputs,
//! autodiff intermediates, their gradients). glibc serves every block above its mmap threshold
//! (at most 32 MiB) with a fresh `mmap` and returns it with `munmap` on free, so the next step
//! touches brand-new pages and the kernel zero-fills each 4 KiB page on its first write. On
//! the cpu preset that was ~59 million page faults in one training step, two thirds of its
//! wall time spent in the kernel (BENCHMARKS.md, "Training step profile"). With mmap disabled
//! and trimming off, freed blocks stay in the heap and are reused as they are.
//!
//! One arena for every thread: glibc gives threads other than `main` arenas of their own, mapped
//! in heaps of at most 64 MiB that are unmapped when they empty, so the large blocks those
//! threads freed were faulted in again on their next use. Training steps and
//! reconstructions run on rayon's threads (`lifegom_render::device::on_pool_thread`), and with
//! per-thread arenas the cpu preset's reconstruction was 10–13 % slower there than on `main`
//! (BENCHMARKS.md, 2026-11-25: "the step on rayon's threads with one malloc arena"). All threads
//! allocating from one arena share its lock, which the step's few hundred large allocations do
//! not contend for.
//!
//! The cost is resident memory: the heap keeps what it once held (cpu preset: 16.5 GB peak,
//! against 14.2 GB before, with the step 3–4× faster). jemalloc and mimalloc with their default
//! purging were measured too, and were slower than untuned glibc on the quickstart step (they
//! return freed pages to the kernel after a delay shorter than a step).

/// Keeps freed memory in the process for reuse (module docs). Call first thing in `main`,
/// before any thread starts. A no-op outside Linux with glibc.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: `mallopt` only sets glibc's allocation parameters; it is called before the
        // program starts threads, and any value is valid (a refused one leaves the default).
        unsafe {
            libc::mallopt(libc::M_MMAP_MAX, 0);
            // -1 disables trimming (mallopt(3)); any finite threshold fits in an `int`, at most
            // 2 GiB, and the cpu preset's backward frees and retakes more than that at a time.
            libc::mallopt(libc::M_TRIM_THRESHOLD, -1);
            libc::mallopt(libc::M_ARENA_MAX, 1);
        }
    }
}
