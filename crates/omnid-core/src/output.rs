//! Output files: checked before a command does its work, written so that nothing is lost or
//! destroyed on the way.
//!
//! - A whole file (weights, a converted log, a summary, a report, a figure, a fault dump, the
//!   motor heat) goes to a temporary file beside its target, renamed over the target only
//!   once complete: a failed write leaves the old file as it was and no temporary behind.
//! - The target must be a regular file or a new path. A symlink is followed, as `run --log`
//!   follows it: the file it names is replaced, the link stays. A directory, device, FIFO or
//!   socket is refused: a rename would replace a node that is not ours.
//! - [`check_file`] and [`check_dir`] find an unusable path before the work starts.
//! - [`create_unique`] makes a new file under a default name, never replacing another.

use std::fs::{File, OpenOptions};
use std::io::{self, BufWriter, Write};
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use thiserror::Error;

/// Why an output file was not written.
#[derive(Debug, Error)]
pub enum OutputError {
    /// The path names something other than a regular file (a directory, a device, a FIFO, …).
    #[error("{} is {what}, not a regular file: refusing to write over it", path.display())]
    NotAFile {
        /// The path.
        path: PathBuf,
        /// What is there instead, e.g. `a directory`.
        what: &'static str,
    },
    /// The file cannot be created or opened for writing (checked before a run starts).
    #[error("cannot write {}: {source}", path.display())]
    Unwritable {
        /// The path.
        path: PathBuf,
        /// What the open said.
        source: io::Error,
    },
    /// Writing failed part-way; the file at the path is as it was.
    #[error("writing {} failed: {source} (nothing was changed there)", path.display())]
    Write {
        /// The path.
        path: PathBuf,
        /// What the write said.
        source: io::Error,
    },
}

impl OutputError {
    /// The path given is unusable (the user's input), rather than a write that failed.
    pub fn is_bad_input(&self) -> bool {
        !matches!(self, OutputError::Write { .. })
    }
}

/// `path` with the symlinks of its last component followed: the file a write reaches (it
/// need not exist).
pub(crate) fn resolve(path: &Path) -> io::Result<PathBuf> {
    let mut p = path.to_path_buf();
    for _ in 0..40 {
        match std::fs::symlink_metadata(&p) {
            Ok(m) if m.file_type().is_symlink() => {
                let target = std::fs::read_link(&p)?;
                // A relative target is relative to the link's directory.
                p = p.parent().map_or(target.clone(), |dir| dir.join(&target));
            }
            Ok(_) => return Ok(p),
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(p),
            Err(e) => return Err(e),
        }
    }
    Err(io::Error::from_raw_os_error(libc::ELOOP))
}

/// What a file type is, for messages ("a directory", …).
pub fn describe(t: std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if t.is_dir() {
        "a directory"
    } else if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else if t.is_fifo() {
        "a FIFO"
    } else if t.is_socket() {
        "a socket"
    } else if t.is_symlink() {
        "a symlink"
    } else {
        "a regular file"
    }
}

/// The resolved target of `path`, refused unless it is a regular file or missing.
fn target(path: &Path) -> Result<PathBuf, OutputError> {
    let unwritable = |source| OutputError::Unwritable {
        path: path.to_path_buf(),
        source,
    };
    let target = resolve(path).map_err(unwritable)?;
    match std::fs::symlink_metadata(&target) {
        Ok(m) if m.is_file() => Ok(target),
        Ok(m) => Err(OutputError::NotAFile {
            path: path.to_path_buf(),
            what: describe(m.file_type()),
        }),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(target),
        Err(e) => Err(unwritable(e)),
    }
}

/// The directory a file goes into ("." for a bare name).
fn dir_of(path: &Path) -> &Path {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    }
}

/// Remove from `dir` the temporaries of omnid processes that are gone (`.omnid-<pid>-<n>.tmp`,
/// left by a process killed mid-write: the file it was writing is whole, the temporary is
/// litter). A live process's temporary, and anything else, is left alone. How many went.
pub fn remove_orphan_temporaries(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let mut removed = 0;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) = name
            .to_str()
            .and_then(|n| n.strip_prefix(".omnid-"))
            .and_then(|n| n.strip_suffix(".tmp"))
            .and_then(|n| n.split_once('-'))
            .filter(|(_, k)| k.parse::<u64>().is_ok())
            .and_then(|(pid, _)| pid.parse::<i32>().ok())
        else {
            continue;
        };
        // SAFETY: kill with signal 0 only asks whether the process exists.
        let gone = pid > 0
            && unsafe { libc::kill(pid, 0) } != 0
            && io::Error::last_os_error().raw_os_error() == Some(libc::ESRCH);
        let regular = entry.file_type().is_ok_and(|t| t.is_file());
        if gone && regular && std::fs::remove_file(entry.path()).is_ok() {
            removed += 1;
        }
    }
    removed
}

/// A temporary file in `dir`, removed when dropped unless renamed into place.
struct Temp {
    path: PathBuf,
    file: File,
    placed: bool,
}

impl Temp {
    fn create(dir: &Path) -> io::Result<Temp> {
        // Unique per process and call, created exclusively: it never meets another file.
        static SEQ: AtomicU64 = AtomicU64::new(0);
        loop {
            let n = SEQ.fetch_add(1, Ordering::Relaxed);
            let path = dir.join(format!(".omnid-{}-{n}.tmp", std::process::id()));
            match OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(file) => {
                    return Ok(Temp {
                        path,
                        file,
                        placed: false,
                    })
                }
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(e),
            }
        }
    }
}

impl Drop for Temp {
    fn drop(&mut self) {
        if !self.placed {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

/// Check that a whole file can be written at `path`: the target is a regular file or new, its
/// directory exists (it is created if needed) and a file can be made there.
pub fn check_file(path: &Path) -> Result<(), OutputError> {
    let target = target(path)?;
    prepare_dir(path, dir_of(&target))
}

/// Check that files can be written in `dir` (created if needed).
pub fn check_dir(dir: &Path) -> Result<(), OutputError> {
    let target = resolve(dir).map_err(|source| OutputError::Unwritable {
        path: dir.to_path_buf(),
        source,
    })?;
    match std::fs::metadata(&target) {
        Ok(m) if !m.is_dir() => {
            return Err(OutputError::Unwritable {
                path: dir.to_path_buf(),
                source: io::Error::other(format!(
                    "it is {}, not a directory",
                    describe(m.file_type())
                )),
            })
        }
        _ => {}
    }
    prepare_dir(dir, &target)
}

/// Create `dir` if needed and prove a file can be made in it (permissions, a read-only file
/// system); errors name `path`, the output asked for.
fn prepare_dir(path: &Path, dir: &Path) -> Result<(), OutputError> {
    let unwritable = |source| OutputError::Unwritable {
        path: path.to_path_buf(),
        source,
    };
    std::fs::create_dir_all(dir).map_err(unwritable)?;
    Temp::create(dir).map(drop).map_err(unwritable)
}

/// Write the whole file at `path` (see the module notes): `fill` writes the contents; the
/// file is in place only if it and the final flush succeed. Its errors are returned as they
/// are; the temporary file is removed on every error.
pub fn write_with<T, E: From<OutputError>>(
    path: &Path,
    fill: impl FnOnce(&mut BufWriter<&File>) -> Result<T, E>,
) -> Result<T, E> {
    let target = target(path)?;
    let dir = dir_of(&target);
    let unwritable = |source| OutputError::Unwritable {
        path: path.to_path_buf(),
        source,
    };
    std::fs::create_dir_all(dir).map_err(unwritable)?;
    let mut tmp = Temp::create(dir).map_err(unwritable)?;
    let failed = |source| OutputError::Write {
        path: path.to_path_buf(),
        source,
    };
    // Replacing a file keeps its permissions.
    if let Ok(m) = std::fs::metadata(&target) {
        tmp.file.set_permissions(m.permissions()).map_err(failed)?;
    }
    let mut w = BufWriter::with_capacity(1 << 16, &tmp.file);
    let value = fill(&mut w)?;
    w.flush().map_err(failed)?;
    drop(w);
    // On the disk before the rename, so a crash leaves the old file or the new one whole.
    tmp.file.sync_all().map_err(failed)?;
    // Whatever appeared at the target meanwhile must still be a file we may replace.
    let target = self::target(path)?;
    std::fs::rename(&tmp.path, &target).map_err(failed)?;
    tmp.placed = true;
    Ok(value)
}

/// [`write_with`] for contents already in memory.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<(), OutputError> {
    write_with(path, |w| {
        w.write_all(bytes).map_err(|source| OutputError::Write {
            path: path.to_path_buf(),
            source,
        })
    })
}

/// Create a new, empty file `dir/stem.ext`, or `dir/stem-2.ext`, `-3`, … if that name is
/// taken: a default name never replaces another file (two runs started in the same second).
pub fn create_unique(dir: &Path, stem: &str, ext: &str) -> Result<(PathBuf, File), OutputError> {
    let unwritable = |path: PathBuf| move |source| OutputError::Unwritable { path, source };
    std::fs::create_dir_all(dir).map_err(unwritable(dir.to_path_buf()))?;
    for n in 1..=10_000 {
        let name = match n {
            1 => format!("{stem}.{ext}"),
            n => format!("{stem}-{n}.{ext}"),
        };
        let path = dir.join(name);
        match OpenOptions::new().write(true).create_new(true).open(&path) {
            Ok(file) => return Ok((path, file)),
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(unwritable(path)(e)),
        }
    }
    Err(unwritable(dir.join(format!("{stem}.{ext}")))(
        io::Error::other("10000 files of that name exist already"),
    ))
}

/// [`create_unique`], filled by `fill`; a file that could not be written whole is removed.
pub(crate) fn write_unique(
    dir: &Path,
    stem: &str,
    ext: &str,
    fill: impl FnOnce(&mut BufWriter<&File>) -> io::Result<()>,
) -> Result<PathBuf, OutputError> {
    let (path, file) = create_unique(dir, stem, ext)?;
    let mut w = BufWriter::with_capacity(1 << 16, &file);
    match fill(&mut w).and_then(|()| w.flush()) {
        Ok(()) => Ok(path),
        Err(source) => {
            drop(w);
            let _ = std::fs::remove_file(&path);
            Err(OutputError::Write { path, source })
        }
    }
}

/// Whether writing `a` and `b` would write the same regular file: the same inode (through
/// symlinks, hard links or different spellings), or the same new path. Devices and FIFOs are
/// never "the same file" (two outputs to /dev/null lose nothing).
pub(crate) fn same_file(a: &Path, b: &Path) -> bool {
    let (Ok(ra), Ok(rb)) = (resolve(a), resolve(b)) else {
        return false;
    };
    match (std::fs::metadata(&ra), std::fs::metadata(&rb)) {
        (Ok(ma), Ok(mb)) => {
            ma.is_file() && mb.is_file() && (ma.dev(), ma.ino()) == (mb.dev(), mb.ino())
        }
        (Err(_), Err(_)) => spelled(&ra) == spelled(&rb),
        _ => false,
    }
}

/// A new path spelled canonically: its directory's real path and its name.
fn spelled(p: &Path) -> PathBuf {
    let canonical = p
        .file_name()
        .and_then(|name| Some(dir_of(p).canonicalize().ok()?.join(name)));
    canonical.unwrap_or_else(|| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_file_is_replaced_whole_and_a_symlink_is_followed() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("w.json");
        std::fs::write(&file, "old").unwrap();
        write_bytes(&file, b"new").unwrap();
        assert_eq!(std::fs::read_to_string(&file).unwrap(), "new");

        let link = dir.path().join("link.json");
        std::os::unix::fs::symlink("w.json", &link).unwrap();
        write_bytes(&link, b"through the link").unwrap();
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert_eq!(std::fs::read_to_string(&file).unwrap(), "through the link");
        // A dangling link is followed too: its target is created.
        let dangling = dir.path().join("dangling.json");
        std::os::unix::fs::symlink("sub/new.json", &dangling).unwrap();
        write_bytes(&dangling, b"x").unwrap();
        assert_eq!(
            std::fs::read_to_string(dir.path().join("sub/new.json")).unwrap(),
            "x"
        );
        assert_eq!(
            names(dir.path()),
            ["dangling.json", "link.json", "sub", "w.json"]
        );
    }

    #[test]
    fn anything_but_a_regular_file_is_refused_and_left_alone() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("fifo");
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a valid C string; mkfifo only creates the node.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let sub = dir.path().join("sub");
        std::fs::create_dir(&sub).unwrap();
        let to_dir = dir.path().join("to-dir");
        std::os::unix::fs::symlink(&sub, &to_dir).unwrap();
        for (p, what) in [
            (&fifo, "a FIFO"),
            (&sub, "a directory"),
            (&to_dir, "a directory"),
            (&PathBuf::from("/dev/null"), "a character device"),
        ] {
            for e in [
                check_file(p).unwrap_err(),
                write_bytes(p, b"x").unwrap_err(),
            ] {
                assert!(
                    matches!(e, OutputError::NotAFile { what: w, .. } if w == what),
                    "{e}"
                );
                assert!(e.to_string().contains(&p.display().to_string()), "{e}");
                assert!(e.is_bad_input());
            }
        }
        assert_eq!(names(dir.path()), ["fifo", "sub", "to-dir"]);
        use std::os::unix::fs::FileTypeExt;
        assert!(std::fs::symlink_metadata("/dev/null")
            .unwrap()
            .file_type()
            .is_char_device());
    }

    #[test]
    fn only_the_temporaries_of_processes_that_are_gone_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        // A process that has ended (its pid is free again, unless reused this instant).
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let dead = child.id();
        child.wait().unwrap();
        let orphan = dir.path().join(format!(".omnid-{dead}-3.tmp"));
        let mine = dir
            .path()
            .join(format!(".omnid-{}-0.tmp", std::process::id()));
        let other = dir.path().join("weights-sim.json");
        let odd = dir.path().join(format!(".omnid-{dead}-x.tmp"));
        for p in [&orphan, &mine, &other, &odd] {
            std::fs::write(p, "x").unwrap();
        }
        assert_eq!(remove_orphan_temporaries(dir.path()), 1);
        assert!(!orphan.exists());
        assert!(mine.exists() && other.exists() && odd.exists());
        assert_eq!(remove_orphan_temporaries(&dir.path().join("none")), 0);
    }

    #[test]
    fn a_failed_fill_leaves_the_old_file_and_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("w.json");
        std::fs::write(&file, "old").unwrap();
        let e = write_with(&file, |w| {
            w.write_all(b"half").unwrap();
            Err::<(), _>(OutputError::Write {
                path: file.clone(),
                source: io::Error::other("disk full"),
            })
        })
        .unwrap_err();
        assert!(e.to_string().contains("disk full"), "{e}");
        assert_eq!(std::fs::read_to_string(&file).unwrap(), "old");
        assert_eq!(names(dir.path()), ["w.json"]);
    }

    #[test]
    fn checks_find_unusable_paths_and_leave_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("f");
        std::fs::write(&file, "").unwrap();
        // A path under a regular file, and a directory that is a file.
        assert!(check_file(&file.join("x.json")).is_err());
        assert!(check_dir(&file)
            .unwrap_err()
            .to_string()
            .contains("not a directory"));
        assert!(check_file(Path::new("/proc/omnid/x.json")).is_err());
        check_file(&dir.path().join("new/deeper/x.json")).unwrap();
        check_dir(&dir.path().join("figs")).unwrap();
        assert_eq!(names(dir.path()), ["f", "figs", "new"]);
        assert!(names(&dir.path().join("new/deeper")).is_empty());
    }

    #[test]
    fn default_names_never_replace_a_file() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("run.csv"), "someone's").unwrap();
        let (a, _) = create_unique(dir.path(), "run", "csv").unwrap();
        let (b, _) = create_unique(dir.path(), "run", "csv").unwrap();
        assert_eq!(a, dir.path().join("run-2.csv"));
        assert_eq!(b, dir.path().join("run-3.csv"));
        assert_eq!(
            std::fs::read_to_string(dir.path().join("run.csv")).unwrap(),
            "someone's"
        );
        let c = write_unique(dir.path(), "run", "csv", |w| w.write_all(b"x")).unwrap();
        assert_eq!(c, dir.path().join("run-4.csv"));
        let e = write_unique(dir.path(), "run", "csv", |_| Err(io::Error::other("full")));
        assert!(e.is_err());
        assert!(!dir.path().join("run-5.csv").exists());
    }

    #[test]
    fn the_same_file_is_seen_through_links_and_spellings() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("a.csv");
        std::fs::write(&a, "").unwrap();
        let sym = dir.path().join("sym.csv");
        std::os::unix::fs::symlink(&a, &sym).unwrap();
        let hard = dir.path().join("hard.csv");
        std::fs::hard_link(&a, &hard).unwrap();
        assert!(same_file(&a, &sym) && same_file(&a, &hard));
        let dotted = dir.path().join("sub/../new.json");
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        assert!(same_file(&dir.path().join("new.json"), &dotted));
        assert!(!same_file(&a, &dir.path().join("new.json")));
        assert!(!same_file(Path::new("/dev/null"), Path::new("/dev/null")));
    }
}
