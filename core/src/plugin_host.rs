//! Loading third-party stages from shared libraries through the C ABI of
//! `grainpipe-plugin-api`, and adapting them to [`Stage`] so they take part in preflight,
//! caching, progress and provenance exactly like built-in stages.
//!
//! Libraries are never unloaded: stage objects and metadata strings point into them.

use crate::model::*;
use crate::registry::Registry;
use crate::stage::{
    InputMetas, Inputs, Outputs, ParamSpec, PortSpec, Preflight, Prepared, RunContext, Stage,
    StageError, StageInfo,
};
use crate::units::{parse_quantity, parse_unit};
use grainpipe_plugin_api::{
    dtype, status, GpArray, GpArtifact, GpHost, GpPluginVTable, GpStr, ABI_MAJOR, ABI_MINOR,
};
use indexmap::IndexMap;
use serde::Deserialize;
use serde_json::{json, Value};
use std::ffi::c_void;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A JSON Schema for a foreign parameter, from the JSON type of its default.
fn json_schema_of(default: &Value) -> Value {
    match default {
        Value::Bool(_) => json!({"type": "boolean"}),
        Value::Number(n) if n.is_f64() => {
            json!({"anyOf": [{"type": "number"}, {"type": "string"}]})
        }
        Value::Number(_) => json!({"anyOf": [{"type": "integer"}, {"type": "string"}]}),
        Value::String(_) => json!({"type": "string"}),
        Value::Array(_) => json!({"type": "array"}),
        Value::Object(_) => json!({"type": "object"}),
        Value::Null => json!({}),
    }
}

/// File name endings of shared libraries on this platform.
const LIB_EXTENSIONS: &[&str] = &["so", "dylib", "dll"];

/// Expands plugin locations: a directory gives every shared library directly in it (sorted),
/// a file gives itself. Missing locations are errors (a typo must not silently load nothing).
pub fn expand_locations(locations: &[PathBuf]) -> Result<Vec<PathBuf>, String> {
    let mut out = Vec::new();
    for loc in locations {
        if loc.is_dir() {
            let mut libs: Vec<PathBuf> = std::fs::read_dir(loc)
                .map_err(|e| format!("plugin directory {}: {e}", loc.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.extension()
                        .and_then(|x| x.to_str())
                        .is_some_and(|x| LIB_EXTENSIONS.contains(&x))
                })
                .collect();
            libs.sort();
            out.extend(libs);
        } else if loc.is_file() {
            out.push(loc.clone());
        } else {
            return Err(format!("plugin location {} does not exist", loc.display()));
        }
    }
    Ok(out)
}

/// Locations from `GRAINPIPE_PLUGIN_PATH` (separated like PATH).
pub fn env_locations() -> Vec<PathBuf> {
    std::env::var_os("GRAINPIPE_PLUGIN_PATH")
        .map(|v| {
            std::env::split_paths(&v)
                .filter(|p| !p.as_os_str().is_empty())
                .collect()
        })
        .unwrap_or_default()
}

#[derive(Deserialize)]
struct MetaDoc {
    stages: Vec<MetaStage>,
}

#[derive(Deserialize)]
struct MetaStage {
    id: String,
    version: String,
    doc: String,
    #[serde(default)]
    params: Vec<MetaParam>,
    #[serde(default)]
    inputs: Vec<MetaPort>,
    #[serde(default)]
    outputs: Vec<MetaPort>,
}

#[derive(Deserialize)]
struct MetaParam {
    name: String,
    #[serde(default)]
    ty: String,
    #[serde(default)]
    unit: String,
    #[serde(default)]
    doc: String,
    default: Value,
    /// The value names an input file or directory (the cache hashes its content).
    #[serde(default)]
    file: bool,
}

#[derive(Deserialize)]
struct MetaPort {
    name: String,
    kind: String,
    #[serde(default)]
    doc: String,
    #[serde(default)]
    optional: bool,
}

fn leak(s: String) -> &'static str {
    Box::leak(s.into_boxed_str())
}

fn kind_from_name(name: &str) -> Result<ArtifactKind, String> {
    Ok(match name {
        "PhaseImage" => ArtifactKind::PhaseImage,
        "Field" => ArtifactKind::Field,
        "Table" => ArtifactKind::Table,
        "Tensor" => ArtifactKind::Tensor,
        "Packing" => ArtifactKind::Packing,
        other => {
            return Err(format!(
                "artifact kind `{other}` cannot cross the plugin ABI {ABI_MAJOR}.{ABI_MINOR} \
                 (supported: PhaseImage, Field, Table, Tensor, Packing)"
            ))
        }
    })
}

/// Reads a little- or big-endian unsigned integer of `n` bytes at `at`.
fn uint(b: &[u8], at: usize, n: usize, little: bool) -> Option<u64> {
    let s = b.get(at..at.checked_add(n)?)?;
    let mut v = 0u64;
    for k in 0..n {
        let byte = if little { s[n - 1 - k] } else { s[k] };
        v = (v << 8) | u64::from(byte);
    }
    Some(v)
}

/// Checks, before `dlopen`, that a file can be a shared library: not empty and, for ELF
/// files, that the program headers and every loadable segment lie inside the file. The
/// dynamic loader maps segments without checking the file size, so a truncated `.so` makes
/// the first access past its end a SIGBUS that kills every command; this turns it into an
/// error naming the file. Non-ELF formats (Mach-O, PE) are left to the loader.
pub fn check_library_file(path: &Path) -> Result<(), String> {
    let shown = path.display();
    let meta = std::fs::metadata(path).map_err(|e| format!("plugin {shown}: {e}"))?;
    if !meta.is_file() {
        return Err(format!("plugin {shown} is not a regular file"));
    }
    let size = meta.len();
    if size == 0 {
        return Err(format!(
            "plugin {shown} is empty (0 bytes): not a shared library (an interrupted copy?)"
        ));
    }
    use std::io::Read;
    let mut head = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(64).read_to_end(&mut head))
        .map_err(|e| format!("plugin {shown}: {e}"))?;
    if !head.starts_with(b"\x7fELF") {
        if cfg!(target_os = "linux") {
            return Err(format!(
                "plugin {shown} is not an ELF shared library (it does not start with the ELF magic)"
            ));
        }
        return Ok(());
    }
    let truncated = |what: &str| {
        format!(
            "plugin {shown} is truncated or corrupt ({what} lies past its {size} bytes); \
             rebuild or copy it again"
        )
    };
    let wide = match head.get(4) {
        Some(2) => true,
        Some(1) => false,
        _ => return Err(truncated("ELF class")),
    };
    let little = match head.get(5) {
        Some(1) => true,
        Some(2) => false,
        _ => return Err(truncated("ELF byte order")),
    };
    let (phoff, phentsize, phnum) = if wide {
        (
            uint(&head, 0x20, 8, little),
            uint(&head, 0x36, 2, little),
            uint(&head, 0x38, 2, little),
        )
    } else {
        (
            uint(&head, 0x1c, 4, little),
            uint(&head, 0x2a, 2, little),
            uint(&head, 0x2c, 2, little),
        )
    };
    let (Some(phoff), Some(phentsize), Some(phnum)) = (phoff, phentsize, phnum) else {
        return Err(truncated("the ELF header"));
    };
    let table_end = phentsize
        .checked_mul(phnum)
        .and_then(|n| n.checked_add(phoff))
        .filter(|&e| e <= size)
        .ok_or_else(|| truncated("the program header table"))?;
    let mut table = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(table_end).read_to_end(&mut table))
        .map_err(|e| format!("plugin {shown}: {e}"))?;
    for k in 0..phnum {
        let at = (phoff + k * phentsize) as usize;
        // p_type, then p_offset and p_filesz
        let (ty, off, filesz) = if wide {
            (
                uint(&table, at, 4, little),
                uint(&table, at + 8, 8, little),
                uint(&table, at + 32, 8, little),
            )
        } else {
            (
                uint(&table, at, 4, little),
                uint(&table, at + 4, 4, little),
                uint(&table, at + 16, 4, little),
            )
        };
        let (Some(ty), Some(off), Some(filesz)) = (ty, off, filesz) else {
            return Err(truncated("a program header"));
        };
        const PT_LOAD: u64 = 1;
        if ty == PT_LOAD && off.checked_add(filesz).is_none_or(|e| e > size) {
            return Err(truncated(&format!("loadable segment {k}")));
        }
    }
    Ok(())
}

/// The error and every cause below it (libloading puts dlopen's reason in the source).
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        let more = c.to_string();
        if !text.contains(&more) {
            text.push_str(": ");
            text.push_str(&more);
        }
        cur = c.source();
    }
    text
}

/// Loads one plugin library and registers its stages; returns their ids.
pub fn load_plugin(path: &Path, registry: &mut Registry) -> Result<Vec<String>, String> {
    let shown = path.display();
    check_library_file(path)?;
    // SAFETY: loading a library runs its initializers; that is the contract of a plugin.
    let lib = unsafe { libloading::Library::new(path) }
        .map_err(|e| format!("cannot load plugin {shown}: {}", error_chain(&e)))?;
    // SAFETY: the symbol's type is fixed by the ABI.
    let version =
        unsafe { lib.get::<extern "C" fn() -> u32>(b"grainpipe_abi_version") }.map_err(|_| {
            format!(
                "{shown} is not a grainpipe plugin: it exports no `grainpipe_abi_version` symbol"
            )
        })?;
    let v = version();
    let (major, minor) = (v >> 16, v & 0xffff);
    if major != ABI_MAJOR {
        return Err(format!(
            "{shown} was built for grainpipe plugin ABI {major}.{minor}, but this pipe speaks ABI \
             {ABI_MAJOR}.{ABI_MINOR}: rebuild the plugin against grainpipe-plugin-api {ABI_MAJOR}.x"
        ));
    }
    // SAFETY: as above.
    let entry = unsafe {
        lib.get::<extern "C" fn(*const GpHost) -> *const GpPluginVTable>(b"grainpipe_plugin_entry")
    }
    .map_err(|_| {
        format!("{shown} is not a grainpipe plugin: it exports no `grainpipe_plugin_entry` symbol")
    })?;
    let mut ctx = HostCtx::default();
    let host = ctx.host();
    let vt = entry(&host);
    if vt.is_null() {
        return Err(format!(
            "{shown}: grainpipe_plugin_entry returned no vtable"
        ));
    }
    // SAFETY: non-null, and the library is never unloaded (forgotten below).
    let vt: &'static GpPluginVTable = unsafe { &*vt };
    if (vt.struct_size as usize) < std::mem::size_of::<GpPluginVTable>() {
        return Err(format!(
            "{shown}: its vtable has {} bytes, this pipe needs {}",
            vt.struct_size,
            std::mem::size_of::<GpPluginVTable>()
        ));
    }
    // SAFETY: the plugin guarantees the metadata string lives as long as the library.
    let meta_text =
        unsafe { (vt.metadata_json)().to_str() }.map_err(|e| format!("{shown}: metadata: {e}"))?;
    if let Ok(Value::Object(m)) = serde_json::from_str::<Value>(meta_text) {
        if let Some(p) = m.get("panic") {
            return Err(format!(
                "{shown}: the plugin panicked while giving its metadata: {}",
                p.as_str().unwrap_or("unknown panic")
            ));
        }
    }
    let meta: MetaDoc = serde_json::from_str(meta_text)
        .map_err(|e| format!("{shown}: metadata JSON is invalid: {e}"))?;
    std::mem::forget(lib);
    let mut stages = Vec::new();
    for (index, m) in meta.stages.into_iter().enumerate() {
        stages.push(ForeignStage::new(vt, index as u32, m).map_err(|e| format!("{shown}: {e}"))?);
    }
    registry.set_origin(Some(path.display().to_string()));
    let mut ids = Vec::new();
    let mut result = Ok(());
    for s in stages {
        ids.push(s.info.id.to_string());
        if let Err(e) = registry.try_add_dyn_stage(Arc::new(s)) {
            result = Err(format!("{shown}: {e}"));
            break;
        }
    }
    registry.set_origin(None);
    result.map(|_| ids)
}

/// A stage living in a plugin library.
pub struct ForeignStage {
    vt: &'static GpPluginVTable,
    index: u32,
    info: StageInfo,
    defaults: serde_json::Map<String, Value>,
}

impl ForeignStage {
    /// One given parameter in canonical SI JSON: the key must be declared, a unit string
    /// must have the declared dimension, and the JSON type must match the default's.
    fn normalize_value(&self, k: &str, v: &Value) -> Result<Value, StageError> {
        let spec = self
            .info
            .params
            .iter()
            .find(|p| p.name == k)
            .ok_or_else(|| StageError::UnknownParam {
                key: k.to_string(),
                suggestion: crate::registry::closest(k, self.info.params.iter().map(|p| p.name)),
            })?;
        let mut v = v.clone();
        let dimensional = !spec.unit.is_empty() && spec.unit != "1";
        if dimensional {
            if let Value::String(s) = &v {
                let (_, want) = parse_unit(&spec.unit).map_err(|e| StageError::param(k, e))?;
                let q = parse_quantity(s).map_err(|e| StageError::param(k, e))?;
                if q.dim != want {
                    return Err(StageError::param(
                        k,
                        format!(
                            "`{s}` has dimension {} but this parameter takes {}",
                            q.dim, spec.unit
                        ),
                    ));
                }
                v = json!(q.value);
            }
        }
        let default = &self.defaults[k];
        if !default.is_null() && json_type(default) != json_type(&v) {
            return Err(StageError::param(
                k,
                format!("expected {}, got {}", json_type(default), json_type(&v)),
            ));
        }
        Ok(v)
    }

    fn new(vt: &'static GpPluginVTable, index: u32, m: MetaStage) -> Result<Self, String> {
        if !m.id.contains('.') {
            return Err(format!(
                "stage id `{}` is not of the form <family>.<name>",
                m.id
            ));
        }
        let ports = |ps: Vec<MetaPort>| -> Result<Vec<PortSpec>, String> {
            ps.into_iter()
                .map(|p| {
                    Ok(PortSpec {
                        kind: kind_from_name(&p.kind)
                            .map_err(|e| format!("{}: port `{}`: {e}", m.id, p.name))?,
                        name: leak(p.name),
                        doc: leak(p.doc),
                        optional: p.optional,
                    })
                })
                .collect()
        };
        let inputs = ports(m.inputs)?;
        let outputs = ports(m.outputs)?;
        let mut defaults = serde_json::Map::new();
        let mut params = Vec::new();
        for p in m.params {
            if !p.unit.is_empty() && p.unit != "1" {
                parse_unit(&p.unit)
                    .map_err(|e| format!("{}: parameter `{}`: {e}", m.id, p.name))?;
            }
            let schema = json_schema_of(&p.default);
            let name = leak(p.name);
            params.push(ParamSpec {
                name,
                ty: p.ty,
                unit: if p.unit == "1" { String::new() } else { p.unit },
                doc: leak(p.doc),
                reads_file: p.file,
                schema,
                default: p.default.clone(),
            });
            defaults.insert(name.to_string(), p.default);
        }
        let info = StageInfo {
            id: leak(m.id),
            version: leak(m.version),
            doc: leak(m.doc),
            params,
            inputs,
            outputs,
        };
        Ok(ForeignStage {
            vt,
            index,
            info,
            defaults,
        })
    }

    fn call(
        &self,
        f: extern "C" fn(u32, GpStr, *const GpArtifact, u32, *const GpHost) -> i32,
        params: &Value,
        inputs: &[Marshalled],
        ctx: &mut HostCtx,
    ) -> Result<(), StageError> {
        let params = params.to_string();
        let raw: Vec<GpArtifact> = inputs.iter().map(|m| m.view()).collect();
        let host = ctx.host();
        let code = f(
            self.index,
            GpStr::new(&params),
            raw.as_ptr(),
            raw.len() as u32,
            &host,
        );
        let (key, message) = ctx.error.take().unwrap_or_default();
        match code {
            status::OK => Ok(()),
            status::INVALID_PARAM => Err(StageError::InvalidParam { key, message }),
            status::INVALID_INPUT => Err(StageError::InvalidInput { port: key, message }),
            status::CANCELLED => Err(StageError::Cancelled),
            status::PANIC => Err(StageError::failed(message)),
            status::FAILED => Err(StageError::failed(message)),
            other => Err(StageError::failed(format!(
                "plugin returned unknown status {other}: {message}"
            ))),
        }
    }
}

fn json_type(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "a list",
        Value::Object(_) => "a mapping",
    }
}

impl Stage for ForeignStage {
    fn info(&self) -> &StageInfo {
        &self.info
    }

    fn default_params(&self) -> Value {
        Value::Object(self.defaults.clone())
    }

    /// Fills defaults, refuses unknown keys, converts unit strings of dimensional parameters
    /// to SI numbers and checks JSON types against the defaults: the plugin receives
    /// canonical SI JSON.
    fn normalize_params(&self, params: &Value) -> Result<Value, StageError> {
        let given = params
            .as_object()
            .ok_or_else(|| StageError::param("", "parameters must be a mapping"))?;
        let mut out = self.defaults.clone();
        let mut errors = Vec::new();
        for (k, v) in given {
            match self.normalize_value(k, v) {
                Ok(v) => {
                    out.insert(k.clone(), v);
                }
                Err(e) => errors.push(e),
            }
        }
        // Every bad key of the step at once, as for built-in stages.
        match errors.len() {
            0 => {}
            1 => return Err(errors.remove(0)),
            _ => return Err(StageError::Several(errors)),
        }
        Ok(Value::Object(out))
    }

    fn preflight(
        &self,
        params: &Value,
        inputs: &InputMetas,
    ) -> Result<(Preflight, Prepared), StageError> {
        let metas: Vec<Marshalled> = inputs
            .iter()
            .map(|(port, m)| Marshalled::meta(port, m))
            .collect();
        let mut ctx = HostCtx::default();
        self.call(self.vt.preflight, params, &metas, &mut ctx)?;
        let mut pf = Preflight::from_info(&self.info, 0);
        if let Some(text) = ctx.preflight {
            let v: Value = serde_json::from_str(&text).map_err(|e| {
                StageError::failed(format!("plugin preflight JSON is invalid: {e}"))
            })?;
            pf.memory_bytes = v.get("memory_bytes").and_then(Value::as_u64).unwrap_or(0);
            if let Some(outs) = v.get("outputs").and_then(Value::as_object) {
                for (port, meta) in outs {
                    if let (Some(m), Some(grid)) = (pf.outputs.get_mut(port), meta.get("grid")) {
                        m.grid = serde_json::from_value(grid.clone()).ok();
                    }
                }
            }
        }
        Ok((pf, Arc::new(())))
    }

    fn run(
        &self,
        params: &Value,
        _prepared: &Prepared,
        inputs: &Inputs,
        rc: &RunContext,
    ) -> Result<Outputs, StageError> {
        let marshalled = inputs
            .iter()
            .map(|(port, a)| Marshalled::artifact(port, a))
            .collect::<Result<Vec<_>, _>>()?;
        let mut ctx = HostCtx {
            progress: Some(rc as *const RunContext as *const c_void),
            declared: self
                .info
                .outputs
                .iter()
                .map(|p| (p.name.to_string(), p.kind))
                .collect(),
            ..Default::default()
        };
        self.call(self.vt.run, params, &marshalled, &mut ctx)?;
        let mut outputs = Outputs::new();
        for spec in &self.info.outputs {
            let pending = ctx.outputs.shift_remove(spec.name).ok_or_else(|| {
                StageError::failed(format!("plugin did not give output `{}`", spec.name))
            })?;
            // Everything a plugin states is checked like a file's header: the artifact's
            // sizes must agree with its metadata before any stage or exporter indexes it.
            let a = unmarshal(spec.kind, &pending)
                .and_then(|a| a.validate().map(|()| a))
                .map_err(|e| StageError::failed(format!("plugin output `{}`: {e}", spec.name)))?;
            outputs.insert(spec.name.to_string(), a);
        }
        Ok(outputs)
    }
}

// ---------------------------------------------------------------------------------------
// Marshalling artifacts to borrowed C views.

/// An owned host array, typed so that its buffer is aligned for its element type.
enum Buf {
    U8(Vec<u8>),
    U32(Vec<u32>),
    I64(Vec<i64>),
    F32(Vec<f32>),
    F64(Vec<f64>),
}

impl Buf {
    /// A zeroed buffer of `n` elements, or `None` (a null pointer for the plugin, which
    /// then fails with a message) when the type is unknown or the bytes exceed the memory
    /// the system still has: `vec![0; n]` would abort the host on an allocation failure, and
    /// a plugin asking for 2^37 f64 must fail, not kill `pipe`.
    fn zeroed(dt: u32, n: usize) -> Option<Buf> {
        fn vec<T: Clone + Default>(n: usize) -> Option<Vec<T>> {
            let bytes = n.checked_mul(std::mem::size_of::<T>())? as u64;
            if bytes > crate::engine::available_memory().unwrap_or(u64::MAX) {
                return None;
            }
            let mut v = Vec::new();
            v.try_reserve_exact(n).ok()?;
            v.resize(n, T::default());
            Some(v)
        }
        Some(match dt {
            dtype::U8 => Buf::U8(vec(n)?),
            dtype::U32 => Buf::U32(vec(n)?),
            dtype::I64 => Buf::I64(vec(n)?),
            dtype::F32 => Buf::F32(vec(n)?),
            dtype::F64 => Buf::F64(vec(n)?),
            _ => return None,
        })
    }
    fn dtype(&self) -> u32 {
        match self {
            Buf::U8(_) => dtype::U8,
            Buf::U32(_) => dtype::U32,
            Buf::I64(_) => dtype::I64,
            Buf::F32(_) => dtype::F32,
            Buf::F64(_) => dtype::F64,
        }
    }
    fn ptr(&self) -> *const c_void {
        match self {
            Buf::U8(v) => v.as_ptr() as *const c_void,
            Buf::U32(v) => v.as_ptr() as *const c_void,
            Buf::I64(v) => v.as_ptr() as *const c_void,
            Buf::F32(v) => v.as_ptr() as *const c_void,
            Buf::F64(v) => v.as_ptr() as *const c_void,
        }
    }
    fn mut_ptr(&mut self) -> *mut c_void {
        match self {
            Buf::U8(v) => v.as_mut_ptr() as *mut c_void,
            Buf::U32(v) => v.as_mut_ptr() as *mut c_void,
            Buf::I64(v) => v.as_mut_ptr() as *mut c_void,
            Buf::F32(v) => v.as_mut_ptr() as *mut c_void,
            Buf::F64(v) => v.as_mut_ptr() as *mut c_void,
        }
    }
}

/// A named array with its shape and C-contiguous byte strides.
struct NamedArray {
    name: String,
    shape: Vec<usize>,
    strides: Vec<isize>,
    data: Buf,
}

impl NamedArray {
    fn new(name: &str, shape: Vec<usize>, data: Buf) -> Self {
        let elem = dtype::size(data.dtype()) as isize;
        let mut strides = vec![0isize; shape.len()];
        let mut s = elem;
        for i in (0..shape.len()).rev() {
            strides[i] = s;
            s *= shape[i] as isize;
        }
        NamedArray {
            name: name.to_string(),
            shape,
            strides,
            data,
        }
    }
}

/// An input artifact converted to (kind, metadata JSON, arrays), owning everything the C
/// views point to for the duration of a call.
struct Marshalled {
    port: String,
    kind: String,
    meta: String,
    arrays: Vec<NamedArray>,
    views: Vec<GpArray>,
}

impl Marshalled {
    fn finish(port: &str, kind: ArtifactKind, meta: Value, arrays: Vec<NamedArray>) -> Self {
        let mut m = Marshalled {
            port: port.into(),
            kind: kind.to_string(),
            meta: meta.to_string(),
            arrays,
            views: vec![],
        };
        m.views = m
            .arrays
            .iter()
            .map(|a| GpArray {
                name: GpStr::new(&a.name),
                dtype: a.data.dtype(),
                ndim: a.shape.len() as u32,
                shape: a.shape.as_ptr(),
                strides: a.strides.as_ptr(),
                data: a.data.ptr(),
            })
            .collect();
        m
    }

    fn meta(port: &str, m: &ArtifactMeta) -> Self {
        let meta = json!({ "grid": m.grid, "count_estimate": m.count_estimate });
        Self::finish(port, m.kind, meta, vec![])
    }

    fn artifact(port: &str, a: &Artifact) -> Result<Self, StageError> {
        let zyx = |g: &Grid| vec![g.dims[2], g.dims[1], g.dims[0]];
        let (meta, arrays) = match a {
            Artifact::PhaseImage(p) => (
                json!({"grid": p.grid, "phases": p.phases}),
                vec![NamedArray::new(
                    "labels",
                    zyx(&p.grid),
                    Buf::U8(p.labels.clone()),
                )],
            ),
            Artifact::Field(f) => {
                let mut shape = zyx(&f.grid);
                shape.push(f.components);
                let data = match &f.data {
                    FieldData::F32(v) => Buf::F32(v.clone()),
                    FieldData::F64(v) => Buf::F64(v.clone()),
                };
                (
                    json!({"grid": f.grid, "name": f.name, "unit": f.unit, "components": f.components,
                           "convention": f.convention.name()}),
                    vec![NamedArray::new("data", shape, data)],
                )
            }
            Artifact::Table(t) => {
                let mut cols = Vec::new();
                let mut arrays = Vec::new();
                for c in &t.columns {
                    match &c.data {
                        ColumnData::F64(v) => {
                            cols.push(json!({"name": c.name, "unit": c.unit, "dtype": "f64"}));
                            arrays.push(NamedArray::new(
                                &c.name,
                                vec![v.len()],
                                Buf::F64(v.clone()),
                            ));
                        }
                        ColumnData::I64(v) => {
                            cols.push(json!({"name": c.name, "unit": c.unit, "dtype": "i64"}));
                            arrays.push(NamedArray::new(
                                &c.name,
                                vec![v.len()],
                                Buf::I64(v.clone()),
                            ));
                        }
                        ColumnData::Str(v) => cols.push(
                            json!({"name": c.name, "unit": c.unit, "dtype": "str", "values": v}),
                        ),
                    }
                }
                (
                    json!({"name": t.name, "rows": t.rows(), "columns": cols}),
                    arrays,
                )
            }
            Artifact::Tensor(t) => (
                json!({"name": t.name, "unit": t.unit, "shape": t.shape, "convention": t.convention}),
                vec![NamedArray::new(
                    "values",
                    t.shape.clone(),
                    Buf::F64(t.values.clone()),
                )],
            ),
            Artifact::Packing(p) => {
                let n = p.bodies.len();
                let mut radii = Vec::with_capacity(n);
                for b in &p.bodies {
                    match b.shape {
                        BodyShape::Sphere { radius } => radii.push(radius),
                        BodyShape::Clump { .. } => {
                            return Err(StageError::input(
                                port,
                                "clump packings cannot cross the plugin ABI 1.0 (spheres only)",
                            ))
                        }
                    }
                }
                let pos: Vec<f64> = p.bodies.iter().flat_map(|b| b.position).collect();
                let layer: Vec<u32> = p.bodies.iter().map(|b| b.layer).collect();
                (
                    json!({"domain": p.domain, "bodies": n}),
                    vec![
                        NamedArray::new("positions", vec![n, 3], Buf::F64(pos)),
                        NamedArray::new("radii", vec![n], Buf::F64(radii)),
                        NamedArray::new("layer", vec![n], Buf::U32(layer)),
                    ],
                )
            }
            other => {
                return Err(StageError::input(
                    port,
                    format!("a {} cannot cross the plugin ABI", other.kind()),
                ))
            }
        };
        Ok(Self::finish(port, a.kind(), meta, arrays))
    }

    fn view(&self) -> GpArtifact {
        GpArtifact {
            port: GpStr::new(&self.port),
            kind: GpStr::new(&self.kind),
            meta_json: GpStr::new(&self.meta),
            n_arrays: self.views.len() as u32,
            arrays: self.views.as_ptr(),
        }
    }
}

/// An output being filled by a plugin.
#[derive(Default)]
struct PendingOutput {
    meta: String,
    arrays: Vec<NamedArray>,
}

impl PendingOutput {
    fn take(&self, name: &str) -> Result<&NamedArray, String> {
        self.arrays
            .iter()
            .find(|a| a.name == name)
            .ok_or_else(|| format!("missing array `{name}`"))
    }
}

fn unmarshal(kind: ArtifactKind, p: &PendingOutput) -> Result<Artifact, String> {
    let meta: Value = serde_json::from_str(&p.meta).map_err(|e| format!("metadata JSON: {e}"))?;
    let get = |k: &str| {
        meta.get(k)
            .cloned()
            .ok_or_else(|| format!("metadata lacks `{k}`"))
    };
    let de = |k: &str, e: serde_json::Error| format!("metadata `{k}`: {e}");
    let expect_len = |a: &NamedArray, n: usize| {
        let len = checked_product(&a.shape).unwrap_or(usize::MAX);
        if len == n && n != usize::MAX {
            Ok(())
        } else {
            Err(format!(
                "array `{}` has {len} elements, expected {n}",
                a.name
            ))
        }
    };
    Ok(match kind {
        ArtifactKind::PhaseImage => {
            let grid: Grid = serde_json::from_value(get("grid")?).map_err(|e| de("grid", e))?;
            grid.validate(1)
                .map_err(|e| format!("metadata `grid`: {e}"))?;
            let phases: Vec<Phase> =
                serde_json::from_value(get("phases")?).map_err(|e| de("phases", e))?;
            let a = p.take("labels")?;
            expect_len(a, grid.voxel_count())?;
            let Buf::U8(labels) = &a.data else {
                return Err("`labels` must be u8".into());
            };
            Artifact::PhaseImage(PhaseImage {
                grid,
                labels: labels.clone(),
                phases,
            })
        }
        ArtifactKind::Field => {
            let grid: Grid = serde_json::from_value(get("grid")?).map_err(|e| de("grid", e))?;
            let components = get("components")?
                .as_u64()
                .ok_or("`components` must be an integer")? as usize;
            grid.validate(8)
                .map_err(|e| format!("metadata `grid`: {e}"))?;
            let a = p.take("data")?;
            expect_len(
                a,
                checked_product(&[grid.voxel_count(), components]).unwrap_or(usize::MAX),
            )?;
            let data = match &a.data {
                Buf::F32(v) => FieldData::F32(v.clone()),
                Buf::F64(v) => FieldData::F64(v.clone()),
                _ => return Err("`data` must be f32 or f64".into()),
            };
            let s = |k: &str| {
                meta.get(k)
                    .and_then(Value::as_str)
                    .unwrap_or("")
                    .to_string()
            };
            // Plugins that do not state a convention give plain components.
            let convention = match meta.get("convention").and_then(Value::as_str) {
                None => ComponentConvention::Plain,
                Some(c) => ComponentConvention::from_name(c).ok_or_else(|| {
                    format!(
                        "unknown component convention `{c}` (plain, vector, voigt, mandel, tensor)"
                    )
                })?,
            };
            // Checks that the component count fits the convention.
            Artifact::Field(Field::new(grid, s("name"), s("unit"), convention, data)?)
        }
        ArtifactKind::Table => {
            let cols = get("columns")?;
            let cols = cols.as_array().ok_or("`columns` must be a list")?;
            let mut t = Table::new(meta.get("name").and_then(Value::as_str).unwrap_or(""));
            for c in cols {
                let name = c
                    .get("name")
                    .and_then(Value::as_str)
                    .ok_or("column without name")?;
                let unit = c.get("unit").and_then(Value::as_str).unwrap_or("");
                let data = match c.get("dtype").and_then(Value::as_str).unwrap_or("f64") {
                    "str" => ColumnData::Str(
                        serde_json::from_value(c.get("values").cloned().unwrap_or_default())
                            .map_err(|e| de(name, e))?,
                    ),
                    _ => match &p.take(name)?.data {
                        Buf::F64(v) => ColumnData::F64(v.clone()),
                        Buf::I64(v) => ColumnData::I64(v.clone()),
                        _ => return Err(format!("column `{name}` must be f64 or i64")),
                    },
                };
                t.columns.push(Column {
                    name: name.into(),
                    unit: unit.into(),
                    data,
                });
            }
            t.validate()?;
            Artifact::Table(t)
        }
        ArtifactKind::Tensor => {
            let a = p.take("values")?;
            let Buf::F64(v) = &a.data else {
                return Err("`values` must be f64".into());
            };
            let convention = match meta.get("convention") {
                Some(c) => serde_json::from_value(c.clone()).map_err(|e| de("convention", e))?,
                None => TensorConvention::Plain,
            };
            let s = |k: &str| {
                meta.get(k)
                    .and_then(Value::as_str)
                    .unwrap_or("")
                    .to_string()
            };
            Artifact::Tensor(Tensor {
                name: s("name"),
                unit: s("unit"),
                shape: a.shape.clone(),
                values: v.clone(),
                convention,
            })
        }
        ArtifactKind::Packing => {
            let domain: Domain =
                serde_json::from_value(get("domain")?).map_err(|e| de("domain", e))?;
            let (Buf::F64(pos), Buf::F64(radii)) =
                (&p.take("positions")?.data, &p.take("radii")?.data)
            else {
                return Err("`positions` and `radii` must be f64".into());
            };
            expect_len(p.take("positions")?, 3 * radii.len())?;
            let mut packing = Packing::new(domain);
            for (i, r) in radii.iter().enumerate() {
                packing.bodies.push(Body::sphere(
                    [pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]],
                    *r,
                ));
            }
            Artifact::Packing(packing)
        }
        other => return Err(format!("a {other} cannot cross the plugin ABI")),
    })
}

// ---------------------------------------------------------------------------------------
// Host callbacks.

/// State of one call into a plugin; `GpHost::ctx` points to it.
#[derive(Default)]
struct HostCtx {
    error: Option<(String, String)>,
    preflight: Option<String>,
    declared: Vec<(String, ArtifactKind)>,
    outputs: IndexMap<String, PendingOutput>,
    /// The RunContext of a run (type-erased so the struct has no lifetime).
    progress: Option<*const c_void>,
}

impl HostCtx {
    fn host(&mut self) -> GpHost {
        GpHost {
            struct_size: std::mem::size_of::<GpHost>() as u32,
            ctx: self as *mut HostCtx as *mut c_void,
            set_error: cb_set_error,
            set_preflight: cb_set_preflight,
            set_output: cb_set_output,
            alloc_array: cb_alloc_array,
            progress: cb_progress,
            log: cb_log,
        }
    }
}

/// # Safety
/// `ctx` must be the pointer given in `GpHost::ctx` during a call.
unsafe fn ctx<'a>(ctx: *mut c_void) -> &'a mut HostCtx {
    // SAFETY: guaranteed by the caller; the host is single-threaded per call.
    unsafe { &mut *(ctx as *mut HostCtx) }
}

fn lossy(s: GpStr) -> String {
    // SAFETY: plugins pass strings valid for the duration of the callback.
    match unsafe { s.to_str() } {
        Ok(s) => s.to_string(),
        Err(e) => format!("<{e}>"),
    }
}

extern "C" fn cb_set_error(c: *mut c_void, key: GpStr, message: GpStr) {
    // SAFETY: called by the plugin with our ctx.
    unsafe { ctx(c) }.error = Some((lossy(key), lossy(message)));
}

extern "C" fn cb_set_preflight(c: *mut c_void, json: GpStr) {
    // SAFETY: as above.
    unsafe { ctx(c) }.preflight = Some(lossy(json));
}

extern "C" fn cb_set_output(c: *mut c_void, port: GpStr, kind: GpStr, meta: GpStr) -> i32 {
    // SAFETY: as above.
    let h = unsafe { ctx(c) };
    let (port, kind) = (lossy(port), lossy(kind));
    match h.declared.iter().find(|(p, _)| *p == port) {
        Some((_, k)) if k.to_string() == kind => {
            h.outputs.entry(port).or_default().meta = lossy(meta);
            0
        }
        _ => 1,
    }
}

/// Refuses arrays above 2^40 elements: a corrupt shape must not take the machine down.
const MAX_ELEMENTS: usize = 1 << 40;

extern "C" fn cb_alloc_array(
    c: *mut c_void,
    port: GpStr,
    name: GpStr,
    dt: u32,
    ndim: u32,
    shape: *const usize,
) -> *mut c_void {
    // SAFETY: as above.
    let h = unsafe { ctx(c) };
    let port = lossy(port);
    if !h.declared.iter().any(|(p, _)| *p == port) || (ndim > 0 && shape.is_null()) || ndim > 8 {
        return std::ptr::null_mut();
    }
    let shape: Vec<usize> = if ndim == 0 {
        vec![]
    } else {
        // SAFETY: the plugin passes ndim extents.
        unsafe { std::slice::from_raw_parts(shape, ndim as usize) }.to_vec()
    };
    let n = match shape.iter().try_fold(1usize, |a, &b| a.checked_mul(b)) {
        Some(n) if n <= MAX_ELEMENTS => n,
        _ => return std::ptr::null_mut(),
    };
    let Some(buf) = Buf::zeroed(dt, n) else {
        return std::ptr::null_mut();
    };
    let out = h.outputs.entry(port).or_default();
    let name = lossy(name);
    out.arrays.retain(|a| a.name != name);
    out.arrays.push(NamedArray::new(&name, shape, buf));
    out.arrays.last_mut().expect("just pushed").data.mut_ptr()
}

extern "C" fn cb_progress(c: *mut c_void, done: u64, total: u64) -> i32 {
    // SAFETY: as above.
    let h = unsafe { ctx(c) };
    match h.progress {
        // SAFETY: set from a &RunContext that outlives the call.
        Some(rc) => i32::from(
            unsafe { &*(rc as *const RunContext) }
                .progress(done, total)
                .is_err(),
        ),
        None => 0,
    }
}

extern "C" fn cb_log(c: *mut c_void, level: i32, message: GpStr) {
    // SAFETY: as above.
    let h = unsafe { ctx(c) };
    if let Some(rc) = h.progress {
        // SAFETY: as above.
        let rc = unsafe { &*(rc as *const RunContext) };
        let m = lossy(message);
        if level == 0 {
            rc.info(&m)
        } else {
            rc.warn(&m)
        }
    }
}
