//! One executive per store: an exclusive lock on a file beside the database.
//!
//! Two executives on one database would each keep their own missions in
//! memory and hand out the same identities. The lock is an advisory `flock`
//! on `<database>.lock`, which the kernel releases when the holder exits, even
//! by SIGKILL, so a crash never leaves a stale lock behind. The file holds a
//! line naming the holder, for the error the next one gets.
//!
//! The lock is not taken on the database file itself: SQLite's own POSIX locks
//! on that file are dropped when any descriptor of it is closed by the process.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

use super::StoreError;

/// Held while an executive uses a store; released on drop.
#[derive(Debug)]
pub struct StoreLock {
    file: File,
    path: PathBuf,
}

impl StoreLock {
    /// Takes the lock of the database at `database`, or says who holds it.
    pub fn acquire(database: &Path) -> Result<Self, StoreError> {
        let path = lock_path(database);
        let io = |cause| StoreError::LockFile { path: path.clone(), cause };
        let mut file =
            OpenOptions::new().read(true).write(true).create(true).truncate(false).open(&path).map_err(io)?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                let mut holder = String::new();
                // The holder wrote one line; an unreadable one is still a held lock.
                let _ = file.read_to_string(&mut holder);
                let holder = holder.trim();
                let holder = if holder.is_empty() { "an unknown process" } else { holder };
                return Err(StoreError::Locked(format!(
                    "the database {} is in use by another executive ({holder}; lock file {}): stop it, or give \
                     this one another database",
                    database.display(),
                    path.display()
                )));
            }
            Err(TryLockError::Error(e)) => return Err(io(e)),
        }
        let holder = format!(
            "pid {} on host {} since {}",
            std::process::id(),
            hostname(),
            crate::domain::Timestamp::now().millis() / 1000
        );
        file.set_len(0).map_err(io)?;
        file.rewind().map_err(io)?;
        writeln!(file, "{holder} (unix seconds)").map_err(io)?;
        file.sync_all().map_err(io)?;
        Ok(Self { file, path })
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for StoreLock {
    fn drop(&mut self) {
        // Closing the file releases the lock too; say so early.
        let _ = self.file.unlock();
    }
}

/// `<database>.lock`, beside the database.
pub fn lock_path(database: &Path) -> PathBuf {
    let mut name = database.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push(".lock");
    database.with_file_name(name)
}

pub(super) fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_owned())
        .ok()
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "unknown".to_owned())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_holder_is_refused_with_the_first_ones_name_until_it_lets_go() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("x.db");
        let first = StoreLock::acquire(&db).unwrap();
        assert_eq!(first.path(), dir.path().join("x.db.lock"));
        let err = StoreLock::acquire(&db).unwrap_err().to_string();
        assert!(err.contains(&format!("pid {}", std::process::id())), "{err}");
        assert!(err.contains("x.db"), "{err}");
        drop(first);
        StoreLock::acquire(&db).unwrap();
    }
}
