//! The content-addressed step cache: one file `<key>.bin` per step result.
//!
//! Entry layout (format 5): `GRPCACH5` | BLAKE3(key, header, payload) (32 bytes) | header
//! length (u32 LE) | header (JSON: step, stage, pipeline, creation time) | payload (postcard of
//! the outputs). The header comes first and is length-prefixed so that `pipe cache` can list
//! entries without reading multi-gigabyte payloads; the checksum covers it too, so a damaged
//! header is refused like a damaged payload. Entries of another layout are misses, never
//! errors, and are recomputed.

use crate::model::Artifact;
use crate::stage::Outputs;
use serde::{Deserialize, Serialize};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

/// Identifies the layout of cached artifacts: bump it whenever the serialized data model
/// or the entry layout changes, so entries written by an older grainpipe are recomputed
/// instead of misread. 2: field component conventions, bond attributes, collections.
/// 3: a BLAKE3 checksum of (key, payload) after the magic. 4: a header naming the step.
/// 5: body radii in contact graphs.
pub const CACHE_MAGIC: &[u8; 8] = b"GRPCACH5";

/// What wrote an entry (shown by `pipe cache`; not used to decide hits).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct EntryHeader {
    pub step: String,
    pub stage: String,
    pub pipeline: String,
    /// Seconds since the Unix epoch when the entry was written.
    pub created: u64,
}

/// The file of the entry with `key` in `dir`.
pub fn path(dir: &Path, key: &str) -> PathBuf {
    dir.join(format!("{key}.bin"))
}

/// What reading a cache entry gave.
pub enum CacheRead {
    /// No entry (the normal miss), or one written by another grainpipe layout.
    Miss,
    Hit(Outputs),
    /// An entry that exists but cannot be trusted; the reason is shown as a warning.
    Corrupt(String),
}

/// The checksum covers the key too, so an entry copied onto another step's key is refused
/// like a flipped bit, before its payload is even decoded.
fn checksum(key: &str, header: &[u8], body: &[u8]) -> blake3::Hash {
    let mut h = blake3::Hasher::new();
    h.update(key.as_bytes());
    h.update(b"\0");
    h.update(&(header.len() as u64).to_le_bytes());
    h.update(header);
    h.update(body);
    h.finalize()
}

/// (checksum, header, payload) of an entry.
type Parts<'a> = (&'a [u8], &'a [u8], &'a [u8]);

/// Splits an entry into its parts; `None` when it is not of this layout (`Some(Err)` when it
/// is, but too short to hold what it announces).
fn split(bytes: &[u8]) -> Option<Result<Parts<'_>, String>> {
    let rest = bytes.strip_prefix(CACHE_MAGIC.as_slice())?;
    if rest.len() < 36 {
        return Some(Err("truncated entry".into()));
    }
    let (sum, rest) = rest.split_at(32);
    let (len, rest) = rest.split_at(4);
    let len = u32::from_le_bytes(len.try_into().expect("4 bytes")) as usize;
    if rest.len() < len {
        return Some(Err("truncated entry".into()));
    }
    let (header, body) = rest.split_at(len);
    Some(Ok((sum, header, body)))
}

/// Reads the entry of `key`. A hit refreshes the file's modification time, which is what
/// size pruning orders by, so the entries a project keeps using are the last to go.
pub fn load(dir: &Path, key: &str) -> CacheRead {
    let p = path(dir, key);
    let Ok(bytes) = std::fs::read(&p) else {
        return CacheRead::Miss;
    };
    let (sum, header, body) = match split(&bytes) {
        None => return CacheRead::Miss,
        Some(Err(m)) => return CacheRead::Corrupt(m),
        Some(Ok(parts)) => parts,
    };
    if checksum(key, header, body).as_bytes() != sum {
        return CacheRead::Corrupt(
            "checksum mismatch (damaged file, or another step's entry)".into(),
        );
    }
    match postcard::from_bytes::<Vec<(String, Artifact)>>(body) {
        Ok(v) => {
            if let Ok(f) = std::fs::File::options().append(true).open(&p) {
                let _ = f.set_modified(SystemTime::now());
            }
            CacheRead::Hit(v.into_iter().collect())
        }
        Err(e) => CacheRead::Corrupt(format!("undecodable payload: {e}")),
    }
}

/// Writes the entry of `key` atomically (a reader sees the old file, the new one, or none).
pub fn store(dir: &Path, key: &str, header: &EntryHeader, outputs: &Outputs) -> Result<(), String> {
    let v: Vec<(&String, &Artifact)> = outputs.iter().collect();
    let body = postcard::to_stdvec(&v).map_err(|e| e.to_string())?;
    let head = serde_json::to_vec(header).map_err(|e| e.to_string())?;
    let mut bytes = CACHE_MAGIC.to_vec();
    bytes.extend_from_slice(checksum(key, &head, &body).as_bytes());
    bytes.extend_from_slice(&(head.len() as u32).to_le_bytes());
    bytes.extend_from_slice(&head);
    bytes.extend(body);
    crate::fsutil::atomic_write_bytes(&path(dir, key), &bytes)
}

/// The cache key of a step: a content hash of (stage id, stage version, canonical
/// parameters, step seed, input file hashes, and for each input port the producer's key and
/// port). Equal keys mean equal results, since a step is a pure function of these.
pub fn key<'a>(
    stage_id: &str,
    stage_version: &str,
    params: &serde_json::Value,
    seed: u64,
    input_files: &[(String, String)],
    inputs: impl IntoIterator<Item = (&'a str, &'a str, &'a str)>,
) -> String {
    let mut h = blake3::Hasher::new();
    h.update(stage_id.as_bytes());
    h.update(b"\0");
    h.update(stage_version.as_bytes());
    h.update(b"\0");
    h.update(params.to_string().as_bytes());
    h.update(&seed.to_le_bytes());
    for (path, hash) in input_files {
        h.update(path.as_bytes());
        h.update(b"#");
        h.update(hash.as_bytes());
        h.update(b";");
    }
    let mut inputs: Vec<_> = inputs.into_iter().collect();
    inputs.sort_by(|a, b| a.0.cmp(b.0));
    for (port, producer_key, producer_port) in inputs {
        h.update(port.as_bytes());
        h.update(b"=");
        h.update(producer_key.as_bytes());
        h.update(b".");
        h.update(producer_port.as_bytes());
        h.update(b";");
    }
    h.finalize().to_hex()[..32].to_string()
}

/// Whether a file name is a cache entry's (`<32 hex digits>.bin`): only those are listed
/// and pruned, so a cache directory pointed at the wrong place deletes nothing else.
fn entry_key(name: &str) -> Option<&str> {
    let key = name.strip_suffix(".bin")?;
    (key.len() == 32 && key.bytes().all(|b| b.is_ascii_hexdigit())).then_some(key)
}

/// One entry as `pipe cache` lists it.
#[derive(Clone, Debug)]
pub struct EntryInfo {
    pub key: String,
    pub path: PathBuf,
    pub size: u64,
    /// Last written or last served (the file's modification time).
    pub used: SystemTime,
    /// `None` for entries of an older layout (they are misses and are best pruned).
    pub header: Option<EntryHeader>,
}

/// Reads only an entry's header (the payload may be large).
fn read_header(p: &Path) -> Option<EntryHeader> {
    let mut f = std::fs::File::open(p).ok()?;
    let mut head = [0u8; 44];
    f.read_exact(&mut head).ok()?;
    if &head[..8] != CACHE_MAGIC {
        return None;
    }
    let len = u32::from_le_bytes(head[40..44].try_into().expect("4 bytes")) as usize;
    if len > 1 << 20 {
        return None;
    }
    let mut h = vec![0u8; len];
    f.read_exact(&mut h).ok()?;
    serde_json::from_slice(&h).ok()
}

/// Every entry in `dir`, oldest use first. A missing directory is an empty cache.
pub fn entries(dir: &Path) -> std::io::Result<Vec<EntryInfo>> {
    let rd = match std::fs::read_dir(dir) {
        Ok(rd) => rd,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e),
    };
    let mut out = Vec::new();
    for ent in rd {
        let ent = ent?;
        let name = ent.file_name();
        let Some(key) = name.to_str().and_then(entry_key) else {
            continue;
        };
        // An entry removed by a concurrent prune between listing and stat is simply gone.
        let Ok(meta) = ent.metadata() else { continue };
        if !meta.is_file() {
            continue;
        }
        out.push(EntryInfo {
            key: key.to_string(),
            path: ent.path(),
            size: meta.len(),
            used: meta.modified().unwrap_or(SystemTime::UNIX_EPOCH),
            header: read_header(&ent.path()),
        });
    }
    out.sort_by(|a, b| a.used.cmp(&b.used).then_with(|| a.key.cmp(&b.key)));
    Ok(out)
}

/// What to remove.
#[derive(Clone, Debug, Default)]
pub struct PruneRule {
    /// Remove the least recently used entries until the total is at most this [bytes].
    pub max_size: Option<u64>,
    /// Remove entries not used for longer than this.
    pub older_than: Option<Duration>,
    /// Remove everything.
    pub all: bool,
}

/// What a prune did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PruneReport {
    pub removed: usize,
    pub freed: u64,
    pub kept: usize,
    pub kept_size: u64,
}

/// Removes entries by `rule`, never those whose key is in `keep` (the current run's). Each
/// entry goes with one `unlink`, which is atomic: a reader either opened the whole file
/// before (and reads it whole) or finds no entry; it never sees half an entry. Temporary
/// files of writes a killed process left behind are removed too.
pub fn prune(dir: &Path, rule: &PruneRule, keep: &[String]) -> std::io::Result<PruneReport> {
    let list = entries(dir)?;
    let now = SystemTime::now();
    let mut total: u64 = list.iter().map(|e| e.size).sum();
    let mut rep = PruneReport::default();
    for e in list {
        let kept = keep.contains(&e.key);
        let old = rule
            .older_than
            .is_some_and(|d| now.duration_since(e.used).unwrap_or_default() > d);
        let over = rule.max_size.is_some_and(|m| total > m);
        if !kept && (rule.all || old || over) {
            match std::fs::remove_file(&e.path) {
                Ok(()) => {}
                Err(x) if x.kind() == std::io::ErrorKind::NotFound => {}
                Err(x) => return Err(x),
            }
            total -= e.size;
            rep.removed += 1;
            rep.freed += e.size;
        } else {
            rep.kept += 1;
            rep.kept_size += e.size;
        }
    }
    if dir.is_dir() {
        crate::fsutil::clean_stale_temps(dir);
    }
    Ok(rep)
}

/// The size cap applied after every `pipe run` unless `GRAINPIPE_CACHE_MAX_SIZE` says
/// otherwise (`0` or `none` turns it off).
pub const DEFAULT_MAX_SIZE: u64 = 10 * 1024 * 1024 * 1024;

/// The cap after each run: `GRAINPIPE_CACHE_MAX_SIZE` (a size such as `2GB`; `0` or `none`
/// for no cap), else [`DEFAULT_MAX_SIZE`].
pub fn default_max_size() -> Result<Option<u64>, String> {
    match std::env::var("GRAINPIPE_CACHE_MAX_SIZE") {
        Err(_) => Ok(Some(DEFAULT_MAX_SIZE)),
        Ok(v) if v.trim() == "0" || v.trim().eq_ignore_ascii_case("none") => Ok(None),
        Ok(v) => parse_size(&v)
            .map(Some)
            .map_err(|m| format!("GRAINPIPE_CACHE_MAX_SIZE: {m}")),
    }
}

/// The leading unsigned decimal number of `text` and the rest (`"2GB"` -> `("2", "GB")`).
fn split_number(text: &str) -> (&str, &str) {
    let t = text.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    t.split_at(split)
}

/// `2GB`, `500 MiB`, `1.5G`, `1000000` [bytes]: decimal (kB, MB, GB, TB) and binary (KiB,
/// MiB, GiB, TiB) units; a bare K/M/G/T is binary, as `du -h` prints it.
pub fn parse_size(text: &str) -> Result<u64, String> {
    let (num, unit) = split_number(text);
    let n: f64 = num
        .parse()
        .map_err(|_| format!("`{text}` is not a size; write e.g. `2GB` or `500MiB`"))?;
    let mult: f64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1.0,
        "kb" => 1e3,
        "mb" => 1e6,
        "gb" => 1e9,
        "tb" => 1e12,
        "k" | "kib" => 1024.0,
        "m" | "mib" => 1024f64.powi(2),
        "g" | "gib" => 1024f64.powi(3),
        "t" | "tib" => 1024f64.powi(4),
        u => {
            return Err(format!(
                "unknown size unit `{u}` in `{text}`; use B, kB, MB, GB, TB, KiB, MiB, GiB or TiB"
            ))
        }
    };
    Ok((n * mult).round() as u64)
}

/// `7d`, `12h`, `30m`, `90s`, `2w`: an age for `--older-than`.
pub fn parse_age(text: &str) -> Result<Duration, String> {
    let (num, unit) = split_number(text);
    let n: f64 = num
        .parse()
        .map_err(|_| format!("`{text}` is not an age; write e.g. `7d`, `12h` or `30m`"))?;
    let s = match unit.trim() {
        "s" => 1.0,
        "m" | "min" => 60.0,
        "h" => 3600.0,
        "d" => 86400.0,
        "w" => 7.0 * 86400.0,
        u => {
            return Err(format!(
                "unknown age unit `{u}` in `{text}`; use s, m, h, d or w"
            ))
        }
    };
    // An age beyond what `Duration` holds (about 5.8e11 years) would panic in
    // `from_secs_f64`; it means "older than anything", so it is capped, not refused.
    let seconds = n * s;
    if !seconds.is_finite() {
        return Err(format!("`{text}` is not a finite age"));
    }
    Ok(Duration::try_from_secs_f64(seconds).unwrap_or(Duration::MAX))
}

/// What `pipe cache` prints: the directory, the number of entries, their total size, and
/// the `top` largest and `top` least recently used entries with the step that wrote them.
pub fn describe(dir: &Path, top: usize) -> std::io::Result<String> {
    use std::fmt::Write;
    let list = entries(dir)?;
    let total: u64 = list.iter().map(|e| e.size).sum();
    let mut out = String::new();
    let _ = writeln!(out, "cache directory: {}", dir.display());
    let _ = writeln!(
        out,
        "entries: {}, total size: {}",
        list.len(),
        crate::engine::human_bytes(total)
    );
    if list.is_empty() {
        return Ok(out);
    }
    let now = SystemTime::now();
    let line = |out: &mut String, e: &EntryInfo| {
        let age = now.duration_since(e.used).unwrap_or_default();
        let what = match &e.header {
            Some(h) => format!("{} ({}) of `{}`", h.step, h.stage, h.pipeline),
            None => "(older cache format: never used again; prune it)".to_string(),
        };
        let _ = writeln!(
            out,
            "  {}  {:>10}  used {:>6} ago  {what}",
            e.key,
            crate::engine::human_bytes(e.size),
            human_age(age)
        );
    };
    let mut largest: Vec<&EntryInfo> = list.iter().collect();
    largest.sort_by(|a, b| b.size.cmp(&a.size).then_with(|| a.key.cmp(&b.key)));
    let _ = writeln!(out, "largest:");
    for e in largest.iter().take(top) {
        line(&mut out, e);
    }
    let _ = writeln!(out, "least recently used:");
    for e in list.iter().take(top) {
        line(&mut out, e);
    }
    Ok(out)
}

/// `3d`, `5h`, `12m`, `40s`: the largest whole unit.
fn human_age(d: Duration) -> String {
    let s = d.as_secs();
    match s {
        0..=119 => format!("{s}s"),
        120..=7199 => format!("{}m", s / 60),
        7200..=172_799 => format!("{}h", s / 3600),
        _ => format!("{}d", s / 86400),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Artifact, Table};

    fn outputs(v: f64) -> Outputs {
        let t = Table::new("t").with_f64("x", "m", vec![v, 2.0 * v]);
        let mut o = Outputs::new();
        o.insert("t".into(), Artifact::Table(t));
        o
    }

    fn header(step: &str) -> EntryHeader {
        EntryHeader {
            step: step.into(),
            stage: "s.t".into(),
            pipeline: "p".into(),
            created: 7,
        }
    }

    #[test]
    fn round_trip_header_and_payload() {
        let d = tempfile::tempdir().unwrap();
        let k = "0123456789abcdef0123456789abcdef";
        store(d.path(), k, &header("a"), &outputs(1.5)).unwrap();
        let CacheRead::Hit(o) = load(d.path(), k) else {
            panic!("miss")
        };
        assert_eq!(o, outputs(1.5));
        let e = entries(d.path()).unwrap();
        assert_eq!(e.len(), 1);
        assert_eq!(e[0].header.as_ref(), Some(&header("a")));
        assert_eq!(
            e[0].size,
            std::fs::metadata(path(d.path(), k)).unwrap().len()
        );
        let text = describe(d.path(), 5).unwrap();
        assert!(text.contains("entries: 1,"), "{text}");
        assert!(text.contains("a (s.t) of `p`"), "{text}");
    }

    #[test]
    fn older_layout_is_a_miss_and_damage_is_corrupt() {
        let d = tempfile::tempdir().unwrap();
        let k = "0123456789abcdef0123456789abcdef";
        let mut old = b"GRPCACH3".to_vec();
        old.extend([0u8; 64]);
        std::fs::write(path(d.path(), k), &old).unwrap();
        assert!(matches!(load(d.path(), k), CacheRead::Miss));
        store(d.path(), k, &header("a"), &outputs(1.0)).unwrap();
        let mut b = std::fs::read(path(d.path(), k)).unwrap();
        let n = b.len();
        b[n - 1] ^= 1;
        std::fs::write(path(d.path(), k), &b).unwrap();
        assert!(matches!(load(d.path(), k), CacheRead::Corrupt(_)));
        // Another key's entry fails the checksum too.
        store(d.path(), k, &header("a"), &outputs(1.0)).unwrap();
        let k2 = "fedcba9876543210fedcba9876543210";
        std::fs::copy(path(d.path(), k), path(d.path(), k2)).unwrap();
        assert!(matches!(load(d.path(), k2), CacheRead::Corrupt(_)));
    }

    #[test]
    fn prune_by_size_removes_least_recently_used_and_spares_kept_and_foreign_files() {
        let d = tempfile::tempdir().unwrap();
        let keys: Vec<String> = (0..4).map(|i| format!("{i:032x}")).collect();
        for (i, k) in keys.iter().enumerate() {
            store(d.path(), k, &header(&format!("s{i}")), &outputs(i as f64)).unwrap();
            let f = std::fs::File::options()
                .append(true)
                .open(path(d.path(), k))
                .unwrap();
            f.set_modified(SystemTime::UNIX_EPOCH + Duration::from_secs(1000 * (i as u64 + 1)))
                .unwrap();
        }
        std::fs::write(d.path().join("notes.txt"), b"mine").unwrap();
        let size = entries(d.path()).unwrap()[0].size;
        // Room for two entries; entry 0 (oldest) is kept on request, so 1 and 2 go.
        let rep = prune(
            d.path(),
            &PruneRule {
                max_size: Some(2 * size),
                ..Default::default()
            },
            &keys[..1],
        )
        .unwrap();
        assert_eq!(rep.removed, 2);
        assert_eq!(rep.freed, 2 * size);
        let left: Vec<String> = entries(d.path())
            .unwrap()
            .into_iter()
            .map(|e| e.key)
            .collect();
        assert_eq!(left, vec![keys[0].clone(), keys[3].clone()]);
        assert!(d.path().join("notes.txt").exists());
        // Older than a day: both remaining entries are from 1970.
        let rep = prune(
            d.path(),
            &PruneRule {
                older_than: Some(Duration::from_secs(86400)),
                ..Default::default()
            },
            &[],
        )
        .unwrap();
        assert_eq!((rep.removed, rep.kept), (2, 0));
        assert!(d.path().join("notes.txt").exists());
    }

    #[test]
    fn sizes_and_ages_parse() {
        assert_eq!(parse_size("2GB").unwrap(), 2_000_000_000);
        assert_eq!(parse_size("500 MiB").unwrap(), 500 * 1024 * 1024);
        assert_eq!(parse_size("1.5k").unwrap(), 1536);
        // u64::MAX seconds overflowed Duration::from_secs_f64 (a panic, exit 101).
        assert_eq!(
            parse_age("18446744073709551615s").unwrap(),
            Duration::MAX,
            "a huge age is 'older than anything'"
        );
        assert_eq!(parse_age("2d").unwrap(), Duration::from_secs(172_800));
        assert!(parse_age("1e400s").is_err());
        assert!(parse_size("2 parsecs").unwrap_err().contains("parsecs"));
        assert_eq!(parse_age("7d").unwrap(), Duration::from_secs(7 * 86400));
        assert_eq!(parse_age("90s").unwrap(), Duration::from_secs(90));
        assert!(parse_age("soon").is_err());
    }
}
