//! Atomic file output: write to a temporary file beside the target, then rename.

use std::path::{Path, PathBuf};

/// A temporary path in the same directory as `path` (so the final rename is atomic).
pub fn temp_path_for(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let unique = format!(
        ".{name}.{}.{}.tmp",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0)
    );
    path.with_file_name(unique)
}

/// Runs `write` on a temporary path, then renames it to `path`. On error the temporary file
/// is removed and `path` is left untouched, so a crash never leaves a half-written file that
/// looks valid.
pub fn atomic_write<E: std::fmt::Display>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<(), String> {
    if let Some(dir) = path.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir)
                .map_err(|e| format!("cannot create directory {}: {e}", dir.display()))?;
        }
    }
    let tmp = temp_path_for(path);
    match write(&tmp) {
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
