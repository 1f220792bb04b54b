//! `analysis.stress_stats`: per-phase statistics of a stress component normalised by its
//! mean (Heinze et al. 2020, section IV: Fig. 9, 13, 14 PDFs, Fig. 12 variance, Fig. 14d/15
//! exponential tail exponent, excess kurtosis after Laubie et al.).

use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, Field, InputMetas, Inputs, Outputs,
    ParamChoice, PhaseImage, PortSpec, Preflight, RunContext, StageError, StageInfo, Table,
    TypedStage,
};
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Component {
    /// sigma_xx.
    Xx,
    /// sigma_yy (the paper's tensile direction).
    Yy,
    /// sigma_zz (3-D).
    Zz,
    /// sigma_xy.
    Xy,
}

impl Component {
    fn name(self) -> &'static str {
        match self {
            Component::Xx => "xx",
            Component::Yy => "yy",
            Component::Zz => "zz",
            Component::Xy => "xy",
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Normalize {
    /// By the mean of each phase (Fig. 14: sigma^phase / mean sigma^phase).
    Phase,
    /// By the mean over all analysed nodes (Fig. 9, 13).
    Global,
}

#[params]
pub struct StressStatsParams {
    /// Stress component analysed.
    #[param(default = Component::Yy)]
    pub component: Component,
    /// What the stress is divided by.
    #[param(default = Normalize::Phase)]
    pub normalize: Normalize,
    /// Histogram bins over `range`.
    #[param(default = 70)]
    pub bins: usize,
    /// Range of sigma / mean covered by the PDFs (values outside are counted in the
    /// `outside` column).
    #[param(default = [-1.0, 6.0])]
    pub range: [f64; 2],
    /// The exponential tail pdf ~ exp(-s x) is fitted over bins with x >= this (Fig. 14d).
    #[param(default = 1.5)]
    pub tail_from: f64,
    /// Bins with fewer nodes than this are left out of the tail fit (their log is noise).
    #[param(default = 5)]
    pub tail_min_count: usize,
    /// Phase names or labels not analysed (the pore, label 0, has no stress).
    #[param(default = vec![grainpipe_core::phases::PORE.to_string(), "0".to_string()])]
    pub exclude: Vec<String>,
    /// Voxel layers along every face of the image (x, y; and z on 3-D images) left out:
    /// within a horizon of a free side a bond-based sample carries less stress (the side
    /// column ~0.78 of the bulk at h = 3, docs/stages/peridynamics.md), which otherwise
    /// enters the PDFs. The paper's horizon is 3 layers; 0 keeps every node.
    #[param(default = 0)]
    pub margin: usize,
}

pub struct StressStats;

fn check(p: &StressStatsParams) -> Result<(), StageError> {
    if !(2..=100_000).contains(&p.bins) {
        return Err(StageError::param("bins", "must be in 2..100000"));
    }
    if !(p.range[0].is_finite() && p.range[1].is_finite() && p.range[0] < p.range[1]) {
        return Err(StageError::param(
            "range",
            "must be [low, high] with low < high",
        ));
    }
    if !(p.tail_from.is_finite() && p.tail_from < p.range[1]) {
        return Err(StageError::param(
            "tail_from",
            "must be finite and below the upper end of `range`",
        ));
    }
    if p.tail_min_count == 0 {
        return Err(StageError::param("tail_min_count", "must be at least 1"));
    }
    Ok(())
}

/// Statistics of one phase.
#[derive(Clone, Debug, PartialEq)]
pub struct PhaseStats {
    pub name: String,
    pub label: u8,
    pub nodes: usize,
    /// Mean stress [Pa].
    pub mean: f64,
    /// Mean of x = sigma / normaliser.
    pub mean_x: f64,
    pub variance: f64,
    pub excess_kurtosis: f64,
    /// Tail exponent s of pdf ~ exp(-s x); None when fewer than 3 bins qualify.
    pub tail_exponent: Option<f64>,
    /// ln pdf of the tail fit extrapolated to x = 0; NaN without a fit.
    pub tail_intercept: f64,
    pub tail_bins: usize,
    pub tail_r2: f64,
    pub outside: usize,
    /// PDF per bin.
    pub pdf: Vec<f64>,
    /// The tail fit exp(a - s x) per bin with x >= tail_from, NaN elsewhere and without a fit.
    pub fit_pdf: Vec<f64>,
}

/// The exponential-tail fit ln pdf = a - s x of one phase.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TailFit {
    /// s; None when fewer than 3 bins qualify.
    pub exponent: Option<f64>,
    /// a = ln pdf extrapolated to x = 0 (NaN without a fit).
    pub intercept: f64,
    pub r2: f64,
    pub bins: usize,
}

impl TailFit {
    /// The fitted pdf at x, NaN without a fit.
    pub fn at(&self, x: f64) -> f64 {
        self.exponent
            .map(|s| (self.intercept - s * x).exp())
            .unwrap_or(f64::NAN)
    }
}

/// Weighted least squares of ln(pdf) = a - s x over the tail bins (weights = counts: the
/// variance of ln(count) is about 1/count).
pub fn tail_fit(
    centres: &[f64],
    counts: &[u64],
    width: f64,
    total: usize,
    from: f64,
    min_count: usize,
) -> TailFit {
    let mut pts = Vec::new();
    for (&x, &c) in centres.iter().zip(counts) {
        if x >= from && c as usize >= min_count {
            pts.push((x, (c as f64 / (total as f64 * width)).ln(), c as f64));
        }
    }
    let none = TailFit {
        exponent: None,
        intercept: f64::NAN,
        r2: 0.0,
        bins: pts.len(),
    };
    if pts.len() < 3 {
        return none;
    }
    let sw: f64 = pts.iter().map(|p| p.2).sum();
    let mx = pts.iter().map(|p| p.2 * p.0).sum::<f64>() / sw;
    let my = pts.iter().map(|p| p.2 * p.1).sum::<f64>() / sw;
    let sxx: f64 = pts.iter().map(|p| p.2 * (p.0 - mx).powi(2)).sum();
    let sxy: f64 = pts.iter().map(|p| p.2 * (p.0 - mx) * (p.1 - my)).sum();
    let syy: f64 = pts.iter().map(|p| p.2 * (p.1 - my).powi(2)).sum();
    if sxx <= 0.0 {
        return none;
    }
    let slope = sxy / sxx;
    let r2 = if syy > 0.0 {
        sxy * sxy / (sxx * syy)
    } else {
        1.0
    };
    TailFit {
        exponent: Some(-slope),
        intercept: my - slope * mx,
        r2,
        bins: pts.len(),
    }
}

/// The per-phase statistics of stress component `comp` of `stress` over `image`.
pub fn analyse(
    p: &StressStatsParams,
    stress: &Field,
    image: &PhaseImage,
) -> Result<(Vec<PhaseStats>, Vec<f64>), StageError> {
    check(p)?;
    if stress.grid.dims != image.grid.dims {
        return Err(StageError::input(
            "stress",
            format!(
                "grid {:?} differs from the image's {:?}",
                stress.grid.dims, image.grid.dims
            ),
        ));
    }
    let names = stress.component_names();
    let want = p.component.name();
    let comp = names.iter().position(|n| n == want).ok_or_else(|| {
        StageError::param(
            "component",
            format!("the stress field has components {names:?}, not `{want}`"),
        )
    })?;
    let nc = stress.components;
    let n = image.labels.len();
    let name_of = |l: u8| {
        image
            .phases
            .iter()
            .find(|ph| ph.id == l)
            .map(|ph| ph.name.clone())
            .unwrap_or_else(|| l.to_string())
    };
    let mut present = [0usize; 256];
    for &l in &image.labels {
        present[l as usize] += 1;
    }
    let labels: Vec<u8> = (0..=255u8)
        .filter(|&l| present[l as usize] > 0)
        .filter(|&l| {
            !p.exclude
                .iter()
                .any(|e| *e == name_of(l) || *e == l.to_string())
        })
        .collect();
    // Nodes with an all-zero tensor carry no material (excluded floating clusters).
    let is_node = |i: usize| (0..nc).any(|k| stress.data.get(i * nc + k) != 0.0);
    let dims = image.grid.dims;
    let inside = |i: usize| {
        let c = [
            i % dims[0],
            (i / dims[0]) % dims[1],
            i / (dims[0] * dims[1]),
        ];
        (0..3).all(|a| dims[a] == 1 || (c[a] >= p.margin && c[a] + p.margin < dims[a]))
    };
    let mut values: Vec<Vec<f64>> = vec![Vec::new(); 256];
    for i in 0..n {
        let l = image.labels[i];
        if labels.contains(&l) && is_node(i) && inside(i) {
            values[l as usize].push(stress.data.get(i * nc + comp));
        }
    }
    let global_mean = {
        let (s, c) = labels.iter().fold((0.0, 0usize), |(s, c), &l| {
            (
                s + values[l as usize].iter().sum::<f64>(),
                c + values[l as usize].len(),
            )
        });
        if c > 0 {
            s / c as f64
        } else {
            0.0
        }
    };
    let [lo, hi] = p.range;
    let width = (hi - lo) / p.bins as f64;
    let centres: Vec<f64> = (0..p.bins).map(|b| lo + (b as f64 + 0.5) * width).collect();
    let mut out = Vec::new();
    for &l in &labels {
        let v = &values[l as usize];
        if v.is_empty() {
            continue;
        }
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        let norm = match p.normalize {
            Normalize::Phase => mean,
            Normalize::Global => global_mean,
        };
        if norm == 0.0 || !norm.is_finite() {
            return Err(StageError::input(
                "stress",
                format!(
                    "the mean sigma_{want} of phase `{}` is {norm}: nothing to normalise by",
                    name_of(l)
                ),
            ));
        }
        let x: Vec<f64> = v.iter().map(|s| s / norm).collect();
        let nx = x.len() as f64;
        let mx = x.iter().sum::<f64>() / nx;
        let m2 = x.iter().map(|a| (a - mx).powi(2)).sum::<f64>() / nx;
        let m4 = x.iter().map(|a| (a - mx).powi(4)).sum::<f64>() / nx;
        let kurt = if m2 > 0.0 { m4 / (m2 * m2) - 3.0 } else { 0.0 };
        let mut counts = vec![0u64; p.bins];
        let mut outside = 0;
        for &a in &x {
            let b = ((a - lo) / width).floor();
            if b >= 0.0 && (b as usize) < p.bins {
                counts[b as usize] += 1;
            } else {
                outside += 1;
            }
        }
        // Normalised over all nodes of the phase, so mass outside the range is missing.
        let pdf = counts.iter().map(|&c| c as f64 / (nx * width)).collect();
        let fit = tail_fit(
            &centres,
            &counts,
            width,
            x.len(),
            p.tail_from,
            p.tail_min_count,
        );
        // The line over the bins it was fitted to (x >= tail_from), for plots.
        let fit_pdf = centres
            .iter()
            .map(|&c| {
                if c >= p.tail_from {
                    fit.at(c)
                } else {
                    f64::NAN
                }
            })
            .collect();
        out.push(PhaseStats {
            name: name_of(l),
            label: l,
            nodes: x.len(),
            mean,
            mean_x: mx,
            variance: m2,
            excess_kurtosis: kurt,
            tail_exponent: fit.exponent,
            tail_intercept: fit.intercept,
            tail_bins: fit.bins,
            tail_r2: fit.r2,
            outside,
            pdf,
            fit_pdf,
        });
    }
    if out.is_empty() {
        return Err(StageError::input(
            "image",
            "no phase left to analyse (all excluded or without stressed nodes)",
        ));
    }
    Ok((out, centres))
}

impl TypedStage for StressStats {
    type Params = StressStatsParams;
    type Plan = ();

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "analysis.stress_stats",
            "1.2.0",
            "Per-phase statistics of one stress component (Heinze et al. 2020, section IV): \
             the PDF of x = sigma / mean (mean of the phase, Fig. 14, or of all analysed \
             nodes, Fig. 9 and 13) as a histogram over `range`, normalised over all nodes of \
             the phase; the mean stress, the variance of x (Fig. 12), its excess kurtosis \
             (m4/m2^2 - 3, Laubie et al.), and the exponent s of the exponential tail \
             pdf ~ exp(-s x) (Fig. 14d, 15), a least-squares fit of ln pdf weighted by the \
             bin counts over the bins with x >= tail_from holding at least tail_min_count \
             nodes (NaN with a note when fewer than 3 bins qualify). Nodes whose stress \
             tensor is exactly zero (void, excluded floating clusters) are skipped, and so \
             are the `margin` voxel layers along the image's faces (free sides).",
        )
        .inputs(vec![
            PortSpec::new(
                "stress",
                ArtifactKind::Field,
                "nodal stress field with named components (Voigt), e.g. \
                 peridynamics.bond_based's `stress`",
            ),
            PortSpec::new(
                "image",
                ArtifactKind::PhaseImage,
                "the phase image the stress lives on (same grid)",
            ),
        ])
        .outputs(vec![
            PortSpec::new(
                "stats",
                ArtifactKind::Table,
                "one row per phase: label, nodes, mean stress (Pa), mean, variance and excess \
                 kurtosis of x, tail exponent s with its r^2 and bins, nodes outside the \
                 range, note",
            ),
            PortSpec::new(
                "pdf",
                ArtifactKind::Table,
                "x (bin centre of sigma / mean), one column pdf_<phase> per phase, then one \
                 column fit_<phase> per phase (the tail fit exp(a - s x) for x >= tail_from, \
                 NaN elsewhere); export to .png for the plot with a log y axis (pdf-png)",
            ),
        ])
    }

    fn preflight(&self, p: &StressStatsParams, i: &InputMetas) -> Result<Preflight, StageError> {
        check(p)?;
        // A former default name (`void`) would exclude nothing and let the phase it meant
        // into the PDFs: refused with its new name when the image announces that phase.
        if let Some(phases) = i.get("image").and_then(|m| m.phases.as_deref()) {
            for e in &p.exclude {
                if phases.iter().any(|ph| &ph.name == e) {
                    continue;
                }
                if let Some(r) =
                    grainpipe_core::phases::renamed_in(e, phases.iter().map(|ph| ph.name.as_str()))
                {
                    return Err(StageError::param("exclude", r.message()));
                }
            }
        }
        let bytes = i
            .get("stress")
            .and_then(|m| m.grid.as_ref())
            // One f64 per node, gathered per phase into vectors grown by doubling: up to
            // 16 B per voxel; plus the tables.
            .map(|g| g.voxel_count() as u64 * 16)
            .unwrap_or(0)
            + (64 << 10);
        Ok(Preflight::from_info(&self.info(), bytes).announce(
            "pdf",
            ArtifactMeta::of(ArtifactKind::Table)
                .with_count(p.bins as u64, Some([p.bins as u64, p.bins as u64])),
        ))
    }

    fn run(
        &self,
        p: &StressStatsParams,
        _plan: &(),
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let stress = input(inputs, "stress", Artifact::as_field)?;
        let image = input(inputs, "image", Artifact::as_phase_image)?;
        let (stats, centres) = analyse(p, stress, image)?;
        let mut notes = Vec::new();
        for s in &stats {
            let note = if s.tail_exponent.is_none() {
                format!(
                    "{} bins with x >= {} and >= {} nodes: too few for a tail fit",
                    s.tail_bins, p.tail_from, p.tail_min_count
                )
            } else {
                String::new()
            };
            ctx.info(&format!(
                "{}: {} nodes, mean {:.4e} Pa, variance {:.4}, excess kurtosis {:.3}, tail s = \
                 {}",
                s.name,
                s.nodes,
                s.mean,
                s.variance,
                s.excess_kurtosis,
                s.tail_exponent
                    .map(|v| format!("{v:.3}"))
                    .unwrap_or_else(|| "-".into())
            ));
            notes.push(note);
        }
        let table = Table::new("stress_stats")
            .with_str("phase", stats.iter().map(|s| s.name.clone()).collect())
            .with_i64("label", "1", stats.iter().map(|s| s.label as i64).collect())
            .with_i64("nodes", "1", stats.iter().map(|s| s.nodes as i64).collect())
            .with_f64("mean_stress", "Pa", stats.iter().map(|s| s.mean).collect())
            .with_f64("mean_x", "1", stats.iter().map(|s| s.mean_x).collect())
            .with_f64("variance", "1", stats.iter().map(|s| s.variance).collect())
            .with_f64(
                "excess_kurtosis",
                "1",
                stats.iter().map(|s| s.excess_kurtosis).collect(),
            )
            .with_f64(
                "tail_exponent",
                "1",
                stats
                    .iter()
                    .map(|s| s.tail_exponent.unwrap_or(f64::NAN))
                    .collect(),
            )
            .with_f64("tail_r2", "1", stats.iter().map(|s| s.tail_r2).collect())
            .with_i64(
                "tail_bins",
                "1",
                stats.iter().map(|s| s.tail_bins as i64).collect(),
            )
            .with_i64(
                "outside",
                "1",
                stats.iter().map(|s| s.outside as i64).collect(),
            )
            .with_str("note", notes);
        let mut pdf = Table::new("stress_pdf").with_f64("x", "1", centres);
        for s in &stats {
            pdf = pdf.with_f64(&format!("pdf_{}", s.name), "1", s.pdf.clone());
        }
        for s in &stats {
            pdf = pdf.with_f64(&format!("fit_{}", s.name), "1", s.fit_pdf.clone());
        }
        let mut out = Outputs::new();
        out.insert("stats".into(), Artifact::Table(table));
        out.insert("pdf".into(), Artifact::Table(pdf));
        Ok(out)
    }
}
