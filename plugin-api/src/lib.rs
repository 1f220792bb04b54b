//! The stable C ABI between `pipe` and third-party stages, and a safe Rust layer over it.
//!
//! A plugin is a shared library exporting two symbols:
//! - `uint32_t grainpipe_abi_version(void)`: `(major << 16) | minor` of [`ABI_VERSION`];
//! - `const GpPluginVTable *grainpipe_plugin_entry(const GpHost *host)`.
//!
//! Metadata (stage ids, versions, docs, parameter schema) and parameter values cross as UTF-8
//! JSON. Arrays cross as borrowed views `{ptr, dtype, shape, strides}`; outputs are allocated
//! through the host's `alloc_array`, so the allocator that allocates also frees. Progress is a
//! host callback whose return value is the cancel flag; errors are a status code plus a
//! message given to `set_error`. The same layout is declared for C in
//! `include/grainpipe_plugin.h`.
//!
//! Rust authors implement [`PluginStage`] and call [`export_stages!`]; every entry point is
//! wrapped in `catch_unwind`, so a panicking stage yields an error, not an abort, and output
//! buffers are handed out as bounded slices, so safe code cannot write outside them.

use std::ffi::c_void;
use std::panic::{catch_unwind, AssertUnwindSafe};

/// Major version: bumped on any incompatible change; the host refuses a different major.
pub const ABI_MAJOR: u32 = 1;
/// Minor version: bumped on compatible additions (new trailing struct fields, new dtypes).
pub const ABI_MINOR: u32 = 0;
/// `(major << 16) | minor`.
pub const ABI_VERSION: u32 = (ABI_MAJOR << 16) | ABI_MINOR;

/// Status codes returned by `preflight` and `run`.
pub mod status {
    pub const OK: i32 = 0;
    /// A parameter is invalid; `set_error` key = parameter name.
    pub const INVALID_PARAM: i32 = 1;
    /// An input is invalid; `set_error` key = port name.
    pub const INVALID_INPUT: i32 = 2;
    /// The method failed (did not converge, ...).
    pub const FAILED: i32 = 3;
    /// The host asked to stop.
    pub const CANCELLED: i32 = 4;
    /// The plugin panicked (caught at the boundary).
    pub const PANIC: i32 = 5;
}

/// Element types of arrays.
pub mod dtype {
    pub const U8: u32 = 1;
    pub const U32: u32 = 2;
    pub const I64: u32 = 3;
    pub const F32: u32 = 4;
    pub const F64: u32 = 5;

    /// Size in bytes of one element, 0 for an unknown dtype.
    pub fn size(d: u32) -> usize {
        match d {
            U8 => 1,
            U32 | F32 => 4,
            I64 | F64 => 8,
            _ => 0,
        }
    }
}

/// Element types that cross the ABI, with their dtype code.
pub trait Element: Copy + 'static + private::Sealed {
    const DTYPE: u32;
}

mod private {
    pub trait Sealed {}
}

macro_rules! element {
    ($($t:ty => $d:expr),*) => {$(
        impl private::Sealed for $t {}
        impl Element for $t {
            const DTYPE: u32 = $d;
        }
    )*};
}
element!(u8 => dtype::U8, u32 => dtype::U32, i64 => dtype::I64, f32 => dtype::F32, f64 => dtype::F64);

/// A borrowed UTF-8 string (not NUL-terminated).
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct GpStr {
    pub ptr: *const u8,
    pub len: usize,
}

impl GpStr {
    pub fn new(s: &str) -> GpStr {
        GpStr {
            ptr: s.as_ptr(),
            len: s.len(),
        }
    }

    /// # Safety
    /// `ptr` must point to `len` readable bytes that outlive `'a` (or be null with len 0).
    pub unsafe fn to_str<'a>(self) -> Result<&'a str, String> {
        if self.len == 0 {
            return Ok("");
        }
        if self.ptr.is_null() {
            return Err("null string".into());
        }
        // SAFETY: guaranteed by the caller.
        let bytes = unsafe { std::slice::from_raw_parts(self.ptr, self.len) };
        std::str::from_utf8(bytes).map_err(|e| format!("invalid UTF-8: {e}"))
    }
}

/// A borrowed n-dimensional array. Strides are in bytes; the host always passes C-contiguous
/// arrays (last index fastest), but a reader should check.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct GpArray {
    pub name: GpStr,
    pub dtype: u32,
    pub ndim: u32,
    pub shape: *const usize,
    pub strides: *const isize,
    pub data: *const c_void,
}

/// An artifact: its kind (`"PhaseImage"`, `"Field"`, `"Table"`, `"Tensor"`, `"Packing"`),
/// metadata as JSON and named arrays. In preflight, `n_arrays` is 0 and the metadata says
/// what is known before running (the grid, when known).
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct GpArtifact {
    pub port: GpStr,
    pub kind: GpStr,
    pub meta_json: GpStr,
    pub n_arrays: u32,
    pub arrays: *const GpArray,
}

/// Callbacks the host gives to every call.
#[repr(C)]
pub struct GpHost {
    /// `size_of::<GpHost>()` as the host knows it: fields beyond it must not be used.
    pub struct_size: u32,
    pub ctx: *mut c_void,
    /// Reports an error: `key` is the parameter or port concerned (may be empty).
    pub set_error: extern "C" fn(ctx: *mut c_void, key: GpStr, message: GpStr),
    /// Preflight result: `{"memory_bytes": n, "outputs": {"port": {meta}}}`.
    pub set_preflight: extern "C" fn(ctx: *mut c_void, json: GpStr),
    /// Declares an output artifact; returns 0, or non-zero if the port or kind is wrong.
    pub set_output:
        extern "C" fn(ctx: *mut c_void, port: GpStr, kind: GpStr, meta_json: GpStr) -> i32,
    /// Allocates an output array owned by the host, zero-filled, C-contiguous; returns null
    /// on a bad dtype, an undeclared port or a size overflow.
    pub alloc_array: extern "C" fn(
        ctx: *mut c_void,
        port: GpStr,
        name: GpStr,
        dtype: u32,
        ndim: u32,
        shape: *const usize,
    ) -> *mut c_void,
    /// Reports progress; returns 1 when the run should stop.
    pub progress: extern "C" fn(ctx: *mut c_void, done: u64, total: u64) -> i32,
    /// Logs a message: level 0 info, 1 warning.
    pub log: extern "C" fn(ctx: *mut c_void, level: i32, message: GpStr),
}

/// What a plugin exports through `grainpipe_plugin_entry`.
#[repr(C)]
pub struct GpPluginVTable {
    /// `size_of::<GpPluginVTable>()` as the plugin knows it.
    pub struct_size: u32,
    pub abi_version: u32,
    /// `{"stages": [{id, version, doc, params: [{name, ty, unit, doc, default}], inputs: [...],
    /// outputs: [...]}]}`; must stay valid for the life of the process.
    pub metadata_json: extern "C" fn() -> GpStr,
    pub preflight: extern "C" fn(
        stage: u32,
        params_json: GpStr,
        inputs: *const GpArtifact,
        n_inputs: u32,
        host: *const GpHost,
    ) -> i32,
    pub run: extern "C" fn(
        stage: u32,
        params_json: GpStr,
        inputs: *const GpArtifact,
        n_inputs: u32,
        host: *const GpHost,
    ) -> i32,
}

// ---------------------------------------------------------------------------------------
// The safe Rust layer.

/// A declared parameter. `default_json` is the default as JSON text (`"0.5"`, `"\"z\""`).
/// Numbers with a non-empty `unit` are given to the stage in SI; YAML may use unit strings.
pub struct ParamMeta {
    pub name: &'static str,
    pub ty: &'static str,
    pub unit: &'static str,
    pub doc: &'static str,
    pub default_json: &'static str,
}

/// A declared port; `kind` is an artifact kind name such as `"PhaseImage"`.
pub struct PortMeta {
    pub name: &'static str,
    pub kind: &'static str,
    pub doc: &'static str,
    pub optional: bool,
}

/// What a stage says about itself.
pub struct StageMeta {
    pub id: &'static str,
    pub version: &'static str,
    pub doc: &'static str,
    pub params: Vec<ParamMeta>,
    pub inputs: Vec<PortMeta>,
    pub outputs: Vec<PortMeta>,
}

/// Why a stage call failed.
#[derive(Debug)]
pub enum Failure {
    Param { key: String, message: String },
    Input { port: String, message: String },
    Failed(String),
    Cancelled,
}

/// A borrowed input array.
pub struct ArrayView<'a> {
    raw: &'a GpArray,
}

impl<'a> ArrayView<'a> {
    pub fn name(&self) -> &'a str {
        // SAFETY: the host keeps names alive for the duration of the call.
        unsafe { self.raw.name.to_str() }.unwrap_or("")
    }
    pub fn dtype(&self) -> u32 {
        self.raw.dtype
    }
    pub fn shape(&self) -> &'a [usize] {
        if self.raw.ndim == 0 {
            return &[];
        }
        // SAFETY: the host passes `ndim` extents.
        unsafe { std::slice::from_raw_parts(self.raw.shape, self.raw.ndim as usize) }
    }
    fn contiguous_len(&self, elem: usize) -> Option<usize> {
        let shape = self.shape();
        // SAFETY: the host passes `ndim` strides.
        let strides =
            unsafe { std::slice::from_raw_parts(self.raw.strides, self.raw.ndim as usize) };
        let mut expected = elem as isize;
        for (s, n) in strides.iter().zip(shape).rev() {
            if *s != expected {
                return None;
            }
            expected *= *n as isize;
        }
        Some(shape.iter().product())
    }
    /// The elements as a slice, if the dtype is `T` and the array is contiguous.
    pub fn as_slice<T: Element>(&self) -> Option<&'a [T]> {
        if self.raw.dtype != T::DTYPE {
            return None;
        }
        let n = self.contiguous_len(std::mem::size_of::<T>())?;
        if n == 0 {
            return Some(&[]);
        }
        // SAFETY: dtype, contiguity and length checked; the host keeps the data alive and
        // aligned for T for the duration of the call.
        Some(unsafe { std::slice::from_raw_parts(self.raw.data as *const T, n) })
    }
}

/// A borrowed input artifact.
pub struct ArtifactView<'a> {
    raw: &'a GpArtifact,
}

impl<'a> ArtifactView<'a> {
    pub fn port(&self) -> &'a str {
        // SAFETY: kept alive by the host during the call.
        unsafe { self.raw.port.to_str() }.unwrap_or("")
    }
    pub fn kind(&self) -> &'a str {
        // SAFETY: as above.
        unsafe { self.raw.kind.to_str() }.unwrap_or("")
    }
    /// Metadata JSON (grid, phase table, units, column names, ...).
    pub fn meta_json(&self) -> &'a str {
        // SAFETY: as above.
        unsafe { self.raw.meta_json.to_str() }.unwrap_or("{}")
    }
    pub fn arrays(&self) -> impl Iterator<Item = ArrayView<'a>> {
        let arrays: &'a [GpArray] = if self.raw.n_arrays == 0 {
            &[]
        } else {
            // SAFETY: the host passes `n_arrays` arrays.
            unsafe { std::slice::from_raw_parts(self.raw.arrays, self.raw.n_arrays as usize) }
        };
        arrays.iter().map(|raw| ArrayView { raw })
    }
    pub fn array(&self, name: &str) -> Option<ArrayView<'a>> {
        self.arrays().find(|a| a.name() == name)
    }
}

/// Where a running stage puts its outputs. Buffers come from the host's allocator and are
/// handed out as bounded slices.
pub struct Outputs<'h> {
    host: &'h GpHost,
}

impl Outputs<'_> {
    /// Declares output `port` of `kind` with its metadata JSON.
    pub fn declare(&mut self, port: &str, kind: &str, meta_json: &str) -> Result<(), Failure> {
        let r = (self.host.set_output)(
            self.host.ctx,
            GpStr::new(port),
            GpStr::new(kind),
            GpStr::new(meta_json),
        );
        if r == 0 {
            Ok(())
        } else {
            Err(Failure::Failed(format!(
                "the host refused output `{port}` of kind `{kind}`"
            )))
        }
    }

    /// Allocates output array `name` of `port` (zero-filled, C-contiguous, owned by the
    /// host) and returns it as a slice of exactly `shape.iter().product()` elements.
    pub fn alloc<T: Element>(
        &mut self,
        port: &str,
        name: &str,
        shape: &[usize],
    ) -> Result<&mut [T], Failure> {
        let n = shape
            .iter()
            .try_fold(1usize, |a, &b| a.checked_mul(b))
            .ok_or_else(|| Failure::Failed(format!("array `{name}`: size overflow")))?;
        let p = (self.host.alloc_array)(
            self.host.ctx,
            GpStr::new(port),
            GpStr::new(name),
            T::DTYPE,
            shape.len() as u32,
            shape.as_ptr(),
        );
        if p.is_null() {
            return Err(Failure::Failed(format!(
                "the host could not allocate `{port}.{name}` {shape:?}"
            )));
        }
        if n == 0 {
            return Ok(&mut []);
        }
        // SAFETY: the host returned a zeroed, aligned buffer of exactly n elements of T that
        // lives until the call returns and is not aliased.
        Ok(unsafe { std::slice::from_raw_parts_mut(p as *mut T, n) })
    }
}

/// Progress reporting and cancellation.
pub struct Progress<'h> {
    host: &'h GpHost,
}

impl Progress<'_> {
    /// Reports progress; `Err(Cancelled)` when the user interrupted the run.
    pub fn report(&self, done: u64, total: u64) -> Result<(), Failure> {
        if (self.host.progress)(self.host.ctx, done, total) != 0 {
            Err(Failure::Cancelled)
        } else {
            Ok(())
        }
    }
    pub fn info(&self, message: &str) {
        (self.host.log)(self.host.ctx, 0, GpStr::new(message));
    }
    pub fn warn(&self, message: &str) {
        (self.host.log)(self.host.ctx, 1, GpStr::new(message));
    }
}

/// Preflight answer: estimated memory, and optionally metadata JSON per output port.
#[derive(Default)]
pub struct PreflightInfo {
    pub memory_bytes: u64,
    pub outputs: Vec<(String, String)>,
}

/// A stage written in safe Rust. `params_json` is the canonical parameter object: every
/// declared parameter present (defaults filled in), dimensional numbers in SI.
pub trait PluginStage: Send + Sync + 'static {
    fn meta(&self) -> StageMeta;
    /// Checks parameters and input metadata; allocate nothing large here.
    fn preflight(
        &self,
        params_json: &str,
        inputs: &[ArtifactView],
    ) -> Result<PreflightInfo, Failure> {
        let _ = (params_json, inputs);
        Ok(PreflightInfo::default())
    }
    fn run(
        &self,
        params_json: &str,
        inputs: &[ArtifactView],
        outputs: &mut Outputs,
        progress: &Progress,
    ) -> Result<(), Failure>;
}

/// The stages of one library (implemented by [`export_stages!`]).
pub trait StageSet: 'static {
    fn stages() -> &'static [Box<dyn PluginStage>];
    fn metadata() -> &'static str;
}

/// Minimal JSON string escaping for metadata.
pub fn json_string(s: &str) -> String {
    let mut o = String::with_capacity(s.len() + 2);
    o.push('"');
    for c in s.chars() {
        match c {
            '"' => o.push_str("\\\""),
            '\\' => o.push_str("\\\\"),
            '\n' => o.push_str("\\n"),
            '\r' => o.push_str("\\r"),
            '\t' => o.push_str("\\t"),
            c if (c as u32) < 0x20 => o.push_str(&format!("\\u{:04x}", c as u32)),
            c => o.push(c),
        }
    }
    o.push('"');
    o
}

/// The metadata JSON of a set of stages.
pub fn metadata_json(stages: &[Box<dyn PluginStage>]) -> String {
    let ports = |ps: &[PortMeta]| {
        ps.iter()
            .map(|p| {
                format!(
                    "{{\"name\":{},\"kind\":{},\"doc\":{},\"optional\":{}}}",
                    json_string(p.name),
                    json_string(p.kind),
                    json_string(p.doc),
                    p.optional
                )
            })
            .collect::<Vec<_>>()
            .join(",")
    };
    let items: Vec<String> = stages
        .iter()
        .map(|s| {
            let m = s.meta();
            let params = m
                .params
                .iter()
                .map(|p| {
                    format!(
                        "{{\"name\":{},\"ty\":{},\"unit\":{},\"doc\":{},\"default\":{}}}",
                        json_string(p.name),
                        json_string(p.ty),
                        json_string(p.unit),
                        json_string(p.doc),
                        p.default_json
                    )
                })
                .collect::<Vec<_>>()
                .join(",");
            format!(
                "{{\"id\":{},\"version\":{},\"doc\":{},\"params\":[{params}],\"inputs\":[{}],\"outputs\":[{}]}}",
                json_string(m.id),
                json_string(m.version),
                json_string(m.doc),
                ports(&m.inputs),
                ports(&m.outputs)
            )
        })
        .collect();
    format!("{{\"stages\":[{}]}}", items.join(","))
}

fn report_failure(host: &GpHost, f: Failure) -> i32 {
    let (code, key, msg) = match f {
        Failure::Param { key, message } => (status::INVALID_PARAM, key, message),
        Failure::Input { port, message } => (status::INVALID_INPUT, port, message),
        Failure::Failed(m) => (status::FAILED, String::new(), m),
        Failure::Cancelled => (status::CANCELLED, String::new(), "cancelled".into()),
    };
    (host.set_error)(host.ctx, GpStr::new(&key), GpStr::new(&msg));
    code
}

fn panic_message(p: Box<dyn std::any::Any + Send>) -> String {
    if let Some(s) = p.downcast_ref::<&str>() {
        s.to_string()
    } else if let Some(s) = p.downcast_ref::<String>() {
        s.clone()
    } else {
        "unknown panic".into()
    }
}

/// What an entry point does once its arguments are checked.
type EntryBody<'a> =
    &'a dyn Fn(&dyn PluginStage, &str, &[ArtifactView], &GpHost) -> Result<(), Failure>;

/// Shared body of the exported entry points: validate arguments, call, catch panics.
fn call<S: StageSet>(
    stage: u32,
    params_json: GpStr,
    inputs: *const GpArtifact,
    n_inputs: u32,
    host: *const GpHost,
    body: EntryBody,
) -> i32 {
    if host.is_null() {
        return status::FAILED;
    }
    // SAFETY: the host passes a valid GpHost for the duration of the call.
    let host = unsafe { &*host };
    let result = catch_unwind(AssertUnwindSafe(|| {
        let s = S::stages()
            .get(stage as usize)
            .ok_or_else(|| Failure::Failed(format!("no stage {stage} in this plugin")))?;
        // SAFETY: the host keeps the params string alive during the call.
        let params =
            unsafe { params_json.to_str() }.map_err(|e| Failure::Failed(format!("params: {e}")))?;
        let raw: &[GpArtifact] = if n_inputs == 0 {
            &[]
        } else {
            // SAFETY: the host passes n_inputs artifacts.
            unsafe { std::slice::from_raw_parts(inputs, n_inputs as usize) }
        };
        let views: Vec<ArtifactView> = raw.iter().map(|raw| ArtifactView { raw }).collect();
        body(s.as_ref(), params, &views, host)
    }));
    match result {
        Ok(Ok(())) => status::OK,
        Ok(Err(f)) => report_failure(host, f),
        Err(p) => {
            let msg = format!("plugin panicked: {}", panic_message(p));
            (host.set_error)(host.ctx, GpStr::new(""), GpStr::new(&msg));
            status::PANIC
        }
    }
}

#[doc(hidden)]
pub extern "C" fn __preflight<S: StageSet>(
    stage: u32,
    params_json: GpStr,
    inputs: *const GpArtifact,
    n_inputs: u32,
    host: *const GpHost,
) -> i32 {
    call::<S>(
        stage,
        params_json,
        inputs,
        n_inputs,
        host,
        &|s, p, views, host| {
            let info = s.preflight(p, views)?;
            let outputs = info
                .outputs
                .iter()
                .map(|(k, v)| format!("{}:{v}", json_string(k)))
                .collect::<Vec<_>>()
                .join(",");
            let json = format!(
                "{{\"memory_bytes\":{},\"outputs\":{{{outputs}}}}}",
                info.memory_bytes
            );
            (host.set_preflight)(host.ctx, GpStr::new(&json));
            Ok(())
        },
    )
}

#[doc(hidden)]
pub extern "C" fn __run<S: StageSet>(
    stage: u32,
    params_json: GpStr,
    inputs: *const GpArtifact,
    n_inputs: u32,
    host: *const GpHost,
) -> i32 {
    call::<S>(
        stage,
        params_json,
        inputs,
        n_inputs,
        host,
        &|s, p, views, host| {
            let mut out = Outputs { host };
            let progress = Progress { host };
            s.run(p, views, &mut out, &progress)
        },
    )
}

#[doc(hidden)]
pub extern "C" fn __metadata<S: StageSet>() -> GpStr {
    // A panic must not unwind out of an `extern "C"` function (that aborts the host, and with
    // it `pipe list`): it becomes `{"panic": message}`, which the host reports as an error.
    // The text is leaked: the contract says metadata lives as long as the library.
    match catch_unwind(S::metadata) {
        Ok(m) => GpStr::new(m),
        Err(p) => {
            static PANIC: std::sync::OnceLock<String> = std::sync::OnceLock::new();
            let text =
                PANIC.get_or_init(|| format!("{{\"panic\":{}}}", json_string(&panic_message(p))));
            GpStr::new(text)
        }
    }
}

/// Exports the given stages (expressions of types implementing [`PluginStage`]) from a
/// `cdylib` crate: defines `grainpipe_abi_version` and `grainpipe_plugin_entry`.
///
/// ```ignore
/// grainpipe_plugin_api::export_stages!(PorosityProfile);
/// ```
#[macro_export]
macro_rules! export_stages {
    ($($stage:expr),+ $(,)?) => {
        #[doc(hidden)]
        pub struct __GrainpipeStages;
        impl $crate::StageSet for __GrainpipeStages {
            fn stages() -> &'static [::std::boxed::Box<dyn $crate::PluginStage>] {
                static STAGES: ::std::sync::OnceLock<::std::vec::Vec<::std::boxed::Box<dyn $crate::PluginStage>>> =
                    ::std::sync::OnceLock::new();
                STAGES.get_or_init(|| vec![$(::std::boxed::Box::new($stage)),+])
            }
            fn metadata() -> &'static str {
                static META: ::std::sync::OnceLock<::std::string::String> = ::std::sync::OnceLock::new();
                META.get_or_init(|| $crate::metadata_json(Self::stages()))
            }
        }
        #[doc(hidden)]
        pub static __GRAINPIPE_VTABLE: $crate::GpPluginVTable = $crate::GpPluginVTable {
            struct_size: ::std::mem::size_of::<$crate::GpPluginVTable>() as u32,
            abi_version: $crate::ABI_VERSION,
            metadata_json: $crate::__metadata::<__GrainpipeStages>,
            preflight: $crate::__preflight::<__GrainpipeStages>,
            run: $crate::__run::<__GrainpipeStages>,
        };
        #[no_mangle]
        pub extern "C" fn grainpipe_abi_version() -> u32 {
            $crate::ABI_VERSION
        }
        #[no_mangle]
        pub extern "C" fn grainpipe_plugin_entry(_host: *const $crate::GpHost) -> *const $crate::GpPluginVTable {
            &__GRAINPIPE_VTABLE
        }
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_strings_are_escaped() {
        assert_eq!(json_string("a\"b\\c\nd\u{1}"), "\"a\\\"b\\\\c\\nd\\u0001\"");
    }

    #[test]
    fn dtype_sizes() {
        assert_eq!(dtype::size(dtype::U8), 1);
        assert_eq!(dtype::size(dtype::F64), 8);
        assert_eq!(dtype::size(99), 0);
    }
}
