//! GPU exclusive prefix sum and stable LSD radix sort of `u32` keys with `u32` values.
//!
//! Both are built from one idea: a thread owns a contiguous *chunk* of the input and walks it
//! serially, so the order inside a chunk is the input order for free, and only the per-chunk
//! totals need a parallel step.
//!
//! - **Scan** (`exclusive_scan`): each thread turns its chunk of `SCAN_CHUNK` values into an
//!   exclusive scan in place and writes the chunk total; the totals are scanned recursively (each
//!   level is `SCAN_CHUNK` times shorter); then every value adds the scanned total of its chunk.
//!   An array of at most `BLOCK_SCAN_MAX` values (every scan of a training-size render, and
//!   every level but the first of a large one) is scanned by one cube in one launch instead:
//!   its threads scan their chunks, one thread scans their totals in shared memory, and each
//!   adds its offset. A training step renders about fifteen times with eleven scans each, so
//!   this saves two launches a scan (two levels and the add) where the launch, not the work,
//!   is the cost. The sums are integer, so both paths give the same values.
//! - **Radix sort** (`radix_sort_pairs`): 4 bits per pass, least significant digit first. Per pass,
//!   each thread counts the 16 digits of its chunk into `counts[digit * num_chunks + chunk]`
//!   (digit-major), the counts are scanned, and each thread walks its chunk again writing every
//!   element to `scanned[digit * num_chunks + chunk] + (elements of that digit seen so far in the
//!   chunk)`. Digit-major order puts all of digit 0 first, chunk by chunk, so each pass is stable
//!   and the whole sort is stable: equal keys keep their input order. The rasterizer relies on
//!   that twice (ties in depth break by index; the tile sort keeps each tile's depth order).
//!
//!   A sort of at most `BLOCK_SORT_MAX` pairs (a training-size render's depth and tile sorts)
//!   runs every pass in one cube and one launch instead (`radix_sort_block`): the same chunks,
//!   digit-major counts and scatter, with the counts in shared memory, scanned by the cube, and a
//!   storage barrier between passes. The order of every write is the same as the multi-launch
//!   path's, so both give the same result; a training step's 15 renders sort with 2 launches
//!   each instead of 30.
//!
//! Keys above `bits` are assumed zero: a pass is only run for digits that can be non-zero.

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;

use crate::cube::host::{ComputeClient, THREADS_1D, arg, count_1d, empty_u32};

/// Elements a scan thread walks serially.
const SCAN_CHUNK: u32 = 256;
/// Threads of the one cube that scans a short array in one launch.
const BLOCK_SCAN_THREADS: u32 = 256;
/// The longest array one cube scans ([`scan_block`]): each thread walks at most `SCAN_CHUNK`.
const BLOCK_SCAN_MAX: usize = (BLOCK_SCAN_THREADS * SCAN_CHUNK) as usize;
/// Elements a radix-sort thread walks serially.
const SORT_CHUNK: u32 = 64;
/// Bits of the key one radix-sort pass sorts on.
const RADIX_BITS: u32 = 4;
/// Digits per pass: `2^RADIX_BITS`, the length of a chunk's histogram.
const RADIX_DIGITS: u32 = 1 << RADIX_BITS;
/// `RADIX_DIGITS` as an array length.
const HIST_LEN: usize = RADIX_DIGITS as usize;
/// Masks one digit out of a shifted key.
const DIGIT_MASK: u32 = RADIX_DIGITS - 1;
/// Threads of the one cube that sorts a short array (`radix_sort_block`): its shared counts are
/// `RADIX_DIGITS` per thread, 8 KiB, within every device's 16 KiB of shared memory.
const BLOCK_SORT_THREADS: u32 = 128;
/// The most pairs one cube sorts: each thread walks at most 512 per pass.
const BLOCK_SORT_MAX: usize = 1 << 16;
/// `RADIX_DIGITS · BLOCK_SORT_THREADS`: the digit-major counts of one cube.
const BLOCK_SORT_COUNTS: usize = (RADIX_DIGITS * BLOCK_SORT_THREADS) as usize;

#[cube(launch)]
fn scan_chunks(data: &mut [u32], totals: &mut [u32], n: u32) {
    let chunk = ABSOLUTE_POS as u32;
    let start = chunk * SCAN_CHUNK;
    if start < n {
        let end = min(start + SCAN_CHUNK, n);
        let mut running = 0u32;
        for i in start..end {
            let value = data[i as usize];
            data[i as usize] = running;
            running += value;
        }
        totals[chunk as usize] = running;
    }
}

#[cube(launch)]
fn scan_add(data: &mut [u32], scanned_totals: &[u32], n: u32) {
    let i = ABSOLUTE_POS as u32;
    if i < n {
        data[i as usize] += scanned_totals[(i / SCAN_CHUNK) as usize];
    }
}

/// The exclusive scan of `data[..n]`, `n ≤ BLOCK_SCAN_MAX`, by one cube of
/// `BLOCK_SCAN_THREADS` threads (module docs).
#[cube(launch)]
fn scan_block(data: &mut [u32], n: u32) {
    let mut totals = Shared::<[u32]>::new_slice(BLOCK_SCAN_THREADS as usize);
    let unit = UNIT_POS;
    let per = n.div_ceil(BLOCK_SCAN_THREADS);
    let start = unit * per;
    let end = min(start + per, n);
    let mut running = 0u32;
    if start < n {
        for i in start..end {
            let value = data[i as usize];
            data[i as usize] = running;
            running += value;
        }
    }
    totals[unit as usize] = running;
    sync_cube();
    if unit == 0 {
        let mut sum = 0u32;
        for t in 0..BLOCK_SCAN_THREADS {
            let total = totals[t as usize];
            totals[t as usize] = sum;
            sum += total;
        }
    }
    sync_cube();
    let offset = totals[unit as usize];
    if start < n {
        for i in start..end {
            data[i as usize] += offset;
        }
    }
}

/// Replaces the first `n` values of `data` by their exclusive prefix sum.
pub(crate) fn exclusive_scan(client: &ComputeClient, data: &Handle, n: usize) {
    if n == 0 {
        return;
    }
    if n <= BLOCK_SCAN_MAX {
        scan_block::launch(
            client,
            CubeCount::Static(1, 1, 1),
            CubeDim::new_1d(BLOCK_SCAN_THREADS),
            arg(data, n),
            n as u32,
        );
        return;
    }
    let chunks = n.div_ceil(SCAN_CHUNK as usize);
    let totals = empty_u32(client, chunks);
    scan_chunks::launch(
        client,
        count_1d(chunks),
        CubeDim::new_1d(THREADS_1D),
        arg(data, n),
        arg(&totals, chunks),
        n as u32,
    );
    if chunks > 1 {
        exclusive_scan(client, &totals, chunks);
        scan_add::launch(
            client,
            count_1d(n),
            CubeDim::new_1d(THREADS_1D),
            arg(data, n),
            arg(&totals, chunks),
            n as u32,
        );
    }
}

#[cube(launch)]
fn radix_count(keys: &[u32], counts: &mut [u32], n: u32, shift: u32, num_chunks: u32) {
    let chunk = ABSOLUTE_POS as u32;
    if chunk < num_chunks {
        let mut hist = Array::<u32>::new(HIST_LEN);
        for d in 0..RADIX_DIGITS {
            hist[d as usize] = 0u32;
        }
        let start = chunk * SORT_CHUNK;
        let end = min(start + SORT_CHUNK, n);
        for i in start..end {
            let digit = (keys[i as usize] >> shift) & DIGIT_MASK;
            hist[digit as usize] += 1u32;
        }
        for d in 0..RADIX_DIGITS {
            counts[(d * num_chunks + chunk) as usize] = hist[d as usize];
        }
    }
}

#[cube(launch)]
fn radix_scatter(
    keys_in: &[u32],
    values_in: &[u32],
    offsets: &[u32],
    keys_out: &mut [u32],
    values_out: &mut [u32],
    n: u32,
    shift: u32,
    num_chunks: u32,
) {
    let chunk = ABSOLUTE_POS as u32;
    if chunk < num_chunks {
        let mut next = Array::<u32>::new(HIST_LEN);
        for d in 0..RADIX_DIGITS {
            next[d as usize] = offsets[(d * num_chunks + chunk) as usize];
        }
        let start = chunk * SORT_CHUNK;
        let end = min(start + SORT_CHUNK, n);
        for i in start..end {
            let key = keys_in[i as usize];
            let digit = (key >> shift) & DIGIT_MASK;
            let at = next[digit as usize];
            keys_out[at as usize] = key;
            values_out[at as usize] = values_in[i as usize];
            next[digit as usize] = at + 1u32;
        }
    }
}

/// One pass of the one-cube sort: thread `unit` counts the digits of its chunk `start..end`, the
/// cube scans the digit-major counts in `counts` (`BLOCK_SORT_COUNTS`, each thread a run of
/// `RADIX_DIGITS` of them), and the thread scatters its chunk from `keys_in` to `keys_out`.
#[cube]
#[allow(clippy::too_many_arguments)]
fn block_sort_pass(
    // Read only; `&mut` because the kernel's buffers swap roles from pass to pass.
    keys_in: &mut [u32],
    values_in: &mut [u32],
    keys_out: &mut [u32],
    values_out: &mut [u32],
    counts: &mut Shared<[u32]>,
    totals: &mut Shared<[u32]>,
    start: u32,
    end: u32,
    shift: u32,
) {
    let unit = UNIT_POS;
    let mut hist = Array::<u32>::new(HIST_LEN);
    for d in 0..RADIX_DIGITS {
        hist[d as usize] = 0u32;
    }
    for i in start..end {
        let digit = (keys_in[i as usize] >> shift) & DIGIT_MASK;
        hist[digit as usize] += 1u32;
    }
    for d in 0..RADIX_DIGITS {
        counts[(d * BLOCK_SORT_THREADS + unit) as usize] = hist[d as usize];
    }
    sync_cube();
    // Exclusive scan of the digit-major counts: each thread its run, one thread the runs'
    // totals, then each thread adds its run's offset.
    let run = unit * RADIX_DIGITS;
    let mut running = 0u32;
    for r in 0..RADIX_DIGITS {
        let value = counts[(run + r) as usize];
        counts[(run + r) as usize] = running;
        running += value;
    }
    totals[unit as usize] = running;
    sync_cube();
    if unit == 0 {
        let mut sum = 0u32;
        for t in 0..BLOCK_SORT_THREADS {
            let total = totals[t as usize];
            totals[t as usize] = sum;
            sum += total;
        }
    }
    sync_cube();
    let offset = totals[unit as usize];
    for r in 0..RADIX_DIGITS {
        counts[(run + r) as usize] += offset;
    }
    sync_cube();
    let mut next = Array::<u32>::new(HIST_LEN);
    for d in 0..RADIX_DIGITS {
        next[d as usize] = counts[(d * BLOCK_SORT_THREADS + unit) as usize];
    }
    for i in start..end {
        let key = keys_in[i as usize];
        let digit = (key >> shift) & DIGIT_MASK;
        let at = next[digit as usize];
        keys_out[at as usize] = key;
        values_out[at as usize] = values_in[i as usize];
        next[digit as usize] = at + 1u32;
    }
    // The next pass reads what every thread of the cube wrote, and reuses `counts`.
    sync_storage();
    sync_cube();
}

/// Every pass of the sort of `n ≤ BLOCK_SORT_MAX` pairs in one cube of `BLOCK_SORT_THREADS`
/// threads (module docs): even passes read `keys`/`values` and write the `_alt` buffers, odd
/// passes the other way round.
#[cube(launch)]
fn radix_sort_block(
    keys: &mut [u32],
    values: &mut [u32],
    keys_alt: &mut [u32],
    values_alt: &mut [u32],
    n: u32,
    passes: u32,
) {
    let mut counts = Shared::<[u32]>::new_slice(BLOCK_SORT_COUNTS);
    let mut totals = Shared::<[u32]>::new_slice(BLOCK_SORT_THREADS as usize);
    let per = n.div_ceil(BLOCK_SORT_THREADS);
    let start = min(UNIT_POS * per, n);
    let end = min(start + per, n);
    for pass in 0..passes {
        let shift = RADIX_BITS * pass;
        if pass % 2 == 0 {
            block_sort_pass(
                keys,
                values,
                keys_alt,
                values_alt,
                &mut counts,
                &mut totals,
                start,
                end,
                shift,
            );
        } else {
            block_sort_pass(
                keys_alt,
                values_alt,
                keys,
                values,
                &mut counts,
                &mut totals,
                start,
                end,
                shift,
            );
        }
    }
}

/// Stably sorts the first `n` `(key, value)` pairs by the low `bits` bits of the key. Returns
/// the handles holding the sorted keys and values (the inputs, or fresh buffers).
pub(crate) fn radix_sort_pairs(
    client: &ComputeClient,
    keys: Handle,
    values: Handle,
    n: usize,
    bits: u32,
) -> (Handle, Handle) {
    if n <= 1 || bits == 0 {
        return (keys, values);
    }
    let passes = bits.div_ceil(RADIX_BITS);
    if n <= BLOCK_SORT_MAX {
        let (keys_alt, values_alt) = (empty_u32(client, n), empty_u32(client, n));
        radix_sort_block::launch(
            client,
            CubeCount::Static(1, 1, 1),
            CubeDim::new_1d(BLOCK_SORT_THREADS),
            arg(&keys, n),
            arg(&values, n),
            arg(&keys_alt, n),
            arg(&values_alt, n),
            n as u32,
            passes,
        );
        return if passes.is_multiple_of(2) {
            (keys, values)
        } else {
            (keys_alt, values_alt)
        };
    }
    let num_chunks = n.div_ceil(SORT_CHUNK as usize);
    let counts_len = RADIX_DIGITS as usize * num_chunks;
    let counts = empty_u32(client, counts_len);
    let (mut keys, mut values) = (keys, values);
    let (mut keys_alt, mut values_alt) = (empty_u32(client, n), empty_u32(client, n));
    for pass in 0..passes {
        let shift = RADIX_BITS * pass;
        radix_count::launch(
            client,
            count_1d(num_chunks),
            CubeDim::new_1d(THREADS_1D),
            arg(&keys, n),
            arg(&counts, counts_len),
            n as u32,
            shift,
            num_chunks as u32,
        );
        exclusive_scan(client, &counts, counts_len);
        radix_scatter::launch(
            client,
            count_1d(num_chunks),
            CubeDim::new_1d(THREADS_1D),
            arg(&keys, n),
            arg(&values, n),
            arg(&counts, counts_len),
            arg(&keys_alt, n),
            arg(&values_alt, n),
            n as u32,
            shift,
            num_chunks as u32,
        );
        std::mem::swap(&mut keys, &mut keys_alt);
        std::mem::swap(&mut values, &mut values_alt);
    }
    (keys, values)
}

/// Number of bits needed to hold every value in `0..=max`.
pub(crate) fn bits_for(max: u32) -> u32 {
    32 - max.leading_zeros()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn client() -> Option<ComputeClient> {
        let device = crate::testing::wgpu_test_device()?;
        match device.as_dispatch() {
            burn::backend::DispatchDevice::Cube(cube) => Some(cube.client()),
            _ => None,
        }
    }

    fn read(client: &ComputeClient, handle: Handle, n: usize) -> Vec<u32> {
        let bytes = client.read_one(handle).unwrap();
        bytes[..4 * n]
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    }

    /// The one-cube scan (short arrays) and the multi-level one (long arrays, whose upper
    /// levels are one-cube scans) both give the exact exclusive prefix sum, at the sizes around
    /// the switch.
    #[test]
    fn exclusive_scan_is_exact_on_both_paths() {
        let Some(client) = client() else { return };
        let mut rng = Rng::new(5);
        for n in [
            1,
            2,
            255,
            257,
            BLOCK_SCAN_MAX - 1,
            BLOCK_SCAN_MAX,
            BLOCK_SCAN_MAX + 1,
            300_001,
        ] {
            let values: Vec<u32> = (0..n).map(|_| rng.below(17) as u32).collect();
            let handle = client.create_from_slice(&crate::cube::host::u32_bytes(&values));
            exclusive_scan(&client, &handle, n);
            let mut expected = Vec::with_capacity(n);
            let mut sum = 0u32;
            for v in &values {
                expected.push(sum);
                sum += v;
            }
            assert!(read(&client, handle, n) == expected, "n = {n}");
        }
    }

    /// The radix sort is a stable sort on the low `bits` bits, as the rasterizer needs, on both
    /// paths: one cube (up to `BLOCK_SORT_MAX` pairs; an even and an odd number of passes;
    /// fewer pairs than threads) and the multi-launch one.
    #[test]
    fn radix_sort_is_stable() {
        let Some(client) = client() else { return };
        let mut rng = Rng::new(9);
        for (n, bits) in [
            (1000, 32),
            (100_003, 32),
            (70_000, 6),
            (BLOCK_SORT_MAX, 32),
            (BLOCK_SORT_MAX + 1, 32),
            (BLOCK_SORT_MAX - 1, 5),
            (130, 8),
            (3, 32),
        ] {
            let keys: Vec<u32> = (0..n)
                .map(|_| {
                    (rng.next_u64() as u32)
                        & if bits == 32 {
                            u32::MAX >> 12
                        } else {
                            (1 << bits) - 1
                        }
                })
                .collect();
            let ids: Vec<u32> = (0..n as u32).collect();
            let (k, v) = radix_sort_pairs(
                &client,
                client.create_from_slice(&crate::cube::host::u32_bytes(&keys)),
                client.create_from_slice(&crate::cube::host::u32_bytes(&ids)),
                n,
                bits,
            );
            let mut expected: Vec<(u32, u32)> = keys.iter().copied().zip(ids).collect();
            expected.sort_by_key(|&(key, _)| key);
            let (ek, ev): (Vec<u32>, Vec<u32>) = expected.into_iter().unzip();
            assert!(read(&client, k, n) == ek, "keys, n = {n}");
            assert!(read(&client, v, n) == ev, "values (stability), n = {n}");
        }
    }
}
