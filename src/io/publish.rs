//! Outputs: files written atomically (temp file in the same directory, fsync, rename), the report,
//! calibrated samples and the flight-stack exports.

use crate::error::Error;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// A file being written atomically: the content goes to a fresh temporary file beside `path` (same
/// directory, so the rename is atomic; same extension, for writers that pick a format by it), which
/// [`AtomicFile::commit`] syncs to disk and renames over `path`. Dropped without a commit, the
/// temporary file is removed. A reader of `path` sees the old file or the new one, never a part.
pub(crate) struct AtomicFile {
    path: PathBuf,
    tmp: PathBuf,
    committed: bool,
}

impl AtomicFile {
    pub fn new(path: &Path) -> Result<AtomicFile, Error> {
        let name = path.file_name().ok_or_else(|| Error::Write {
            path: path.to_path_buf(),
            source: std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a file path"),
        })?;
        let dir = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let n = TMP_COUNTER.fetch_add(1, Ordering::Relaxed);
        let ext = path
            .extension()
            .map(|e| format!(".{}", e.to_string_lossy()))
            .unwrap_or_default();
        let tmp = dir.join(format!(
            ".{}.{}-{n}.tmp{ext}",
            name.to_string_lossy(),
            std::process::id()
        ));
        Ok(AtomicFile {
            path: path.to_path_buf(),
            tmp,
            committed: false,
        })
    }

    /// Where to write the content.
    pub(crate) fn temp_path(&self) -> &Path {
        &self.tmp
    }

    /// Sync the written temporary file and rename it over the destination.
    pub(crate) fn commit(mut self) -> Result<(), Error> {
        let res = std::fs::File::open(&self.tmp)
            .and_then(|f| f.sync_all())
            .and_then(|()| std::fs::rename(&self.tmp, &self.path));
        self.committed = res.is_ok();
        res.map_err(|source| Error::Write {
            path: self.path.clone(),
            source,
        })
    }
}

impl Drop for AtomicFile {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Write `path` atomically ([`AtomicFile`]) with `body` writing the content into the new file.
pub(crate) fn write_atomic_with<F>(path: &Path, body: F) -> Result<(), Error>
where
    F: FnOnce(&mut std::fs::File) -> std::io::Result<()>,
{
    let file = AtomicFile::new(path)?;
    let werr = |source| Error::Write {
        path: path.to_path_buf(),
        source,
    };
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(file.temp_path())
        .map_err(werr)?;
    body(&mut f).map_err(werr)?;
    drop(f);
    file.commit()
}

/// Write `bytes` to `path` atomically ([`AtomicFile`]).
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), Error> {
    write_atomic_with(path, |f| f.write_all(bytes))
}

/// Write a text file atomically.
pub fn write_text(path: &Path, text: &str) -> Result<(), Error> {
    write_atomic(path, text.as_bytes())
}

/// Serialise as pretty JSON and write atomically.
pub fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<(), Error> {
    let text =
        serde_json::to_string_pretty(value).map_err(|e| Error::Other(format!("json: {e}")))?;
    write_atomic(path, text.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_replaces_and_leaves_no_temp() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("cal.json");
        write_atomic(&p, b"old").unwrap();
        write_atomic(&p, b"new").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"new");
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
        assert!(write_atomic(&d.path().join("missing/dir/x"), b"x").is_err());
        // A body that fails leaves the old file and no temporary file.
        let failed = write_atomic_with(&p, |f| {
            f.write_all(b"half")?;
            Err(std::io::Error::other("disk full"))
        });
        assert!(failed.is_err());
        assert_eq!(std::fs::read(&p).unwrap(), b"new");
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
        // A path-based writer: the temporary file keeps the extension; uncommitted, it goes.
        let png = d.path().join("map.png");
        let a = AtomicFile::new(&png).unwrap();
        assert_eq!(a.temp_path().extension().unwrap(), "png");
        std::fs::write(a.temp_path(), b"x").unwrap();
        drop(a);
        assert!(!png.exists());
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
    }
}
