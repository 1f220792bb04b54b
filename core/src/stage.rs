//! The stage contract: what a stage declares (id, version, doc, parameters, ports), how it
//! is checked before anything runs (`preflight`) and how it runs.
//!
//! Stage authors implement [`TypedStage`] with a serde params struct; the engine sees the
//! object-safe [`Stage`], whose parameters are JSON values (the same representation crosses
//! the C ABI for third-party plugins).

use crate::model::{Artifact, ArtifactKind, ArtifactMeta, Grid};
use crate::params::{unknown_keys, Params};
use indexmap::IndexMap;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::any::Any;
use std::sync::Arc;

pub use crate::params::ParamSpec;

/// A declared input or output port.
#[derive(Clone, Debug)]
pub struct PortSpec {
    pub name: &'static str,
    pub kind: ArtifactKind,
    pub doc: &'static str,
    /// Optional inputs may be left unconnected.
    pub optional: bool,
}

impl PortSpec {
    pub const fn new(name: &'static str, kind: ArtifactKind, doc: &'static str) -> Self {
        PortSpec {
            name,
            kind,
            doc,
            optional: false,
        }
    }
    pub const fn optional(name: &'static str, kind: ArtifactKind, doc: &'static str) -> Self {
        PortSpec {
            name,
            kind,
            doc,
            optional: true,
        }
    }
}

/// Everything a stage says about itself.
#[derive(Clone, Debug)]
pub struct StageInfo {
    /// `<family>.<name>`, e.g. `packing.rsa`.
    pub id: &'static str,
    /// Semantic version; part of the cache key, so bump it when results change.
    pub version: &'static str,
    /// One paragraph: what it does, the method, the paper it follows.
    pub doc: &'static str,
    /// Filled from the stage's parameter declaration (`#[params]`); leave it empty.
    pub params: Vec<ParamSpec>,
    pub inputs: Vec<PortSpec>,
    pub outputs: Vec<PortSpec>,
}

impl StageInfo {
    /// A stage with no ports yet; add them with [`StageInfo::inputs`] and [`StageInfo::outputs`].
    pub fn new(id: &'static str, version: &'static str, doc: &'static str) -> Self {
        StageInfo {
            id,
            version,
            doc,
            params: Vec::new(),
            inputs: Vec::new(),
            outputs: Vec::new(),
        }
    }
    pub fn inputs(mut self, inputs: Vec<PortSpec>) -> Self {
        self.inputs = inputs;
        self
    }
    pub fn outputs(mut self, outputs: Vec<PortSpec>) -> Self {
        self.outputs = outputs;
        self
    }
}

/// Result of a successful preflight: what the run will produce, what it will cost, and the
/// stage's own plan (what preflight worked out and `run` consumes, so nothing is parsed or
/// built twice; `()` for stages with nothing to carry over).
#[derive(Clone, Debug)]
pub struct Preflight<P = ()> {
    /// The outputs the run will give, with everything known about them before running (grid,
    /// domain box, count bounds). A stage whose parameters select among alternative outputs
    /// (e.g. `as: phase_image | field`) lists only the selected ones; consumers and exports of
    /// an unlisted output are refused before anything runs. The engine checks the produced
    /// artifacts against these announcements.
    pub outputs: IndexMap<String, ArtifactMeta>,
    /// Estimated peak memory of `run` [bytes].
    pub memory_bytes: u64,
    pub plan: P,
}

impl Preflight {
    /// Outputs as declared by `info`, nothing known about them yet, given memory estimate.
    pub fn from_info(info: &StageInfo, memory_bytes: u64) -> Self {
        Preflight {
            outputs: info
                .outputs
                .iter()
                .map(|p| (p.name.to_string(), ArtifactMeta::of(p.kind)))
                .collect(),
            memory_bytes,
            plan: (),
        }
    }
}

impl<P> Preflight<P> {
    /// The same announcement carrying another plan.
    pub fn with_plan<Q>(self, plan: Q) -> Preflight<Q> {
        Preflight {
            outputs: self.outputs,
            memory_bytes: self.memory_bytes,
            plan,
        }
    }

    /// Replaces what is announced about output `port`.
    pub fn announce(mut self, port: &str, meta: ArtifactMeta) -> Self {
        self.outputs.insert(port.to_string(), meta);
        self
    }
}

/// Errors a stage reports. Parameter and input errors are found in preflight and refer to
/// the YAML; failures happen while running (a packing that jams, a solver that diverges).
#[derive(Debug, thiserror::Error)]
pub enum StageError {
    #[error("parameter `{key}`: {message}")]
    InvalidParam { key: String, message: String },
    #[error("unknown parameter `{key}`")]
    UnknownParam {
        key: String,
        /// The closest declared parameter name.
        suggestion: Option<String>,
    },
    #[error("input `{port}`: {message}")]
    InvalidInput { port: String, message: String },
    #[error("{0}")]
    Failed(String),
    #[error("cancelled")]
    Cancelled,
    #[error("I/O: {0}")]
    Io(#[from] std::io::Error),
    /// Several parameter errors of one step, reported together so a user fixes them in one
    /// pass instead of one run per mistake.
    #[error("{}", .0.iter().map(|e| e.to_string()).collect::<Vec<_>>().join("; "))]
    Several(Vec<StageError>),
}

impl StageError {
    pub fn param(key: &str, message: impl Into<String>) -> Self {
        StageError::InvalidParam {
            key: key.to_string(),
            message: message.into(),
        }
    }
    pub fn input(port: &str, message: impl Into<String>) -> Self {
        StageError::InvalidInput {
            port: port.to_string(),
            message: message.into(),
        }
    }
    pub fn failed(message: impl Into<String>) -> Self {
        StageError::Failed(message.into())
    }
}

/// Receives progress and messages from a running stage; also carries the cancel flag.
pub trait Reporter: Send + Sync {
    /// `done` out of `total` units of work (total 0 = unknown).
    fn progress(&self, done: u64, total: u64);
    fn message(&self, level: Level, text: &str);
    fn cancelled(&self) -> bool;
    /// A short status beside the bar (an iterative solver's residual against its tolerance);
    /// reporters without a bar ignore it.
    fn detail(&self, _text: &str) {}
}

/// Progress of an iterative solver measured by its residual, not its iteration count: an
/// iteration count against `max_iterations` shows 1 % and "eta 6 h" for a solve that ends
/// in a minute. Each case (load case, flow direction) counts as the fraction of the way its
/// residual has come from the largest it has reported down to the tolerance, on a log scale
/// (CG and MINRES residuals fall about geometrically): ln(r_max / r) / ln(r_max / tol),
/// clamped to [0, 1], never moving back. Shared by parallel cases (a mutex per update; the
/// updates are once per iteration of a whole-image sweep).
pub struct ResidualProgress {
    tolerance: f64,
    /// Per case: the largest residual reported and the furthest fraction shown.
    cases: std::sync::Mutex<Vec<(f64, f64)>>,
}

impl ResidualProgress {
    /// Units of the progress total per case.
    const STEPS: u64 = 1000;

    pub fn new(cases: usize, tolerance: f64) -> Self {
        ResidualProgress {
            tolerance,
            cases: std::sync::Mutex::new(vec![(0.0, 0.0); cases.max(1)]),
        }
    }

    /// Records that `case` is at `residual`; returns (done, total) over all cases and the
    /// status text (`case 2/3: residual 3.2e-4 -> 1.0e-5`).
    pub fn update(&self, case: usize, residual: f64) -> (u64, u64, String) {
        let mut cases = self.cases.lock().unwrap_or_else(|p| p.into_inner());
        let n = cases.len();
        let (max, shown) = &mut cases[case.min(n - 1)];
        if residual.is_finite() {
            *max = max.max(residual);
        }
        let fraction = if residual <= self.tolerance {
            1.0
        } else if *max > self.tolerance && residual.is_finite() && residual > 0.0 {
            ((*max / residual).ln() / (*max / self.tolerance).ln()).clamp(0.0, 1.0)
        } else {
            0.0
        };
        *shown = shown.max(fraction);
        let done: f64 = cases.iter().map(|c| c.1).sum();
        let text = format!(
            "case {}/{n}: residual {residual:.1e} -> {:.1e}",
            case.min(n - 1) + 1,
            self.tolerance
        );
        (
            (done * Self::STEPS as f64).round() as u64,
            n as u64 * Self::STEPS,
            text,
        )
    }

    /// Marks `case` as done (converged, or stopped by its own criterion).
    pub fn finish(&self, case: usize) {
        let mut cases = self.cases.lock().unwrap_or_else(|p| p.into_inner());
        let n = cases.len();
        cases[case.min(n - 1)].1 = 1.0;
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Level {
    Info,
    Warn,
}

/// A reporter that discards everything (tests, nested runs).
pub struct SilentReporter;

impl Reporter for SilentReporter {
    fn progress(&self, _: u64, _: u64) {}
    fn message(&self, _: Level, _: &str) {}
    fn cancelled(&self) -> bool {
        false
    }
}

/// What a running stage gets from the engine.
pub struct RunContext<'a> {
    /// The stage's own seed, derived from the pipeline seed and the step id.
    pub seed: u64,
    reporter: &'a dyn Reporter,
}

impl<'a> RunContext<'a> {
    pub fn new(seed: u64, reporter: &'a dyn Reporter) -> Self {
        RunContext { seed, reporter }
    }

    /// A fresh generator for this stage's stream. Calling it twice gives the same stream.
    pub fn rng(&self) -> ChaCha8Rng {
        ChaCha8Rng::seed_from_u64(self.seed)
    }

    /// An independent stream `k` of this stage, for parallel work whose result must not
    /// depend on the number of threads (give each work item its own stream).
    pub fn substream(&self, k: u64) -> ChaCha8Rng {
        ChaCha8Rng::seed_from_u64(crate::derive_seed(self.seed, &k.to_le_bytes()))
    }

    /// Reports progress; returns `Err(Cancelled)` when the user interrupted the run.
    pub fn progress(&self, done: u64, total: u64) -> Result<(), StageError> {
        self.reporter.progress(done, total);
        if self.reporter.cancelled() {
            Err(StageError::Cancelled)
        } else {
            Ok(())
        }
    }

    /// Reports an iterative solver's residual (see [`ResidualProgress`]): the bar moves by
    /// the residual's way down to the tolerance and shows the residual beside it. Returns
    /// `Err(Cancelled)` when the user interrupted the run.
    pub fn residual_progress(
        &self,
        progress: &ResidualProgress,
        case: usize,
        residual: f64,
    ) -> Result<(), StageError> {
        let (done, total, text) = progress.update(case, residual);
        self.reporter.detail(&text);
        self.progress(done, total)
    }

    /// `Err(Cancelled)` when the user interrupted the run, without reporting progress: for
    /// inner loops that may run long between progress reports (a packing near jamming).
    pub fn check_cancelled(&self) -> Result<(), StageError> {
        if self.reporter.cancelled() {
            Err(StageError::Cancelled)
        } else {
            Ok(())
        }
    }

    pub fn info(&self, text: &str) {
        self.reporter.message(Level::Info, text);
    }

    pub fn warn(&self, text: &str) {
        self.reporter.message(Level::Warn, text);
    }
}

/// Inputs by port name.
pub type Inputs = IndexMap<String, Arc<Artifact>>;
/// Outputs by port name.
pub type Outputs = IndexMap<String, Artifact>;
/// Input metadata by port name, for preflight.
pub type InputMetas = IndexMap<String, ArtifactMeta>;

/// Fetches a typed input, with an error naming the port when it is missing or of the wrong kind.
pub fn input<'a, T>(
    inputs: &'a Inputs,
    port: &str,
    get: impl Fn(&'a Artifact) -> Option<&'a T>,
) -> Result<&'a T, StageError> {
    let a = inputs
        .get(port)
        .ok_or_else(|| StageError::input(port, "not connected"))?;
    get(a).ok_or_else(|| StageError::input(port, format!("got a {}", a.kind())))
}

/// The grid announced upstream for the image at `port`, for preflights whose memory estimate
/// needs it (the image solvers); an error naming the port when it is not known before running.
pub fn announced_grid(inputs: &InputMetas, port: &str) -> Result<Grid, StageError> {
    inputs
        .get(port)
        .and_then(|m| m.grid.clone())
        .ok_or_else(|| {
            StageError::input(
                port,
                "the grid of the image is not known before running; give the upstream stage a \
             voxel_size so the memory can be estimated",
            )
        })
}

/// What a stage's preflight prepared for its run (the typed parameters and the stage's plan),
/// held by the engine between planning and running.
pub type Prepared = Arc<dyn Any + Send + Sync>;

/// The object-safe stage interface the engine uses.
pub trait Stage: Send + Sync {
    fn info(&self) -> &StageInfo;
    /// Default parameter values as JSON (SI numbers).
    fn default_params(&self) -> serde_json::Value;
    /// Parses and validates parameters; returns the canonical JSON (defaults filled in, units
    /// converted to SI), which is what the cache key hashes.
    fn normalize_params(&self, params: &serde_json::Value)
        -> Result<serde_json::Value, StageError>;
    /// Checks parameters (canonical JSON) and input metadata; announces the outputs and the
    /// memory needed, and prepares what `run` consumes.
    fn preflight(
        &self,
        params: &serde_json::Value,
        inputs: &InputMetas,
    ) -> Result<(Preflight, Prepared), StageError>;
    fn run(
        &self,
        params: &serde_json::Value,
        prepared: &Prepared,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError>;
}

/// The typed interface stage authors implement.
pub trait TypedStage: Send + Sync + 'static {
    /// A struct declared with `#[params]`.
    type Params: Params;
    /// What preflight works out and run needs again (a parsed file, a built geometry);
    /// `()` when there is nothing to carry over.
    type Plan: Send + Sync + 'static;
    /// Id, version, doc and ports; the parameters come from `Params`.
    fn info(&self) -> StageInfo;
    /// Checks parameter values and input shapes without allocating anything large, and
    /// announces the outputs (with grids, boxes and counts where they are known).
    fn preflight(
        &self,
        params: &Self::Params,
        inputs: &InputMetas,
    ) -> Result<Preflight<Self::Plan>, StageError>;
    fn run(
        &self,
        params: &Self::Params,
        plan: &Self::Plan,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError>;
}

/// Adapts a [`TypedStage`] to [`Stage`].
pub struct Typed<T: TypedStage> {
    inner: T,
    info: StageInfo,
    /// This stage's defaults, key by key (flattened groups included).
    defaults: serde_json::Map<String, serde_json::Value>,
}

impl<T: TypedStage> Typed<T> {
    pub fn new(inner: T) -> Self {
        let mut info = inner.info();
        debug_assert!(
            info.params.is_empty(),
            "{}: parameters come from the Params declaration",
            info.id
        );
        info.params = T::Params::specs();
        let defaults = match serde_json::to_value(T::Params::default()) {
            Ok(serde_json::Value::Object(m)) => m,
            other => panic!(
                "{}: parameters must serialize to a mapping, got {other:?}",
                info.id
            ),
        };
        Typed {
            inner,
            info,
            defaults,
        }
    }

    /// Checks the keys against the declaration, fills in this stage's defaults, then
    /// deserializes. Filling the defaults here (rather than leaving them to serde) is what
    /// gives a flattened group the defaults of the stage that includes it: serde would take
    /// the group's own `Default` for keys missing inside a flattened field.
    fn parse(&self, params: &serde_json::Value) -> Result<T::Params, StageError> {
        let given = match params {
            serde_json::Value::Object(m) => m,
            serde_json::Value::Null => &serde_json::Map::new(),
            _ => return Err(StageError::param("", "parameters must be a mapping")),
        };
        // Every unknown key and every value that fails on its own, in the order written.
        let unknown = unknown_keys(params, &self.info.params);
        let mut errors: Vec<StageError> = Vec::new();
        for (k, v) in given {
            if let Some(u) = unknown.iter().find(|u| &u.key == k) {
                errors.push(StageError::UnknownParam {
                    key: u.key.clone(),
                    suggestion: u.suggestion.clone(),
                });
            } else if let Some(Err((key, message))) = T::Params::check_value(k, v) {
                errors.push(StageError::InvalidParam { key, message });
            }
        }
        match errors.len() {
            0 => {}
            1 => return Err(errors.remove(0)),
            _ => return Err(StageError::Several(errors)),
        }
        let mut full = self.defaults.clone();
        for (k, v) in given {
            full.insert(k.clone(), v.clone());
        }
        let full = serde_json::Value::Object(full);
        serde_path_to_error::deserialize(&full).map_err(|e| {
            let path = e.path().to_string();
            let message = e.into_inner().to_string();
            // Every given value already deserialized alone above (which is also what locates
            // an error inside a flattened group, where serde loses the path), and the rest
            // are this stage's defaults: what fails here is the mapping as a whole.
            let key = if path == "." || path.is_empty() {
                unknown_field_name(&message).unwrap_or_default()
            } else {
                path
            };
            StageError::InvalidParam { key, message }
        })
    }
}

/// Extracts `x` from serde's "unknown field `x`, expected ..." message.
pub fn unknown_field_name(message: &str) -> Option<String> {
    let rest = message.strip_prefix("unknown field `")?;
    Some(rest[..rest.find('`')?].to_string())
}

impl<T: TypedStage> Stage for Typed<T> {
    fn info(&self) -> &StageInfo {
        &self.info
    }
    fn default_params(&self) -> serde_json::Value {
        serde_json::to_value(T::Params::default()).expect("params serialize")
    }
    fn normalize_params(
        &self,
        params: &serde_json::Value,
    ) -> Result<serde_json::Value, StageError> {
        let p = self.parse(params)?;
        serde_json::to_value(p).map_err(|e| StageError::failed(e.to_string()))
    }
    fn preflight(
        &self,
        params: &serde_json::Value,
        inputs: &InputMetas,
    ) -> Result<(Preflight, Prepared), StageError> {
        let p = self.parse(params)?;
        let pf = self.inner.preflight(&p, inputs)?;
        let plan = pf.plan;
        let pf = Preflight {
            outputs: pf.outputs,
            memory_bytes: pf.memory_bytes,
            plan: (),
        };
        Ok((pf, Arc::new((p, plan))))
    }
    fn run(
        &self,
        _params: &serde_json::Value,
        prepared: &Prepared,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let (p, plan) = prepared
            .downcast_ref::<(T::Params, T::Plan)>()
            .ok_or_else(|| {
                StageError::failed(format!(
                    "internal error: `{}` ran without its own preflight",
                    self.info.id
                ))
            })?;
        self.inner.run(p, plan, inputs, ctx)
    }
}

#[cfg(test)]
mod residual_progress_tests {
    use super::ResidualProgress;

    /// A residual falling geometrically from 1 to the tolerance 1e-6 moves the bar linearly:
    /// 1e-3 is half way, the tolerance is the end; a residual that rises again does not move
    /// the bar back; two cases each count for half.
    #[test]
    fn residual_progress_is_linear_in_log_residual() {
        let p = ResidualProgress::new(2, 1e-6);
        assert_eq!(p.update(0, 1.0).0, 0);
        let (done, total, text) = p.update(0, 1e-3);
        assert_eq!(total, 2000);
        assert_eq!(done, 500);
        assert_eq!(text, "case 1/2: residual 1.0e-3 -> 1.0e-6");
        assert_eq!(p.update(0, 1e-1).0, 500, "never back");
        assert_eq!(
            p.update(1, 1e-2).0,
            500,
            "a case's first residual is its start"
        );
        assert_eq!(p.update(1, 1e-4).0, 500 + 500);
        assert_eq!(p.update(0, 5e-7).0, 1000 + 500);
        p.finish(1);
        assert_eq!(p.update(1, f64::NAN).0, 2000);
    }
}
