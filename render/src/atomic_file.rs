//! Writing a file so that a reader sees either its old or its new contents, never a truncated
//! mix: the one place the workspace does it (avatars, trained-model checkpoints, reports,
//! pictures: [`write_png`] encodes in memory first).
//!
//! The bytes go to a temporary file in the target's own folder (a rename is atomic only
//! within one file system), are flushed to disk, and the temporary file is then renamed over
//! the target. If anything fails, the temporary file is removed and the target is untouched.
//! A process killed while writing leaves its temporary file behind (nothing runs on `SIGKILL`);
//! [`remove_stale_temporaries`] is how the next writer of the folder clears them.

use std::io::Write;
use std::path::Path;

/// The prefix and suffix of [`write_atomic`]'s temporary files.
const TEMPORARY: (&str, &str) = (".lifegom-", ".tmp");

/// Removes the temporary files [`write_atomic`] left in `dir` and its subfolders, `depth` levels
/// down, when a writer was killed mid-write; returns how many. Call it only where no other
/// process writes (a run's folder, by the process that owns it). A missing `dir` has none.
pub fn remove_stale_temporaries(dir: &Path, depth: usize) -> std::io::Result<usize> {
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
        Err(e) => return Err(e),
    };
    let mut removed = 0;
    for entry in entries {
        let entry = entry?;
        let path = entry.path();
        let kind = entry.file_type()?;
        let name = entry.file_name();
        let name = name.to_string_lossy();
        if kind.is_dir() && depth > 0 {
            removed += remove_stale_temporaries(&path, depth - 1)?;
        } else if kind.is_file() && name.starts_with(TEMPORARY.0) && name.ends_with(TEMPORARY.1) {
            std::fs::remove_file(&path)?;
            removed += 1;
        }
    }
    Ok(removed)
}

/// Writes `bytes` to `path` atomically, creating the parent folder if needed.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(dir)?;
    let mut tmp = tempfile::Builder::new()
        .prefix(TEMPORARY.0)
        .suffix(TEMPORARY.1)
        .tempfile_in(dir)?;
    tmp.write_all(bytes)?;
    tmp.as_file().sync_all()?;
    tmp.persist(path).map_err(|e| e.error)?;
    Ok(())
}

/// Encodes `pixels` (`width × height`, `color` layout) as a PNG in memory and writes it with
/// [`write_atomic`]: on a full disk the previous picture stays whole.
pub fn write_png(
    path: &Path,
    pixels: &[u8],
    width: u32,
    height: u32,
    color: image::ExtendedColorType,
) -> image::ImageResult<()> {
    let mut png = Vec::new();
    image::ImageEncoder::write_image(
        image::codecs::png::PngEncoder::new(&mut png),
        pixels,
        width,
        height,
        color,
    )?;
    write_atomic(path, &png).map_err(image::ImageError::IoError)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replaces_whole_files_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("nested").join("file.bin");
        write_atomic(&path, b"one").unwrap();
        write_atomic(&path, b"two!").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"two!");
        let names: Vec<String> = std::fs::read_dir(path.parent().unwrap())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["file.bin"]);
    }

    #[test]
    fn a_failed_write_leaves_the_target_alone() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("target");
        std::fs::create_dir(&target).unwrap(); // renaming a file over a folder fails
        assert!(write_atomic(&target, b"x").is_err());
        assert!(target.is_dir());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    /// What a killed writer leaves (its temporary file, `depth` levels down or deeper) is
    /// removed down to `depth` and no further; files that only look alike, and the targets, stay.
    #[test]
    fn stale_temporaries_are_removed_down_to_the_depth() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        let keep = [
            root.join("latest.lgck"),
            root.join("snapshots").join("step.png"),
            root.join("snapshots").join(".lifegom-notes.txt"),
            root.join("a").join("b").join(".lifegom-deep.tmp"),
        ];
        let stale = [
            root.join(".lifegom-1.tmp"),
            root.join("snapshots").join(".lifegom-2.tmp"),
        ];
        for path in keep.iter().chain(&stale) {
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(path, b"x").unwrap();
        }
        assert_eq!(remove_stale_temporaries(root, 1).unwrap(), 2);
        assert!(
            keep.iter().all(|p| p.exists()),
            "a file that is not stale went"
        );
        assert!(
            stale.iter().all(|p| !p.exists()),
            "a stale temporary stayed"
        );
        assert_eq!(
            remove_stale_temporaries(&root.join("missing"), 1).unwrap(),
            0
        );
    }
}
