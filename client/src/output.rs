//! Output files that are complete or absent.
//!
//! Every file `fetch` and `fly` write (CSV, charts, overview, frames) is written under a
//! hidden temporary name beside its place and renamed into it only once complete, so a full
//! disk, a killed client or an error never leaves a file cut short or of 0 bytes; a
//! temporary file is removed when its writer is dropped. Where a file's size is bounded up
//! front ([`Output::create`] with `reserve`), its disk space is reserved when it is created,
//! so a disk too full for it is found before the work that fills it starts, not after.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use tempfile::TempPath;

/// A file being written under a temporary name; [`Output::commit`] puts it in its place.
#[derive(Debug)]
pub struct Output {
    path: PathBuf,
    writer: BufWriter<File>,
    temp: TempPath,
    written: u64,
}

/// A temporary file beside `path` named after it (`.NAME.partial-XXXXXX.EXT`: hidden, and
/// with `path`'s extension, which image encoders read).
fn temporary_beside(path: &Path) -> std::io::Result<tempfile::NamedTempFile> {
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    let name = path
        .file_name()
        .map_or_else(|| "output".into(), |n| n.to_string_lossy());
    let suffix = path
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    tempfile::Builder::new()
        .prefix(&format!(".{name}.partial-"))
        .suffix(&suffix)
        .tempfile_in(dir)
}

impl Output {
    /// Starts writing `path`, reserving `reserve` bytes of disk for it where the platform
    /// can (Linux and macOS; elsewhere, and on file systems that cannot, nothing is
    /// reserved): a disk without room for them is an error now.
    pub fn create(path: &Path, reserve: u64) -> std::io::Result<Output> {
        let (file, temp) = temporary_beside(path)?.into_parts();
        if reserve > 0 {
            reserve_space(&file, reserve)?;
        }
        Ok(Output {
            path: path.to_path_buf(),
            writer: BufWriter::new(file),
            temp,
            written: 0,
        })
    }

    /// Where the file goes once committed.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Flushes, trims what was reserved and not written, and renames the file into its
    /// place (replacing a file there).
    pub fn commit(self) -> std::io::Result<PathBuf> {
        let file = self.writer.into_inner().map_err(|e| e.into_error())?;
        file.set_len(self.written)?;
        drop(file);
        self.temp.persist(&self.path).map_err(|e| e.error)?;
        Ok(self.path)
    }
}

/// Buffered: a write the disk refuses is an error at the next flush of the buffer (8 KiB),
/// while the work goes on, not only at the end.
impl Write for Output {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        let n = self.writer.write(bytes)?;
        self.written += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.writer.flush()
    }
}

/// A file that could not be made, or put in its place.
#[derive(Debug, thiserror::Error)]
#[error("cannot write {path}")]
pub struct OutputError {
    pub path: PathBuf,
    #[source]
    pub source: std::io::Error,
}

/// Writes `path` through `write`, which is given a temporary path beside it with the same
/// extension (for writers that take a path: chart and image encoders); renamed into place
/// when `write` succeeds, removed when it fails.
pub fn write_via<T, E: From<OutputError>>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<T, E>,
) -> Result<T, E> {
    let error = |source| OutputError {
        path: path.to_path_buf(),
        source,
    };
    let temp = temporary_beside(path).map_err(error)?.into_temp_path();
    let value = write(&temp)?;
    temp.persist(path).map_err(|e| error(e.error))?;
    Ok(value)
}

/// `std::fs::write`, complete or absent: `bytes` under a temporary name, then renamed.
pub fn write_file(path: &Path, bytes: impl AsRef<[u8]>) -> std::io::Result<()> {
    let mut out = Output::create(path, 0)?;
    out.write_all(bytes.as_ref())?;
    out.commit().map(drop)
}

#[cfg(any(target_os = "linux", target_os = "android", target_os = "macos"))]
fn reserve_space(file: &File, bytes: u64) -> std::io::Result<()> {
    match rustix::fs::fallocate(file, rustix::fs::FallocateFlags::empty(), 0, bytes) {
        Ok(()) => Ok(()),
        // A file system that cannot reserve: the writes will say.
        Err(rustix::io::Errno::OPNOTSUPP | rustix::io::Errno::NOSYS) => Ok(()),
        Err(errno) => Err(errno.into()),
    }
}

#[cfg(not(any(target_os = "linux", target_os = "android", target_os = "macos")))]
fn reserve_space(_: &File, _: u64) -> std::io::Result<()> {
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .expect("dir")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn a_committed_output_holds_what_was_written_and_nothing_reserved_past_it() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("out.csv");
        let mut out = Output::create(&path, 1 << 20).expect("create");
        out.write_all(b"a,b\n1,2\n").expect("write");
        assert_eq!(names(dir.path()).len(), 1);
        assert!(!path.exists(), "not in place before the commit");
        out.commit().expect("commit");
        assert_eq!(std::fs::read(&path).expect("read"), b"a,b\n1,2\n");
        assert_eq!(names(dir.path()), vec!["out.csv".to_string()]);
    }

    #[test]
    fn an_output_dropped_before_its_commit_leaves_nothing_and_the_old_file_whole() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("out.csv");
        std::fs::write(&path, "old").expect("old file");
        let mut out = Output::create(&path, 4096).expect("create");
        out.write_all(b"new but cut short").expect("write");
        drop(out);
        assert_eq!(names(dir.path()), vec!["out.csv".to_string()]);
        assert_eq!(std::fs::read_to_string(&path).expect("read"), "old");
    }

    #[derive(Debug)]
    struct Failed;
    impl From<OutputError> for Failed {
        fn from(_: OutputError) -> Failed {
            Failed
        }
    }

    #[test]
    fn write_via_renames_what_succeeded_and_removes_what_failed() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("chart.png");
        let seen = write_via(&path, |temp| {
            assert_eq!(temp.extension().and_then(|e| e.to_str()), Some("png"));
            std::fs::write(temp, "png").map_err(|_| Failed)?;
            Ok::<_, Failed>(temp.to_path_buf())
        })
        .expect("written");
        assert!(!seen.exists());
        assert_eq!(std::fs::read_to_string(&path).expect("read"), "png");
        let failed = dir.path().join("failed.png");
        let result = write_via(&failed, |temp| {
            std::fs::write(temp, "half").map_err(|_| Failed)?;
            Err::<(), _>(Failed)
        });
        assert!(result.is_err());
        assert_eq!(names(dir.path()), vec!["chart.png".to_string()]);
    }
}
