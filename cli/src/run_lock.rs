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
        use std::io::BufRead;
        let dir = tempfile::tempdir().unwrap();
        let mut holder = std::process::Command::new(std::env::current_exe().unwrap())
            .args([
                "--exact",
                "run_lock::tests::hold_the_lock_for_a_minute",
                "--ignored",
                "--test-threads=1",
                "--nocapture",
            ])
            .env(HOLDER_DIR, dir.path())
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        // Probing with `acquire` would take the lock whenever the holder has not yet, and a
        // holder refused then would die; the holder says on its stdout when it holds the lock.
        // (libtest may print its "test … ..." prefix on the same line.) The wait is for that line
        // or for the pipe's end (the holder gone): a file polled for 60 s once ran out under
        // load ("the holder never took the lock", cause not found), so the only deadline left
        // is one against a hang.
        let stdout = holder.stdout.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let ready = std::io::BufReader::new(stdout)
                .lines()
                .map_while(Result::ok)
                .any(|line| line.contains(HOLDER_READY));
            let _ = tx.send(ready);
        });
        match rx.recv_timeout(std::time::Duration::from_secs(600)) {
            Ok(true) => {}
            Ok(false) => panic!("the holder ended before taking the lock"),
            Err(_) => {
                let _ = holder.kill();
                panic!("the holder did not take the lock in 10 minutes");
            }
        }
        let e = RunLock::acquire(dir.path()).unwrap_err().to_string();
        assert!(e.contains(&format!("process {}", holder.id())), "{e}");
        holder.kill().unwrap(); // SIGKILL
        holder.wait().unwrap();
        acquire_soon(dir.path()).expect("no lock left by a killed holder");
    }

    const HOLDER_DIR: &str = "LIFEGOM_TEST_LOCK_HOLDER_DIR";
    /// Printed by the holder once it holds the lock.
    const HOLDER_READY: &str = "lifegom-test-lock-holder-ready";

    /// The lock holder of [`a_killed_holder_leaves_no_lock`], run in a child process.
    #[test]
    #[ignore = "started by a_killed_holder_leaves_no_lock in a child process"]
    fn hold_the_lock_for_a_minute() {
        let Some(dir) = std::env::var_os(HOLDER_DIR) else {
            return;
        };
        let dir = Path::new(&dir);
        let _lock = acquire_soon(dir).unwrap();
        {
            use std::io::Write;
            let mut out = std::io::stdout().lock();
            writeln!(out, "{HOLDER_READY}").unwrap();
            out.flush().unwrap();
        }
        std::thread::sleep(std::time::Duration::from_secs(60));
    }
}
