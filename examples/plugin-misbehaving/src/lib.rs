//! Test fixture for the plugin host: stages that misbehave in the ways the ABI must contain.

use grainpipe_plugin_api::{
    export_stages, ArtifactView, Failure, Outputs, PluginStage, PortMeta, Progress, StageMeta,
};

/// Panics while running.
pub struct Panics;
/// Writes one element past the end of the output buffer the host gave it.
pub struct Overflows;

fn meta(id: &'static str, doc: &'static str) -> StageMeta {
    StageMeta {
        id,
        version: "1.0.0",
        doc,
        params: vec![],
        inputs: vec![],
        outputs: vec![PortMeta {
            name: "table",
            kind: "Table",
            doc: "never valid",
            optional: false,
        }],
    }
}

/// Asks the host for 2^37 f64 (1 TiB): the host must refuse, not abort.
pub struct Huge;

impl PluginStage for Panics {
    fn meta(&self) -> StageMeta {
        // The host must survive a panic in the metadata call too (it would abort `pipe list`);
        // the hardening tests set this variable to provoke one.
        if std::env::var_os("GRAINPIPE_MISBEHAVE_PANIC_IN_METADATA").is_some() {
            panic!("deliberate panic in metadata");
        }
        meta("misbehave.panic", "Panics in run.")
    }
    fn run(
        &self,
        _: &str,
        _: &[ArtifactView],
        _: &mut Outputs,
        _: &Progress,
    ) -> Result<(), Failure> {
        panic!("deliberate panic inside a plugin")
    }
}

impl PluginStage for Overflows {
    fn meta(&self) -> StageMeta {
        meta(
            "misbehave.overflow",
            "Writes past the end of its output buffer.",
        )
    }
    fn run(
        &self,
        _: &str,
        _: &[ArtifactView],
        out: &mut Outputs,
        _: &Progress,
    ) -> Result<(), Failure> {
        out.declare(
            "table",
            "Table",
            r#"{"name":"t","columns":[{"name":"x","unit":"","dtype":"f64"}]}"#,
        )?;
        let x = out.alloc::<f64>("table", "x", &[4])?;
        let past_the_end = x.len();
        x[past_the_end] = 1.0; // bounds-checked: panics instead of corrupting host memory
        Ok(())
    }
}

impl PluginStage for Huge {
    fn meta(&self) -> StageMeta {
        meta("misbehave.huge", "Asks for an output of 2^37 f64 (1 TiB).")
    }
    fn run(
        &self,
        _: &str,
        _: &[ArtifactView],
        out: &mut Outputs,
        _: &Progress,
    ) -> Result<(), Failure> {
        out.declare(
            "table",
            "Table",
            r#"{"name":"t","columns":[{"name":"x","unit":"","dtype":"f64"}]}"#,
        )?;
        out.alloc::<f64>("table", "x", &[1usize << 37])?;
        Ok(())
    }
}

export_stages!(Panics, Overflows, Huge);
