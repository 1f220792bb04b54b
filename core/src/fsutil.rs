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
