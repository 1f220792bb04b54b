//! A third-party grainpipe stage, built as a shared library and loaded by `pipe` at run time:
//! `example.porosity_profile`, the porosity of every slice of a phase image along an axis.
//!
//! Build: `cargo build --release -p grainpipe-plugin-example`, then
//! `pipe run pipeline.yaml --plugin-dir target/release` (or list the library under `plugins:`).

use grainpipe_plugin_api::{
    export_stages, ArtifactView, Failure, Outputs, ParamMeta, PluginStage, PortMeta, PreflightInfo,
    Progress, StageMeta,
};
use serde_json::Value;

pub struct PorosityProfile;

struct Params {
    axis: usize,
    pore_label: u8,
}

fn params(json: &str) -> Result<Params, Failure> {
    let v: Value =
        serde_json::from_str(json).map_err(|e| Failure::Failed(format!("params: {e}")))?;
    let axis = match v["axis"].as_str() {
        Some("x") => 0,
        Some("y") => 1,
        Some("z") => 2,
        other => {
            return Err(Failure::Param {
                key: "axis".into(),
                message: format!("{other:?} is not one of x, y, z"),
            })
        }
    };
    let pore_label = v["pore_label"]
        .as_u64()
        .filter(|&l| l <= 255)
        .ok_or_else(|| Failure::Param {
            key: "pore_label".into(),
            message: "must be an integer label 0..255".into(),
        })?;
    Ok(Params {
        axis,
        pore_label: pore_label as u8,
    })
}

/// The image grid as read from the metadata JSON.
struct Grid {
    dims: [usize; 3],
    spacing: [f64; 3],
    origin: [f64; 3],
}

fn grid(image: &ArtifactView) -> Result<Grid, Failure> {
    let bad = |m: &str| Failure::Input {
        port: "image".into(),
        message: m.into(),
    };
    let meta: Value =
        serde_json::from_str(image.meta_json()).map_err(|_| bad("metadata is not JSON"))?;
    let g = &meta["grid"];
    let arr = |k: &str| -> Result<[f64; 3], Failure> {
        let a = g[k]
            .as_array()
            .filter(|a| a.len() == 3)
            .ok_or_else(|| bad("grid unknown"))?;
        Ok([
            a[0].as_f64().unwrap_or(0.0),
            a[1].as_f64().unwrap_or(0.0),
            a[2].as_f64().unwrap_or(0.0),
        ])
    };
    let d = arr("dims")?;
    Ok(Grid {
        dims: [d[0] as usize, d[1] as usize, d[2] as usize],
        spacing: arr("spacing")?,
        origin: arr("origin")?,
    })
}

impl PluginStage for PorosityProfile {
    fn meta(&self) -> StageMeta {
        StageMeta {
            id: "example.porosity_profile",
            version: "1.0.0",
            doc: "Porosity of every slice of a phase image normal to an axis (fraction of voxels \
                  carrying the pore label), with the slice centre coordinate. An example of a \
                  third-party stage loaded through the plugin C ABI.",
            params: vec![
                ParamMeta {
                    name: "axis",
                    ty: "one of x, y, z",
                    unit: "",
                    doc: "axis the profile runs along",
                    default_json: "\"z\"",
                },
                ParamMeta {
                    name: "pore_label",
                    ty: "integer 0..255",
                    unit: "",
                    doc: "label of the pore phase",
                    default_json: "0",
                },
            ],
            inputs: vec![PortMeta {
                name: "image",
                kind: "PhaseImage",
                doc: "segmented volume",
                optional: false,
            }],
            outputs: vec![PortMeta {
                name: "profile",
                kind: "Table",
                doc: "position [m], porosity",
                optional: false,
            }],
        }
    }

    fn preflight(
        &self,
        params_json: &str,
        inputs: &[ArtifactView],
    ) -> Result<PreflightInfo, Failure> {
        params(params_json)?;
        if !inputs.iter().any(|i| i.port() == "image") {
            return Err(Failure::Input {
                port: "image".into(),
                message: "not connected".into(),
            });
        }
        Ok(PreflightInfo::default())
    }

    fn run(
        &self,
        params_json: &str,
        inputs: &[ArtifactView],
        out: &mut Outputs,
        progress: &Progress,
    ) -> Result<(), Failure> {
        let p = params(params_json)?;
        let image = inputs
            .iter()
            .find(|i| i.port() == "image")
            .ok_or(Failure::Failed("no image".into()))?;
        let Grid {
            dims,
            spacing,
            origin,
        } = grid(image)?;
        let labels = image
            .array("labels")
            .and_then(|a| a.as_slice::<u8>())
            .ok_or(Failure::Input {
                port: "image".into(),
                message: "no u8 `labels` array".into(),
            })?;
        if labels.len() != dims.iter().product::<usize>() {
            return Err(Failure::Input {
                port: "image".into(),
                message: "labels do not match the grid".into(),
            });
        }
        let n = dims[p.axis];
        let mut pores = vec![0u64; n];
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    if labels[x + dims[0] * (y + dims[1] * z)] == p.pore_label {
                        pores[[x, y, z][p.axis]] += 1;
                    }
                }
            }
            progress.report(z as u64 + 1, dims[2] as u64)?;
        }
        let per_slice = (dims.iter().product::<usize>() / n.max(1)) as f64;
        out.declare(
            "profile",
            "Table",
            r#"{"name":"porosity_profile","columns":[{"name":"position","unit":"m","dtype":"f64"},{"name":"porosity","unit":"1","dtype":"f64"}]}"#,
        )?;
        let position = out.alloc::<f64>("profile", "position", &[n])?;
        for (i, x) in position.iter_mut().enumerate() {
            *x = origin[p.axis] + (i as f64 + 0.5) * spacing[p.axis];
        }
        let porosity = out.alloc::<f64>("profile", "porosity", &[n])?;
        for (v, c) in porosity.iter_mut().zip(&pores) {
            *v = *c as f64 / per_slice;
        }
        Ok(())
    }
}

export_stages!(PorosityProfile);
