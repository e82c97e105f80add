//! One run, one writer: a run folder is locked by the process training, resuming or exporting
//! it, so that a second process on the same folder stops at once instead of interleaving its
//! checkpoints and logs with the first one's.
//!
//! The lock is the operating system's advisory lock on `<run>/.lock` (`flock` on Unix,
//! `LockFileEx` on Windows, through `std::fs::File::try_lock`): it goes with the process, so a
//! holder killed with `kill -9` leaves nothing locked. The file also holds the holder's process
//! id, which is only read to name it in the error; a stale id in an unlocked file means nothing.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};

/// File name of the lock inside a run folder.
pub const LOCK_FILE: &str = ".lock";

/// An exclusive lock on a run folder, held until dropped.
#[derive(Debug)]
pub struct RunLock {
    // Never read: holding the open file holds the lock.
    _file: File,
    dir: PathBuf,
}

impl RunLock {
    /// Locks `dir` (created if missing) for this process; an error naming the folder and the
    /// holder's process id when another process holds it.
    pub fn acquire(dir: &Path) -> anyhow::Result<Self> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let path = dir.join(LOCK_FILE);
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .with_context(|| format!("opening {}", path.display()))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                let mut holder = String::new();
                let _ = file.read_to_string(&mut holder);
                let holder = holder.trim();
                bail!(
                    "the run folder {} is in use by process {} (it holds {}): one run has one \
                     writer; wait for that process to end or stop it, or use another --out",
                    dir.display(),
                    if holder.is_empty() { "?" } else { holder },
                    path.display()
                );
            }
            Err(TryLockError::Error(e)) => {
                return Err(e).with_context(|| format!("locking {}", path.display()));
            }
        }
        file.set_len(0)
            .and_then(|()| file.seek(SeekFrom::Start(0)).map(|_| ()))
            .and_then(|()| writeln!(file, "{}", std::process::id()))
            .and_then(|()| file.flush())
            .with_context(|| format!("writing {}", path.display()))?;
        Ok(Self {
            _file: file,
            dir: dir.to_path_buf(),
        })
    }

    /// The locked folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_holder_is_refused_with_the_first_ones_id() {
        let dir = tempfile::tempdir().unwrap();
        let first = RunLock::acquire(dir.path()).unwrap();
        let e = RunLock::acquire(dir.path()).unwrap_err().to_string();
        assert!(e.contains(&dir.path().display().to_string()), "{e}");
        assert!(
            e.contains(&format!("process {}", std::process::id())),
            "{e}"
        );
        drop(first);
        RunLock::acquire(dir.path()).expect("free again once dropped");
    }

    /// A holder killed with SIGKILL leaves the folder free: the lock is the kernel's.
    #[cfg(unix)]
    #[test]
    fn a_killed_holder_leaves_no_lock() {
        let dir = tempfile::tempdir().unwrap();
        let lock = dir.path().join(LOCK_FILE);
        std::fs::write(&lock, "").unwrap();
        // `flock` from util-linux takes the same lock `File::try_lock` does; `-o` keeps it out
        // of the `sleep` child, so killing `flock` kills the only holder.
        let Ok(mut holder) = std::process::Command::new("flock")
            .arg("-o")
            .arg(&lock)
            .args(["sleep", "60"])
            .spawn()
        else {
            eprintln!("`flock` (util-linux) not found: the kill -9 case is not run");
            return;
        };
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        while RunLock::acquire(dir.path()).is_ok() {
            assert!(
                std::time::Instant::now() < deadline,
                "the holder never took the lock"
            );
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        holder.kill().unwrap(); // SIGKILL
        holder.wait().unwrap();
        RunLock::acquire(dir.path()).expect("no lock left by a killed holder");
    }
}
