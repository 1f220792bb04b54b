//! Opens reports in a real headless browser (Debian's `chromium`): a run report built from
//! small synthetic artifacts, a sweep report and an `html` export. Each page must load with
//! every expected section present, every image decoded (the page's script sets
//! `data-images-ok` on <html>) and a screenshot written. Skipped, loudly, only when no
//! chromium is installed (`apt-get install chromium`).

use grainpipe_core::model::*;
use grainpipe_core::values::{Comparison, Verdict};
use grainpipe_report::data::{self, ReportData};
use grainpipe_report::numbers;
use grainpipe_report::record::{self, RunRecord, StepProvenance, StepRecord};
use std::path::{Path, PathBuf};
use std::process::Command;

fn chromium() -> Option<PathBuf> {
    for name in ["chromium", "chromium-browser", "google-chrome"] {
        for dir in std::env::var_os("PATH")
            .map(|p| std::env::split_paths(&p).collect::<Vec<_>>())
            .unwrap_or_default()
        {
            let p = dir.join(name);
            if p.is_file() {
                return Some(p);
            }
        }
    }
    None
}

/// Runs chromium headless on `page`; returns the DOM after load and writes `shot`.
fn browse(page: &Path, shot: &Path, profile: &Path) -> String {
    let exe = chromium().expect("checked");
    let url = format!("file://{}", page.canonicalize().unwrap().display());
    let common = [
        "--headless",
        "--disable-gpu",
        "--no-sandbox",
        "--no-first-run",
        "--disable-extensions",
        "--hide-scrollbars",
        "--virtual-time-budget=5000",
    ];
    let user = format!("--user-data-dir={}", profile.display());
    let out = Command::new(&exe)
        .args(common)
        .arg(&user)
        .arg("--dump-dom")
        .arg(&url)
        .env("HOME", profile)
        .output()
        .expect("chromium runs");
    assert!(
        out.status.success(),
        "chromium --dump-dom failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let dom = String::from_utf8_lossy(&out.stdout).into_owned();
    let out = Command::new(&exe)
        .args(common)
        .arg(&user)
        .arg(format!("--screenshot={}", shot.display()))
        .arg("--window-size=1200,3000")
        .arg(&url)
        .env("HOME", profile)
        .output()
        .expect("chromium runs");
    assert!(
        out.status.success(),
        "chromium --screenshot failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    dom
}

fn skip() -> bool {
    if chromium().is_none() {
        eprintln!(
            "\n\n*** SKIPPED: no chromium on PATH; the report was not checked in a browser. \
             Install it: apt-get install -y chromium ***\n\n"
        );
        return true;
    }
    false
}

/// With GRAINPIPE_REPORT_KEEP=DIR, the pages and screenshots are copied there to look at.
fn keep(files: &[&Path]) {
    if let Some(d) = std::env::var_os("GRAINPIPE_REPORT_KEEP") {
        let d = PathBuf::from(d);
        std::fs::create_dir_all(&d).unwrap();
        for f in files {
            // run/report.html -> run-report.html
            let parent = f.parent().and_then(|p| p.file_name()).unwrap_or_default();
            let name = format!(
                "{}-{}",
                parent.to_string_lossy(),
                f.file_name().unwrap().to_string_lossy()
            );
            let _ = std::fs::copy(f, d.join(name));
        }
    }
}

/// The screenshot is a real, non-blank PNG of the requested width.
fn check_screenshot(shot: &Path) {
    keep(&[shot]);
    let bytes = std::fs::read(shot).expect("screenshot written");
    let dec = png::Decoder::new(std::io::Cursor::new(bytes));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size()];
    let info = r.next_frame(&mut buf).unwrap();
    assert_eq!(info.width, 1200);
    let px = &buf[..info.buffer_size()];
    let first = &px[..3];
    let distinct = px
        .chunks(info.color_type.samples())
        .filter(|p| &p[..3] != first)
        .count();
    assert!(distinct > 1000, "screenshot is blank");
}

fn grid(n: usize, h: f64) -> Grid {
    Grid {
        dims: [n, n, n],
        spacing: [h; 3],
        origin: [0.0; 3],
        periodic: [true; 3],
    }
}

/// A sphere of grain with a binder shell in a periodic cube, its velocity, a stress pair,
/// the packing, an isotropic stiffness with its constants, a permeability.
fn synthetic() -> (RunRecord, ReportData, data::Pictures) {
    let n = 24;
    let h = 8e-6;
    let g = grid(n, h);
    let mut labels = vec![0u8; n * n * n];
    let c = n as f64 / 2.0;
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let r = ((x as f64 + 0.5 - c).powi(2)
                    + (y as f64 + 0.5 - c).powi(2)
                    + (z as f64 + 0.5 - c).powi(2))
                .sqrt();
                labels[g.index(x, y, z)] = if r < 8.0 {
                    1
                } else if r < 9.5 {
                    2
                } else {
                    0
                };
            }
        }
    }
    let img = PhaseImage {
        grid: g.clone(),
        labels: labels.clone(),
        phases: vec![
            Phase {
                id: 0,
                name: "pore".into(),
            },
            Phase {
                id: 1,
                name: "grain".into(),
            },
            Phase {
                id: 2,
                name: "binder".into(),
            },
        ],
    };
    let vel: Vec<f64> = (0..n * n * n)
        .flat_map(|i| {
            let s = if labels[i] == 0 {
                1e-3 * (i % 7) as f64
            } else {
                0.0
            };
            [s, 0.1 * s, 0.0]
        })
        .collect();
    let velocity = Field::new(
        g.clone(),
        "velocity",
        "m/s",
        ComponentConvention::Vector,
        FieldData::F64(vel),
    )
    .unwrap();
    let stress = |scale: f32| {
        let d: Vec<f32> = (0..n * n * n)
            .flat_map(|i| {
                let s = if labels[i] == 0 {
                    0.0
                } else {
                    scale * (1.0 + (i % 5) as f32)
                };
                [s, 0.2 * s, 0.1 * s, 0.0, 0.0, 0.05 * s]
            })
            .collect();
        Field::new(
            g.clone(),
            "stress",
            "Pa",
            ComponentConvention::Voigt,
            FieldData::F32(d),
        )
        .unwrap()
    };
    let stresses = Collection {
        items: vec![
            ("xx".into(), Artifact::Field(stress(1e9))),
            ("yy".into(), Artifact::Field(stress(2e9))),
        ],
    };
    let mut packing = Packing::new(Domain::boxed([0.0; 3], [n as f64 * h; 3], [true; 3]));
    for (k, p) in [
        [0.3, 0.3, 0.3],
        [0.7, 0.4, 0.6],
        [0.5, 0.75, 0.5],
        [0.2, 0.8, 0.8],
    ]
    .iter()
    .enumerate()
    {
        packing.bodies.push(Body::sphere(
            p.map(|v| v * n as f64 * h),
            (20.0 + 10.0 * k as f64) * 1e-6,
        ));
    }
    let (e, nu) = (4.8e9, 0.16);
    let c6 = numbers::isotropic_stiffness(e, nu);
    let stiffness = Tensor {
        name: "stiffness".into(),
        unit: "Pa".into(),
        shape: vec![6, 6],
        values: c6.concat(),
        convention: TensorConvention::Voigt,
    };
    let k = numbers::engineering(&c6).unwrap();
    let mut constants = Table::new("constants").with_str(
        "approximation",
        vec![
            "apparent".into(),
            "orthotropic".into(),
            "transversely_isotropic_z".into(),
            "isotropic".into(),
        ],
    );
    for (j, name) in numbers::ENGINEERING_NAMES.iter().enumerate() {
        constants = constants.with_f64(name, if j < 6 { "Pa" } else { "" }, vec![k[j]; 4]);
    }
    constants = constants.with_f64("relative_error", "", vec![0.0, 0.0476, 0.0666, 0.0948]);
    let permeability = Tensor {
        name: "permeability".into(),
        unit: "m^2".into(),
        shape: vec![3, 3],
        values: vec![3.8e-11, 2e-13, 0.0, 2e-13, 3.9e-11, 0.0, 0.0, 0.0, 3.5e-11],
        convention: TensorConvention::Plain,
    };
    // Two load cases converging at different rates, 100 rows in all (more than a table shows).
    let history = Table::new("history")
        .with_str(
            "load_case",
            (0..100)
                .map(|i| if i < 50 { "xx" } else { "yy" }.to_string())
                .collect(),
        )
        .with_i64("iteration", "", (0..100).map(|i| i % 50).collect())
        .with_f64(
            "residual",
            "",
            (0..100)
                .map(|i| {
                    if i < 50 {
                        0.7f64.powi(i)
                    } else {
                        0.6f64.powi(i - 50)
                    }
                })
                .collect(),
        );
    let mut pics = vec![];
    let items = vec![
        data::item("pack.packing", &Artifact::Packing(packing), &mut pics),
        data::item("binder.image", &Artifact::PhaseImage(img), &mut pics),
        data::item(
            "stiffness.stiffness",
            &Artifact::Tensor(stiffness),
            &mut pics,
        ),
        data::item(
            "stiffness.constants",
            &Artifact::Table(constants),
            &mut pics,
        ),
        data::item(
            "stiffness.stress",
            &Artifact::Collection(stresses),
            &mut pics,
        ),
        data::item("stiffness.history", &Artifact::Table(history), &mut pics),
        data::item(
            "flow.permeability",
            &Artifact::Tensor(permeability),
            &mut pics,
        ),
        data::item("flow.velocity", &Artifact::Field(velocity), &mut pics),
    ];
    let step = |s: &str, st: &str, w: f64| StepRecord {
        step: s.into(),
        stage: st.into(),
        wall_s: w,
        from_cache: s == "pack",
        peak_bytes: Some(1 << 20),
        peak_heap_bytes: Some(3 << 20),
        estimate_bytes: Some(2 << 20),
    };
    let rec = RunRecord {
        grainpipe_version: grainpipe_core::VERSION.into(),
        pipeline_file: "pipelines/synthetic.yaml".into(),
        pipeline_name: "synthetic <test>".into(),
        description: "a synthetic run".into(),
        seed: 42,
        overrides: vec!["binder.binder_fraction=0.03".into()],
        effective_yaml: "name: synthetic\n".into(),
        source_yaml: "name: synthetic\n".into(),
        started_unix_s: 1.8e9,
        wall_s: 3.5,
        status: "ok".into(),
        error: None,
        steps: vec![
            step("pack", "mcm.stacked", 0.0),
            step("binder", "binder.levelset", 1.0),
            step("stiffness", "elasticity.fft", 2.0),
            step("flow", "stokes.permeability", 0.5),
        ],
        exports: vec![],
        provenance: vec![
            StepProvenance {
                step: "pack".into(),
                stage: "mcm.stacked".into(),
                stage_version: "1.0.0".into(),
                origin: "built-in".into(),
                seed: 7,
                cache_key: "abc".into(),
                params: serde_json::json!({"layers": 2}),
                inputs: vec![],
                input_files: vec![],
            },
            StepProvenance {
                step: "stiffness".into(),
                stage: "elasticity.fft".into(),
                stage_version: "1.0.0".into(),
                origin: "built-in".into(),
                seed: 8,
                cache_key: "def".into(),
                params: serde_json::json!({"tolerance": 1e-6}),
                inputs: vec![],
                input_files: vec![],
            },
        ],
        host: "test".into(),
        threads: 2,
        warnings: vec![grainpipe_report::WarningRecord {
            step: "pack".into(),
            text: "radii: KS test against the target law failed (p = 0.003 < 0.01)".into(),
        }],
        reference: Some(grainpipe_report::record::ReferenceRecord {
            source: "a test table".into(),
            note: String::new(),
            rows: vec![
                Comparison {
                    quantity: "stiffness.constants.E_x".into(),
                    component: None,
                    reference: 5.0e9,
                    reference_written: "5 GPa".into(),
                    result: Some(4.6e9),
                    unit: "Pa".into(),
                    relative_difference: Some(-0.08),
                    tolerance: "10 %".into(),
                    verdict: Verdict::Within,
                    why: String::new(),
                },
                Comparison {
                    quantity: "flow.permeability.kappa_zz".into(),
                    component: Some("kappa_zz".into()),
                    reference: 1.0e-11,
                    reference_written: "1e-11 m^2".into(),
                    result: Some(3.5e-11),
                    unit: "m^2".into(),
                    relative_difference: Some(2.5),
                    tolerance: "20 %".into(),
                    verdict: Verdict::Outside,
                    why: String::new(),
                },
            ],
        }),
        auto_voxel: None,
    };
    (rec, ReportData { items }, pics)
}

fn attr<'a>(dom: &'a str, name: &str) -> Option<&'a str> {
    let start = dom.find(&format!("{name}=\""))? + name.len() + 2;
    let end = dom[start..].find('"')? + start;
    Some(&dom[start..end])
}

#[test]
fn run_report_in_a_browser() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("run");
    let (rec, data, pics) = synthetic();
    let mut rec = rec;
    // A PNG the run exported (as `bonds_top.png` of a sintering run): shown inline.
    let exported = tmp.path().join("bonds_top.png");
    let mut bonds = grainpipe_report::raster::Rgb::new(40, 30, [250, 250, 250]);
    bonds.set(10, 10, [200, 0, 0]);
    std::fs::write(&exported, bonds.png()).unwrap();
    rec.exports.push(record::ExportRecord {
        from: "sinter.bonds".into(),
        path: exported.display().to_string(),
        format: "png".into(),
        written: true,
    });
    record::write_run_files(&dir, &rec, &data, &pics).unwrap();
    let page = grainpipe_report::render_dir(&dir, None).unwrap();
    assert_eq!(page, dir.join("report.html"));
    let html = std::fs::read_to_string(&page).unwrap();
    // Self-contained: nothing fetched from elsewhere.
    assert!(!html.contains("src=\"http") && !html.contains("href=\"http"));
    // The numbers shown: the isotropic stiffness gives back E = 4.8 GPa and nu = 0.16, and
    // the permeability's symmetry error is 0 (symmetric by construction).
    assert!(
        html.contains("E_x 4.8 GPa, E_y 4.8 GPa, E_z 4.8 GPa"),
        "headline moduli"
    );
    assert!(
        html.contains("E = 4.8 GPa, ν = 0.16"),
        "Table 7 isotropy row"
    );
    assert!(html.contains("9.48 %"));
    assert!(html.contains("<span class=\"symmetry-error\">0</span>"));
    assert!(html.contains("100 rows; the first and last 20 shown"));
    // Issue 36: no remark about a paper on a run that declares no reference.
    assert!(
        !html.contains("the paper reports"),
        "a paper's numbers on a run's page"
    );
    // Issue 36: reference values only where the pipeline declares them, in their written
    // unit, judged against their tolerance.
    assert!(html.contains("<a href=\"#reference\">Reference</a>"));
    assert!(html.contains("1 of 2 within their tolerance"));
    assert!(
        html.contains("<td>4.6 GPa</td><td>5 GPa</td><td>−0.4 GPa (−8.00 %)</td><td>± 10 %</td>")
    );
    assert!(html.contains("<span class=\"bad\">outside</span>"));
    // Issue 36: warnings are shown at the top and per step, and the status says so.
    assert!(html.contains("id=\"status\">completed with 1 warning</span>"));
    assert!(html.contains("<span class=\"step\">pack</span>: radii: KS test"));
    assert!(html.contains("cache, <a class=\"warn\" href=\"#warnings\">1 warning</a>"));
    // Issue 36: the residual history on a log axis, a line per load case, the tolerance.
    let conv = html
        .split("<svg class=\"chart convergence\"")
        .nth(1)
        .expect("a convergence chart");
    assert!(conv.starts_with(" data-y-scale=\"log\""), "{}", &conv[..80]);
    let conv = &conv[..conv.find("</svg>").unwrap()];
    assert!(conv.contains("tolerance 1e-6"), "tolerance line");
    assert!(conv.contains("xx") && conv.contains("yy"), "load cases");
    assert!(
        conv.contains("1e-6") && conv.contains("iteration"),
        "log ticks"
    );
    // Issue 36: every slice and rendering framed with axes in µm and a scale bar; fields
    // with a colour bar in their unit.
    assert_eq!(html.matches("<svg class=\"slice-axes\"").count(), 14);
    assert!(html.contains("x [µm]") && html.contains("z [µm]"));
    assert_eq!(html.matches("data-scale-bar=\"").count(), 14);
    assert!(html.contains("velocity magnitude [m/s]"));
    assert!(html.contains("von Mises equivalent of stress [Pa]"));
    if skip() {
        return;
    }
    let shot = tmp.path().join("run.png");
    let dom = browse(&page, &shot, &tmp.path().join("profile"));
    keep(&[&page]);
    for id in [
        "warnings",
        "summary",
        "microstructure",
        "packing",
        "fields",
        "convergence",
        "pictures",
        "stiffness",
        "permeability",
        "tables",
        "steps",
        "exports",
        "provenance",
    ] {
        assert!(
            dom.contains(&format!("<section id=\"{id}\"")),
            "section #{id} missing"
        );
    }
    // 3 phase slices + 2 renderings + 3 velocity slices + 2 x 3 stress slices + 1 export.
    assert_eq!(attr(&dom, "data-images"), Some("15"), "image count");
    assert_eq!(
        attr(&dom, "data-images-ok"),
        Some("true"),
        "an image is broken"
    );
    assert!(dom.contains("von Mises equivalent of stress"));
    assert!(
        dom.contains("<svg class=\"chart histogram\""),
        "size distribution chart"
    );
    assert!(dom.contains("data-y-scale=\"log\""), "log residual axis");
    assert!(dom.contains("class=\"slice-axes\""), "slice axes");
    assert!(
        dom.contains("bonds_top.png (from sinter.bonds)"),
        "exported PNG"
    );
    check_screenshot(&shot);
}

#[test]
fn sweep_report_and_html_export_in_a_browser() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("sweep");
    std::fs::create_dir_all(&dir).unwrap();
    let mut csv = String::from(
        "run,point,realization,binder_fraction [1],E_x [Pa],flow.permeability[8] [m^2],seed,wall_time [s],peak_memory [B],status,error\n",
    );
    for p in 0..2 {
        for r in 0..8 {
            let e = 4.5e9 + 0.4e9 * p as f64 + 1e8 * ((r * 37 % 11) as f64 - 5.0);
            let _ = std::fmt::Write::write_fmt(
                &mut csv,
                format_args!(
                    "p{p}-r{r},{p},{r},{},{e},{},{},1.5,1e8,ok,\n",
                    0.02 + 0.02 * p as f64,
                    3.5e-11 - 1e-12 * r as f64,
                    1000 + r
                ),
            );
        }
    }
    std::fs::write(dir.join("sweep.csv"), csv).unwrap();
    std::fs::write(
        dir.join("sweep.json"),
        r#"{"pipeline_name":"sandcore","vary":[{"key":"binder_fraction","values":["0.02","0.04"]}]}"#,
    )
    .unwrap();
    // A run's result.json names the tensor component; the sweep's charts/ has a mean
    // against the parameter; the directory is a study with a chosen level.
    std::fs::create_dir_all(dir.join("runs/p0-r0")).unwrap();
    std::fs::write(
        dir.join("runs/p0-r0/result.json"),
        r#"{"id":"p0-r0","status":"ok","error":"","seed":1000,"wall_time":1.5,"peak_memory":1,
            "values":[{"name":"flow.permeability[8]","unit":"m^2","value":3.5e-11,"component":"kappa_zz"}]}"#,
    )
    .unwrap();
    let mean = grainpipe_charts::Figure {
        title: "E_x against binder_fraction (mean, 90 % CI)".into(),
        x_label: "binder_fraction".into(),
        y_label: "E_x [Pa]".into(),
        series: vec![grainpipe_charts::Series {
            name: "mean".into(),
            points: vec![(0.02, 4.5e9), (0.04, 4.9e9)],
            err: vec![(4.4e9, 4.6e9), (4.8e9, 5.0e9)],
            line: true,
            markers: true,
            ..Default::default()
        }],
        ..Default::default()
    };
    mean.save(&dir.join("charts/E_x_vs_binder_fraction"))
        .unwrap();
    std::fs::write(
        dir.join("study.json"),
        r#"{"parameter":"binder_fraction","metric":"E_x","levels":["0.02","0.04"],
            "error_basis":"finest level","target_error":0.05,"chosen_level":"0.04",
            "evidence":{"error":0.01,"wall_time_s":1.5,"peak_memory_bytes":100000000}}"#,
    )
    .unwrap();
    let front = grainpipe_charts::Figure {
        x_label: "wall time [s]".into(),
        y_label: "relative error".into(),
        x_log: true,
        y_log: true,
        series: vec![grainpipe_charts::Series {
            name: "Pareto front".into(),
            points: vec![(1.0, 0.1), (1.5, 0.01)],
            line: true,
            ..Default::default()
        }],
        ..Default::default()
    };
    front.save(&dir.join("study")).unwrap();
    let page = grainpipe_report::render_dir(&dir, None).unwrap();
    let html = std::fs::read_to_string(&page).unwrap();
    // One chart per value column (E_x, kappa_zz, wall_time, peak_memory; the constant ones
    // get violins without a density), each with the violins of both points: one y axis.
    assert_eq!(html.matches("<svg class=\"violin\"").count(), 4);
    assert_eq!(html.matches("data-violins=\"2\"").count(), 4);
    let ex = html
        .split("data-column=\"E_x\"")
        .nth(1)
        .unwrap()
        .split("</div>")
        .next()
        .unwrap();
    assert_eq!(
        ex.matches("<svg").count(),
        1,
        "one chart for the violins of E_x"
    );
    assert_eq!(ex.matches("<polygon").count(), 2, "two violins in it");
    // The shared y range holds every value of both points (4.0e9 .. 5.5e9).
    let range = attr(ex, "data-y-range").unwrap();
    let (lo, hi) = range.split_once(' ').unwrap();
    let (lo, hi): (f64, f64) = (lo.parse().unwrap(), hi.parse().unwrap());
    assert!(lo <= 4.0e9 && hi >= 5.3e9, "{range}");
    // Tensor components by name.
    assert!(html.contains("flow.permeability kappa_zz [m^2]"));
    // The sweep's mean-against-parameter chart and the study's front and choice.
    assert!(html.contains("data-file=\"E_x_vs_binder_fraction.svg\""));
    assert!(html.contains("<section id=\"study\""));
    assert!(html.contains("<span class=\"ok\" id=\"chosen-level\">0.04</span>"));
    assert!(html.contains("data-file=\"study.svg\""));

    // The html export of one artifact (a phase image with provenance).
    let g = grid(10, 1e-5);
    let img = PhaseImage {
        grid: g.clone(),
        labels: (0..1000).map(|i| (i % 3) as u8).collect(),
        phases: vec![
            Phase {
                id: 0,
                name: "pore".into(),
            },
            Phase {
                id: 1,
                name: "grain".into(),
            },
        ],
    };
    let mut prov = Provenance::default();
    prov.entries.insert("step".into(), "binder.image".into());
    prov.entries.insert("pipeline_name".into(), "t".into());
    prov.entries
        .insert("pipeline_yaml".into(), "name: t\n".into());
    let exp = grainpipe_report::export::HtmlExporter;
    let html_path = tmp.path().join("image.html");
    grainpipe_core::Exporter::write_defaults(&exp, &Artifact::PhaseImage(img), &html_path, &prov)
        .unwrap();
    if skip() {
        return;
    }
    let dom = browse(
        &page,
        &tmp.path().join("sweep.png"),
        &tmp.path().join("profile"),
    );
    keep(&[&page]);
    for id in ["summary", "violins", "charts", "study", "intervals", "runs"] {
        assert!(
            dom.contains(&format!("<section id=\"{id}\"")),
            "section #{id} missing"
        );
    }
    assert!(dom.contains("binder_fraction = 0.02"));
    check_screenshot(&tmp.path().join("sweep.png"));
    let dom = browse(
        &html_path,
        &tmp.path().join("image.png"),
        &tmp.path().join("profile"),
    );
    assert_eq!(attr(&dom, "data-images"), Some("3"));
    assert_eq!(attr(&dom, "data-images-ok"), Some("true"));
    assert!(dom.contains("<section id=\"provenance\""));
    assert!(dom.contains("label 2"), "unnamed label listed");
}
