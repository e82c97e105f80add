//! Structure-blind mutation fuzzing of the file readers (`.lgck`, `.lgom`, the official
//! checkpoints as `torch.save` zip and SafeTensors, configs, motion files, AIST++ capture pickles
//! and `.npz`, `subject.json` and its PNG photo and mask, the body template), bounded for CI: seeded bit flips,
//! truncations, splices of another part of the file, huge little-endian length fields, and for
//! the text formats numbers replaced by NaN, inf or huge values. Each reader must return (an
//! error naming the file, or a value), never panic, and never ask for more than
//! [`ALLOCATION_BOUND`] bytes at once (a counting global allocator records the largest request).
//! The pickle reader has its own fuzzer (`data/src/pickle/reader.rs`).
//!
//! A second test mutates the length-prefixed formats (`.lgck`, `.lgom`, SafeTensors) where
//! their structure is: every section's length field and boundaries.
//!
//! The case counts fit CI; `LIFEGOM_FUZZ_CASES=N` runs N per reader instead (a longer run:
//! `LIFEGOM_FUZZ_CASES=20000 cargo test --release --workspace --test fuzz_readers`).

#![allow(deprecated)] // Device::ndarray(): the CI backend (design.md §1.4).

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use burn::tensor::Device;
use lifegom_model::avatar::Avatar;
use lifegom_model::reconstructor::ReconstructorConfig;
use lifegom_model::trained;
use lifegom_render::motion::{JointRoles, Motion, PoseSequence};
use lifegom_render::rng::Rng;
use lifegom_render::template::{BodyTemplate, lowres_template_path};
use lifegom_tests::patterned_avatar;
use lifegom_train::config::ExperimentConfig;

/// The largest single allocation a reader may ask for while reading a damaged file: 1 GiB.
const ALLOCATION_BOUND: usize = 1 << 30;

/// The system allocator, recording the largest request.
struct Counting;

static LARGEST: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards to the system allocator unchanged; only records sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        LARGEST.fetch_max(layout.size(), Ordering::Relaxed);
        // SAFETY: the caller's contract is the system allocator's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: as above.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        LARGEST.fetch_max(new_size, Ordering::Relaxed);
        // SAFETY: as above.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

fn cases(default: usize) -> usize {
    std::env::var("LIFEGOM_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// One mutation of `base`.
fn mutate(base: &[u8], text: bool, rng: &mut Rng) -> Vec<u8> {
    let mut b = base.to_vec();
    let at = |rng: &mut Rng, len: usize| rng.below(len.max(1));
    match rng.below(if text { 6 } else { 5 }) {
        0 => {
            for _ in 0..1 + rng.below(8) {
                let i = at(rng, b.len());
                if let Some(byte) = b.get_mut(i) {
                    *byte ^= 1 << rng.below(8);
                }
            }
        }
        1 => b.truncate(at(rng, b.len())),
        2 => {
            // Splice: a run of the file copied over another place.
            let (from, to) = (at(rng, b.len()), at(rng, b.len()));
            let n = rng.below(64).min(b.len() - from.max(to));
            let run = b[from..from + n].to_vec();
            b[to..to + n].copy_from_slice(&run);
        }
        3 => {
            // A huge length field: 4 or 8 bytes of 0xff or of a large count.
            let i = at(rng, b.len());
            let word: [u8; 8] = if rng.below(2) == 0 {
                [0xff; 8]
            } else {
                (1u64 << (30 + rng.below(30))).to_le_bytes()
            };
            let n = if rng.below(2) == 0 { 4 } else { 8 };
            for (k, w) in word.iter().take(n).enumerate() {
                if let Some(byte) = b.get_mut(i + k) {
                    *byte = *w;
                }
            }
        }
        4 => {
            // Random bytes inserted.
            let i = at(rng, b.len());
            let junk: Vec<u8> = (0..1 + rng.below(32))
                .map(|_| rng.below(256) as u8)
                .collect();
            b.splice(i..i, junk);
        }
        _ => {
            // A number in the text replaced by an extreme one.
            let s = String::from_utf8_lossy(&b).into_owned();
            let digits: Vec<usize> = s
                .char_indices()
                .filter(|(_, c)| c.is_ascii_digit())
                .map(|(i, _)| i)
                .collect();
            if let Some(&i) = digits.get(at(rng, digits.len())) {
                let end = s[i..]
                    .find(|c: char| !(c.is_ascii_digit() || c == '.' || c == 'e' || c == '-'))
                    .map_or(s.len(), |k| i + k);
                let repl =
                    ["NaN", "inf", "-inf", "1e300", "-1", "99999999999", "nan"][rng.below(7)];
                b = format!("{}{}{}", &s[..i], repl, &s[end..]).into_bytes();
            }
        }
    }
    b
}

/// Fuzzes `read` on mutations of `base`, written to `path` each time. Returns the cases run.
fn fuzz<T, E: std::fmt::Display>(
    name: &str,
    base: &[u8],
    text: bool,
    path: &Path,
    n: usize,
    read: impl Fn(&Path) -> Result<T, E>,
) -> usize {
    let mut rng = Rng::new(name.len() as u64 * 7919 + 13);
    let file = path.file_name().unwrap().to_string_lossy().into_owned();
    let (mut errors, mut ok) = (0, 0);
    for case in 0..n {
        let bytes = mutate(base, text, &mut rng);
        std::fs::write(path, &bytes).unwrap();
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| read(path)));
        match outcome {
            Err(_) => panic!(
                "{name}: case {case} panicked (input kept at {})",
                path.display()
            ),
            Ok(Err(e)) => {
                let msg = e.to_string();
                assert!(
                    msg.contains(&file),
                    "{name}: case {case}: `{msg}` does not name {file}"
                );
                errors += 1;
            }
            Ok(Ok(_)) => ok += 1,
        }
    }
    eprintln!("{name}: {n} cases, {errors} errors, {ok} read, 0 panics");
    n
}

/// The structure-aware cases of a file whose sections are `u64` little-endian length fields
/// followed by that many bytes, at `fields` (each field's offset): every length set to 0, one
/// less, one more, 2^40 and `u64::MAX`, and the file cut at each field, after it, one byte
/// before its section's end, at the end and one byte past it (a byte of junk).
fn section_cases(base: &[u8], fields: &[usize]) -> Vec<Vec<u8>> {
    let mut cases = Vec::new();
    for &at in fields {
        let len = u64::from_le_bytes(base[at..at + 8].try_into().unwrap());
        for value in [0, len.saturating_sub(1), len + 1, 1 << 40, u64::MAX] {
            let mut b = base.to_vec();
            b[at..at + 8].copy_from_slice(&value.to_le_bytes());
            cases.push(b);
        }
        let end = at + 8 + len as usize;
        for cut in [at, at + 8, end.saturating_sub(1), end] {
            cases.push(base[..cut.min(base.len())].to_vec());
        }
        let mut junk = base[..end.min(base.len())].to_vec();
        junk.push(0x5a);
        cases.push(junk);
    }
    cases
}

/// Runs `read` on each of `cases`, written to `path`: no panic, and every error names the
/// file. Returns the number of cases.
fn run_cases<T, E: std::fmt::Display>(
    name: &str,
    cases: &[Vec<u8>],
    path: &Path,
    read: impl Fn(&Path) -> Result<T, E>,
) -> usize {
    let file = path.file_name().unwrap().to_string_lossy().into_owned();
    let mut errors = 0;
    for (case, bytes) in cases.iter().enumerate() {
        std::fs::write(path, bytes).unwrap();
        match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| read(path))) {
            Err(_) => panic!("{name}: section case {case} panicked"),
            Ok(Err(e)) => {
                let msg = e.to_string();
                assert!(
                    msg.contains(&file),
                    "{name}: case {case}: `{msg}` does not name {file}"
                );
                errors += 1;
            }
            Ok(Ok(_)) => {}
        }
    }
    eprintln!(
        "{name}: {} section cases, {errors} errors, 0 panics",
        cases.len()
    );
    cases.len()
}

/// The length-prefixed formats, mutated where their structure is: each section's length field
/// and each section's boundaries (module docs; the random mutations above rarely land there).
#[test]
fn section_lengths_and_boundaries_are_errors_not_panics() {
    let dir = scratch("sections");
    let device = Device::ndarray();
    let config = ReconstructorConfig::tiny(3).with_iterations(1);
    let model = config.init(1229, &device).unwrap();
    let mut total = 0;

    // `.lgck`: magic (8), version (4), then header, weights and payload, each length-prefixed.
    let lgck = dir.join("model.lgck");
    trained::save(
        &lgck,
        &model,
        &config,
        serde_json::json!({"step": 1}),
        b"payload",
    )
    .unwrap();
    let base = std::fs::read(&lgck).unwrap();
    let mut fields = vec![12usize];
    for _ in 0..2 {
        let at = *fields.last().unwrap();
        let len = u64::from_le_bytes(base[at..at + 8].try_into().unwrap()) as usize;
        fields.push(at + 8 + len);
    }
    total += run_cases(
        "lgck",
        &section_cases(&base, &fields),
        &dir.join("cut.lgck"),
        |p| trained::load(p, &device),
    );

    // `.lgom`: magic (8), then the length-prefixed JSON header.
    let avatar = patterned_avatar(&lowres_template_path(), 1, &device);
    let lgom = dir.join("avatar.lgom");
    avatar.save(&lgom).unwrap();
    let base = std::fs::read(&lgom).unwrap();
    total += run_cases(
        "lgom",
        &section_cases(&base, &[8]),
        &dir.join("cut.lgom"),
        |p| Avatar::load(p, &device),
    );

    // SafeTensors: the length-prefixed JSON header, then the data; read as an official file.
    let safetensors = dir.join("model.safetensors");
    lifegom_model::checkpoint::save_official_safetensors(&model, &safetensors).unwrap();
    let base = std::fs::read(&safetensors).unwrap();
    total += run_cases(
        "safetensors",
        &section_cases(&base, &[0]),
        &dir.join("cut.safetensors"),
        |p| trained::load_any(p, &ReconstructorConfig::tiny(3), &device),
    );

    let largest = LARGEST.load(Ordering::Relaxed);
    eprintln!("{total} section cases; largest single allocation {largest} bytes");
    assert!(
        largest <= ALLOCATION_BOUND,
        "an allocation of {largest} bytes"
    );
    std::fs::remove_dir_all(&dir).ok();
}

fn scratch(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lifegom-fuzz-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn no_reader_panics_or_overallocates_on_damaged_files() {
    let dir = scratch("readers");
    let device = Device::ndarray();
    let mut total = 0;

    // The trained-model file (.lgck) of the tiny network.
    let config = ReconstructorConfig::tiny(3).with_iterations(1);
    let model = config.init(1229, &device).unwrap();
    let lgck = dir.join("model.lgck");
    trained::save(
        &lgck,
        &model,
        &config,
        serde_json::json!({"step": 3}),
        b"payload",
    )
    .unwrap();
    let base = std::fs::read(&lgck).unwrap();
    total += fuzz(
        "lgck",
        &base,
        false,
        &dir.join("fuzz.lgck"),
        cases(150),
        |p| trained::load(p, &device),
    );

    // An avatar file (.lgom): the low-res template at one subdivision.
    let avatar = patterned_avatar(&lowres_template_path(), 1, &device);
    let lgom = dir.join("avatar.lgom");
    avatar.save(&lgom).unwrap();
    let base = std::fs::read(&lgom).unwrap();
    total += fuzz(
        "lgom",
        &base,
        false,
        &dir.join("fuzz.lgom"),
        cases(150),
        |p| Avatar::load(p, &device),
    );

    // The experiment config (TOML).
    let toml = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/synthetic-tiny.toml");
    let base = std::fs::read(&toml).unwrap();
    total += fuzz(
        "config",
        &base,
        true,
        &dir.join("fuzz.toml"),
        cases(1500),
        ExperimentConfig::load,
    );

    // A motion file.
    let motion = dir.join("walk.json");
    PoseSequence::from_motion(
        Motion::Walk,
        &JointRoles::for_rig(104).unwrap(),
        104,
        3,
        10.0,
    )
    .save(&motion)
    .unwrap();
    let base = std::fs::read(&motion).unwrap();
    total += fuzz(
        "motion",
        &base,
        true,
        &dir.join("fuzz.json"),
        cases(1500),
        |p| PoseSequence::load(p),
    );

    // An official checkpoint written by real `torch.save` (zip), and the same weights as an
    // official-format SafeTensors file, read as the commands read them.
    let fixtures = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures");
    let official = ReconstructorConfig::tiny(3);
    let base = std::fs::read(fixtures.join("official/demo-v2.pth")).unwrap();
    total += fuzz(
        "official-pth",
        &base,
        false,
        &dir.join("fuzz.pth"),
        cases(60),
        |p| trained::load_any(p, &official, &device),
    );
    let safetensors = dir.join("model.safetensors");
    lifegom_model::checkpoint::save_official_safetensors(&model, &safetensors).unwrap();
    let base = std::fs::read(&safetensors).unwrap();
    total += fuzz(
        "official-safetensors",
        &base,
        false,
        &dir.join("fuzz.safetensors"),
        cases(60),
        |p| trained::load_any(p, &official, &device),
    );

    // AIST++-style capture files: Python's pickle and numpy's compressed .npz.
    for (name, file, n) in [
        ("capture-pkl", "aist_like.pkl", 600),
        ("capture-npz", "aist_like.npz", 600),
    ] {
        let base = std::fs::read(fixtures.join("capture").join(file)).unwrap();
        let ext = Path::new(file).extension().unwrap().to_str().unwrap();
        total += fuzz(
            name,
            &base,
            false,
            &dir.join(format!("fuzz.{ext}")),
            cases(n),
            lifegom_data::capture::load,
        );
    }

    // A subject in the JSON layout (its images beside it, as shipped in data/me).
    let me = dir.join("me");
    std::fs::create_dir_all(&me).unwrap();
    let shipped = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../data/me");
    for entry in std::fs::read_dir(&shipped).unwrap() {
        let entry = entry.unwrap().path();
        std::fs::copy(&entry, me.join(entry.file_name().unwrap())).unwrap();
    }
    let base = std::fs::read(me.join("subject.json")).unwrap();
    total += fuzz(
        "subject-json",
        &base,
        true,
        &me.join("subject.json"),
        cases(300),
        lifegom_data::custom::load_subject,
    );
    std::fs::copy(shipped.join("subject.json"), me.join("subject.json")).unwrap();

    // Its photo and mask (PNG), decoded as reconstruction decodes them.
    for (name, file, n) in [
        ("photo-png", "frame_000000.png", 150),
        ("mask-png", "frame_000000_mask.png", 150),
    ] {
        let base = std::fs::read(shipped.join(file)).unwrap();
        total += fuzz(name, &base, false, &me.join(file), cases(n), |p| {
            let subject = lifegom_data::custom::load_subject(&p.with_file_name("subject.json"))?;
            lifegom_data::dataset::load_sample(&subject, &[0, 1, 2], 3, [0.0; 3], (128, 128))
        });
        std::fs::copy(shipped.join(file), me.join(file)).unwrap();
    }

    // The body template (.glb).
    let base = std::fs::read(lowres_template_path()).unwrap();
    total += fuzz(
        "template",
        &base,
        false,
        &dir.join("fuzz.glb"),
        cases(300),
        |p| BodyTemplate::load(p),
    );

    let largest = LARGEST.load(Ordering::Relaxed);
    eprintln!("{total} cases in all; largest single allocation {largest} bytes");
    assert!(
        largest <= ALLOCATION_BOUND,
        "an allocation of {largest} bytes"
    );
    std::fs::remove_dir_all(&dir).ok();
}
