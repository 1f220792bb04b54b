//! Atomic file output: write to a temporary file beside the target, then rename.

use std::path::{Path, PathBuf};

/// Suffix of every temporary file of an atomic write: recognisable, so that files left by a
/// killed process can be found and removed ([`clean_stale_temps`]).
pub const TEMP_SUFFIX: &str = ".grainpipe-tmp";

/// A temporary path in the same directory as `path` (so the final rename is atomic):
/// `.<name>.<pid>.<nanos>.grainpipe-tmp`.
pub fn temp_path_for(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let unique = format!(
        ".{name}.{}.{}{TEMP_SUFFIX}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0)
    );
    path.with_file_name(unique)
}

/// When this process first wrote a file; temporary files older than that cannot be ours.
fn process_epoch() -> std::time::SystemTime {
    static EPOCH: std::sync::OnceLock<std::time::SystemTime> = std::sync::OnceLock::new();
    *EPOCH.get_or_init(std::time::SystemTime::now)
}

/// Whether the process that made a temporary file may still be writing it. On Linux the pid
/// in the name is looked up in /proc; elsewhere a file is presumed live for an hour.
fn writer_may_be_alive(name: &str, modified: std::time::SystemTime) -> bool {
    let pid = name
        .strip_suffix(TEMP_SUFFIX)
        .and_then(|s| s.rsplit('.').nth(1))
        .and_then(|p| p.parse::<u32>().ok());
    if pid == Some(std::process::id()) {
        return true;
    }
    if Path::new("/proc/self").exists() {
        return pid.is_some_and(|p| Path::new(&format!("/proc/{p}")).exists());
    }
    modified
        .elapsed()
        .map(|age| age < std::time::Duration::from_secs(3600))
        .unwrap_or(true)
}

/// Removes the temporary files a killed grainpipe left in `dir`: files with
/// [`TEMP_SUFFIX`] older than this process whose writer is gone. Each directory is
/// scanned once per process (a cache directory can hold thousands of entries). Returns how
/// many files were removed.
pub fn clean_stale_temps(dir: &Path) -> usize {
    static SCANNED: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());
    let epoch = process_epoch();
    {
        let mut seen = SCANNED.lock().unwrap_or_else(|e| e.into_inner());
        if seen.iter().any(|d| d == dir) {
            return 0;
        }
        seen.push(dir.to_path_buf());
    }
    let Ok(entries) = std::fs::read_dir(if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    }) else {
        return 0;
    };
    let mut removed = 0;
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if !name.ends_with(TEMP_SUFFIX) {
            continue;
        }
        let Ok(meta) = e.metadata() else { continue };
        let Ok(modified) = meta.modified() else {
            continue;
        };
        if meta.is_file() && modified < epoch && !writer_may_be_alive(&name, modified) {
            removed += usize::from(std::fs::remove_file(e.path()).is_ok());
        }
    }
    removed
}

/// Set by the interrupt handler (`pipe run`'s Ctrl-C) so that long writes stop: streaming
/// exporters poll [`interrupted`] between blocks and fail, which removes their temporary
/// file. Stages see the interrupt through their reporter; this flag is for writers, which
/// have no reporter.
static INTERRUPTED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Asks running writes to stop (see [`interrupted`]).
pub fn request_interrupt() {
    INTERRUPTED.store(true, std::sync::atomic::Ordering::SeqCst);
}

/// Whether an interrupt was requested ([`request_interrupt`]).
pub fn interrupted() -> bool {
    INTERRUPTED.load(std::sync::atomic::Ordering::SeqCst)
}

/// The message of a write stopped by an interrupt; the engine reports such a failure as an
/// interruption (exit 130), not as a failed export.
pub const INTERRUPTED_MESSAGE: &str = "interrupted";

/// `Err(INTERRUPTED_MESSAGE)` once an interrupt was requested: for writers' loops.
pub fn check_interrupt() -> Result<(), String> {
    if interrupted() {
        Err(INTERRUPTED_MESSAGE.into())
    } else {
        Ok(())
    }
}

/// Temporary files and directories being written by this process right now.
static LIVE: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());

/// Registers a temporary path as being written (removed by [`remove_live_temps`] when the
/// process is made to exit), until [`temp_done`].
pub fn temp_started(p: &Path) {
    LIVE.lock()
        .unwrap_or_else(|e| e.into_inner())
        .push(p.to_path_buf());
}

/// The temporary path is renamed or removed: no longer ours to clean up.
pub fn temp_done(p: &Path) {
    LIVE.lock()
        .unwrap_or_else(|e| e.into_inner())
        .retain(|x| x != p);
}

/// Removes every temporary file and directory this process is writing: called by an
/// interrupt handler just before it exits (a second Ctrl-C), so that no `.grainpipe-tmp`
/// is left behind. Returns how many were removed.
pub fn remove_live_temps() -> usize {
    let live = std::mem::take(&mut *LIVE.lock().unwrap_or_else(|e| e.into_inner()));
    live.iter()
        .filter(|p| {
            if p.is_dir() {
                std::fs::remove_dir_all(p).is_ok()
            } else {
                std::fs::remove_file(p).is_ok()
            }
        })
        .count()
}

/// Removes the temporary files and directories that killed writers of `target` left beside
/// it (`.<name>.<pid>.<nanos>.grainpipe-tmp` whose writer is gone), whatever their age: run
/// by every export of `target` before it writes, so a killed export's leftovers (a 1.5 GB
/// STL, a directory of slices) go with the next run of that export. Returns how many were
/// removed.
pub fn clean_stale_temps_of(target: &Path) -> usize {
    let Some(name) = target.file_name().map(|n| n.to_string_lossy().into_owned()) else {
        return 0;
    };
    let dir = target
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let prefix = format!(".{name}.");
    let mut removed = 0;
    for e in entries.flatten() {
        let entry = e.file_name().to_string_lossy().into_owned();
        let Some(rest) = entry
            .strip_prefix(&prefix)
            .and_then(|r| r.strip_suffix(TEMP_SUFFIX))
        else {
            continue;
        };
        // `<pid>.<nanos>`: exactly this target's temporaries, not those of `name.x`.
        let mut parts = rest.split('.');
        let ours = matches!(
            (parts.next(), parts.next(), parts.next()),
            (Some(a), Some(b), None) if a.parse::<u32>().is_ok() && b.parse::<u128>().is_ok()
        );
        if !ours {
            continue;
        }
        let Ok(meta) = std::fs::symlink_metadata(e.path()) else {
            continue;
        };
        let modified = meta.modified().unwrap_or(std::time::SystemTime::UNIX_EPOCH);
        if writer_may_be_alive(&entry, modified) {
            continue;
        }
        let gone = if meta.is_dir() {
            std::fs::remove_dir_all(e.path())
        } else {
            std::fs::remove_file(e.path())
        };
        removed += usize::from(gone.is_ok());
    }
    removed
}

/// Runs `write` on a temporary path, then renames it to `path`. On error the temporary file
/// is removed and `path` is left untouched, so a crash never leaves a half-written file that
/// looks valid. The temporary file is flushed to disk before the rename (a power loss after
/// the rename must not leave an empty file under the final name). An existing target that
/// is not a regular file (a device node, FIFO, socket, directory) is refused: the rename
/// would replace the node itself.
pub fn atomic_write<E: std::fmt::Display>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<(), String> {
    process_epoch();
    if let Ok(meta) = std::fs::metadata(path) {
        if !meta.is_file() {
            return Err(format!(
                "{} exists and is not a regular file; refusing to replace it",
                path.display()
            ));
        }
    }
    if let Some(dir) = path.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir)
                .map_err(|e| format!("cannot create directory {}: {e}", dir.display()))?;
        }
        clean_stale_temps(dir);
    }
    clean_stale_temps_of(path);
    let tmp = temp_path_for(path);
    temp_started(&tmp);
    let result = write_and_rename(path, &tmp, write);
    temp_done(&tmp);
    result
}

fn write_and_rename<E: std::fmt::Display>(
    path: &Path,
    tmp: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<(), String> {
    let tmp = tmp.to_path_buf();
    let synced = |tmp: &Path| -> Result<(), String> {
        std::fs::File::open(tmp)
            .and_then(|f| f.sync_all())
            .map_err(|e| format!("cannot flush {}: {e}", tmp.display()))
    };
    match write(&tmp)
        .map_err(|e| e.to_string())
        .and_then(|()| synced(&tmp))
    {
        Ok(()) => std::fs::rename(&tmp, path).map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            format!("cannot move {} to {}: {e}", tmp.display(), path.display())
        }),
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            Err(format!("writing {}: {e}", path.display()))
        }
    }
}

/// Writes bytes atomically.
pub fn atomic_write_bytes(path: &Path, bytes: &[u8]) -> Result<(), String> {
    atomic_write(path, |tmp| std::fs::write(tmp, bytes))
}

/// BLAKE3 of a file's bytes, or of a directory's files (relative names and contents, in
/// sorted order, recursively), as hex. Identifies an input by content, not by path or time.
pub fn content_hash(path: &Path) -> std::io::Result<String> {
    let mut h = blake3::Hasher::new();
    hash_into(path, Path::new(""), &mut h)?;
    Ok(h.finalize().to_hex().to_string())
}

fn hash_into(path: &Path, relative: &Path, h: &mut blake3::Hasher) -> std::io::Result<()> {
    let meta = std::fs::metadata(path)?;
    if meta.is_dir() {
        let mut entries: Vec<_> = std::fs::read_dir(path)?
            .map(|e| e.map(|e| e.file_name()))
            .collect::<Result<_, _>>()?;
        entries.sort();
        for name in entries {
            hash_into(&path.join(&name), &relative.join(&name), h)?;
        }
    } else {
        h.update(relative.to_string_lossy().as_bytes());
        h.update(&meta.len().to_le_bytes());
        h.update_reader(std::fs::File::open(path)?)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failed_write_leaves_no_file() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("out.bin");
        let r = atomic_write(&target, |tmp| {
            std::fs::write(tmp, b"partial").unwrap();
            Err("simulated crash")
        });
        assert!(r.is_err());
        assert!(!target.exists());
        assert_eq!(
            std::fs::read_dir(dir.path()).unwrap().count(),
            0,
            "temp file left behind"
        );
        atomic_write_bytes(&target, b"ok").unwrap();
        assert_eq!(std::fs::read(&target).unwrap(), b"ok");
    }

    #[test]
    fn stale_temp_files_of_dead_writers_are_removed_live_ones_kept() {
        let dir = tempfile::tempdir().unwrap();
        process_epoch();
        // pid 0 never names a live writer in /proc; our own pid always does
        let dead = dir.path().join(format!(".a.vti.0.1{TEMP_SUFFIX}"));
        let mine = dir
            .path()
            .join(format!(".b.vti.{}.1{TEMP_SUFFIX}", std::process::id()));
        let other = dir.path().join(".c.vti.0.1.tmp");
        for p in [&dead, &mine, &other] {
            std::fs::write(p, b"x").unwrap();
            let old = std::time::SystemTime::now() - std::time::Duration::from_secs(7200);
            std::fs::File::options()
                .write(true)
                .open(p)
                .unwrap()
                .set_modified(old)
                .unwrap();
        }
        atomic_write_bytes(&dir.path().join("new.bin"), b"ok").unwrap();
        assert!(!dead.exists(), "stale temp file kept");
        assert!(mine.exists(), "a live writer's temp file removed");
        assert!(other.exists(), "a file that is not ours removed");
    }

    #[cfg(unix)]
    #[test]
    fn non_regular_targets_are_never_replaced() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe");
        let ok = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .map(|s| s.success())
            .unwrap_or(false);
        let sub = dir.path().join("sub");
        std::fs::create_dir(&sub).unwrap();
        let e = atomic_write_bytes(&sub, b"x").unwrap_err();
        assert!(e.contains("not a regular file"), "{e}");
        if ok {
            let e = atomic_write_bytes(&fifo, b"x").unwrap_err();
            assert!(e.contains("not a regular file"), "{e}");
            use std::os::unix::fs::FileTypeExt;
            assert!(std::fs::metadata(&fifo).unwrap().file_type().is_fifo());
        }
    }

    #[test]
    fn content_hash_follows_bytes_and_names_not_times() {
        let d = tempfile::tempdir().unwrap();
        let f = d.path().join("a.txt");
        std::fs::write(&f, "one").unwrap();
        let h1 = super::content_hash(&f).unwrap();
        std::fs::write(&f, "one").unwrap();
        assert_eq!(
            super::content_hash(&f).unwrap(),
            h1,
            "rewriting the same bytes"
        );
        std::fs::write(&f, "two").unwrap();
        assert_ne!(super::content_hash(&f).unwrap(), h1);
        // A directory: renaming a file inside changes the hash, as does adding one.
        let h_dir = super::content_hash(d.path()).unwrap();
        std::fs::rename(&f, d.path().join("b.txt")).unwrap();
        let h_renamed = super::content_hash(d.path()).unwrap();
        assert_ne!(h_renamed, h_dir);
        std::fs::write(d.path().join("c.txt"), "").unwrap();
        assert_ne!(super::content_hash(d.path()).unwrap(), h_renamed);
        assert!(super::content_hash(&d.path().join("missing")).is_err());
    }
}
