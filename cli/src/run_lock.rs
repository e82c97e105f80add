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

    /// Acquires `dir`, retrying for a second: the test threads of this process spawn children,
    /// and a child between its fork and its exec shares every descriptor of the process, a
    /// just-dropped lock's too, for that moment.
    fn acquire_soon(dir: &Path) -> anyhow::Result<RunLock> {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(1);
        loop {
            match RunLock::acquire(dir) {
                Ok(lock) => return Ok(lock),
                Err(e) if std::time::Instant::now() > deadline => return Err(e),
                Err(_) => std::thread::sleep(std::time::Duration::from_millis(10)),
            }
        }
    }

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
        acquire_soon(dir.path()).expect("free again once dropped");
    }

    /// A holder killed with SIGKILL leaves the folder free: the lock is the kernel's. The
    /// holder is this test binary again, running [`hold_the_lock_for_a_minute`] (one process,
    /// no child that could share its lock).
    #[cfg(unix)]
    #[test]
    fn a_killed_holder_leaves_no_lock() {
        let dir = tempfile::tempdir().unwrap();
        let mut holder = std::process::Command::new(std::env::current_exe().unwrap())
            .args([
                "--exact",
                "run_lock::tests::hold_the_lock_for_a_minute",
                "--ignored",
                "--test-threads=1",
            ])
            .env(HOLDER_DIR, dir.path())
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        // Probing with `acquire` would take the lock whenever the holder has not yet, and a
        // holder refused then would die; the holder says when it holds the lock instead.
        let ready = dir.path().join(HOLDER_READY);
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
        while !ready.exists() {
            assert!(
                std::time::Instant::now() < deadline,
                "the holder never took the lock"
            );
            assert!(
                holder.try_wait().unwrap().is_none(),
                "the holder ended before taking the lock"
            );
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let e = RunLock::acquire(dir.path()).unwrap_err().to_string();
        assert!(e.contains(&format!("process {}", holder.id())), "{e}");
        holder.kill().unwrap(); // SIGKILL
        holder.wait().unwrap();
        acquire_soon(dir.path()).expect("no lock left by a killed holder");
    }

    const HOLDER_DIR: &str = "LIFEGOM_TEST_LOCK_HOLDER_DIR";
    /// Written by the holder once it holds the lock.
    const HOLDER_READY: &str = "holder-ready";

    /// The lock holder of [`a_killed_holder_leaves_no_lock`], run in a child process.
    #[test]
    #[ignore = "started by a_killed_holder_leaves_no_lock in a child process"]
    fn hold_the_lock_for_a_minute() {
        let Some(dir) = std::env::var_os(HOLDER_DIR) else {
            return;
        };
        let dir = Path::new(&dir);
        let _lock = acquire_soon(dir).unwrap();
        std::fs::write(dir.join(HOLDER_READY), b"").unwrap();
        std::thread::sleep(std::time::Duration::from_secs(60));
    }
}
