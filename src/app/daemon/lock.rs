//! One service per calibration store: the lock file `imucald.lock` in `daemon.calibration_dir`,
//! held with the operating system's advisory lock (`flock(2)`, Unix) for as long as the service
//! runs, with the holder's process id inside. The lock goes with the
//! process (a `kill -9` frees it), so a stale file never blocks a start; a second service on the
//! same store stops at start with [`Error::StoreLocked`] naming the holder.

use crate::error::Error;
use std::io::{Read, Seek, Write};
use std::path::Path;

/// The lock file's name in the calibration directory.
pub const LOCK_FILE: &str = "imucald.lock";

/// The store's lock, held while this value lives.
#[derive(Debug)]
pub struct StoreLock {
    /// The lock file (none when it could not be made: a store this process may not write).
    file: Option<std::fs::File>,
    /// This process's id was written into it.
    writable: bool,
}

impl StoreLock {
    /// Take the lock of the store in `dir` (made when missing), writing this process's id into
    /// it; [`Error::StoreLocked`] with the holder's id when another process holds it.
    pub fn take(dir: &Path) -> Result<StoreLock, Error> {
        let write_err = |path: &Path| {
            let path = path.to_path_buf();
            move |source| Error::Write { path, source }
        };
        std::fs::create_dir_all(dir).map_err(write_err(dir))?;
        let path = dir.join(LOCK_FILE);
        let opened = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path);
        let (mut file, writable) = match opened {
            Ok(f) => (f, true),
            // A store this process may not write (nothing will be written there either): locked
            // through the file read only when it is there, else not at all.
            Err(e) if read_only(&e) => match std::fs::File::open(&path) {
                Ok(f) => (f, false),
                Err(_) => {
                    tracing::warn!(
                        "{}: cannot be made ({e}); the store is not locked",
                        path.display()
                    );
                    return Ok(StoreLock {
                        file: None,
                        writable: false,
                    });
                }
            },
            Err(e) => return Err(write_err(&path)(e)),
        };
        if !try_lock(&file).map_err(write_err(&path))? {
            let mut text = String::new();
            let _ = file.read_to_string(&mut text);
            let holder = text.trim().parse::<u32>().ok();
            return Err(Error::StoreLocked { path, holder });
        }
        if writable {
            file.set_len(0).map_err(write_err(&path))?;
            file.rewind().map_err(write_err(&path))?;
            writeln!(file, "{}", std::process::id()).map_err(write_err(&path))?;
            file.sync_data().map_err(write_err(&path))?;
        }
        Ok(StoreLock {
            file: Some(file),
            writable,
        })
    }
}

impl Drop for StoreLock {
    /// The id emptied; the lock goes with the file's descriptor, closed right after.
    fn drop(&mut self) {
        if let Some(f) = self.file.as_ref().filter(|_| self.writable) {
            let _ = f.set_len(0);
        }
    }
}

/// Whether opening for writing failed for want of permission (a read-only store).
fn read_only(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        std::io::ErrorKind::PermissionDenied | std::io::ErrorKind::ReadOnlyFilesystem
    )
}

/// Take the exclusive advisory lock on `file` without waiting: `true` taken, `false` held by
/// another open file (another process, or another service in this one).
#[cfg(unix)]
fn try_lock(file: &std::fs::File) -> std::io::Result<bool> {
    use std::os::fd::AsRawFd;
    // SAFETY: flock(2) reads only its two integer arguments and touches no memory of ours; the
    // descriptor is `file`'s, open for the whole call.
    let r = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
    if r == 0 {
        return Ok(true);
    }
    let e = std::io::Error::last_os_error();
    if e.raw_os_error() == Some(libc::EWOULDBLOCK) {
        Ok(false)
    } else {
        Err(e)
    }
}

/// Without `flock` (not Unix) the lock file only records the holder: nothing stops a second
/// service.
#[cfg(not(unix))]
fn try_lock(_file: &std::fs::File) -> std::io::Result<bool> {
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_holder_is_refused_with_the_first_ones_id_until_it_lets_go() {
        let dir = tempfile::tempdir().unwrap();
        let store = dir.path().join("cal");
        let first = StoreLock::take(&store).unwrap();
        let text = std::fs::read_to_string(store.join(LOCK_FILE)).unwrap();
        assert_eq!(text.trim(), std::process::id().to_string());
        match StoreLock::take(&store) {
            Err(Error::StoreLocked { path, holder }) => {
                assert_eq!(path, store.join(LOCK_FILE));
                assert_eq!(holder, Some(std::process::id()));
            }
            other => panic!("{other:?}"),
        }
        drop(first);
        assert!(StoreLock::take(&store).is_ok());
    }
}
