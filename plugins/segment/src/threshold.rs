//! `segment.threshold`: grey values to phase labels, by thresholds given or found on the
//! histogram (Otsu 1979; three classes by exhaustive search, Liao et al. 2001). Kernels in
//! [`crate::otsu`].

use crate::common::{scalar_values, TABLES_BYTES};
use crate::otsu::{finite_range, histogram, multi_otsu3, otsu};
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, InputMetas, Inputs, Outputs, ParamChoice,
    Phase, PhaseImage, PortSpec, Preflight, RunContext, StageError, StageInfo, Table, TypedStage,
};
use rayon::prelude::*;

/// How the thresholds are chosen.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// The `thresholds` given.
    Manual,
    /// One threshold maximising the between-class variance of the histogram (Otsu 1979).
    Otsu,
    /// Two thresholds (three classes) maximising the between-class variance by exhaustive
    /// search (Liao et al. 2001); with `classes: 2` the same as `otsu`.
    MultiOtsu,
}

#[params]
pub struct ThresholdParams {
    /// `manual` (the `thresholds` given), `otsu` (two classes) or `multi_otsu` (two or three
    /// classes)
    #[param(default = Method::Otsu)]
    pub method: Method,
    /// number of classes: 2 for `otsu`, 2 or 3 for `multi_otsu`; for `manual` it is the
    /// number of thresholds + 1 (default: 2, or that number for `manual`)
    pub classes: Option<usize>,
    /// with `manual`: the thresholds, ascending, in the field's unit; a voxel of value v
    /// gets class k = the number of thresholds <= v
    pub thresholds: Vec<f64>,
    /// histogram bins between the smallest and largest finite value of the field (`otsu`,
    /// `multi_otsu`); a threshold found lies on a bin edge
    #[param(default = 256)]
    pub bins: usize,
    /// the label of each class, from the darkest (default 0, 1, 2, ...)
    pub labels: Vec<u8>,
    /// the phase name of each class, from the darkest (default `pore`, `grain` for two
    /// classes; `pore`, `binder`, `grain` for three: air, binder and quartz of a sand core's
    /// CT; `pore`, `phase1`, ... for more), the phase vocabulary of docs/ARCHITECTURE.md
    pub names: Vec<String>,
}

impl ThresholdParams {
    /// The number of classes, checked against the method.
    fn class_count(&self) -> Result<usize, StageError> {
        let n = match self.method {
            Method::Manual => {
                if self.thresholds.is_empty() {
                    return Err(StageError::param(
                        "thresholds",
                        "`method: manual` needs at least one threshold, e.g. `thresholds: \
                         [0.5]`, or use `method: otsu`",
                    ));
                }
                let n = self.thresholds.len() + 1;
                if let Some(c) = self.classes {
                    if c != n {
                        return Err(StageError::param(
                            "classes",
                            format!(
                                "{c} classes but {} thresholds give {n}; drop `classes` or give \
                                 {} thresholds",
                                self.thresholds.len(),
                                c.saturating_sub(1)
                            ),
                        ));
                    }
                }
                n
            }
            Method::Otsu => match self.classes.unwrap_or(2) {
                2 => 2,
                c => {
                    return Err(StageError::param(
                        "classes",
                        format!("`otsu` gives 2 classes, not {c}; use `method: multi_otsu` for 3"),
                    ))
                }
            },
            Method::MultiOtsu => match self.classes.unwrap_or(2) {
                c @ (2 | 3) => c,
                c => {
                    return Err(StageError::param(
                        "classes",
                        format!(
                            "`multi_otsu` searches 2 or 3 classes exhaustively, not {c}; use \
                             `method: manual` with {} thresholds",
                            c.saturating_sub(1)
                        ),
                    ))
                }
            },
        };
        if self.method != Method::Manual && !self.thresholds.is_empty() {
            return Err(StageError::param(
                "thresholds",
                "thresholds are found by the method; give them only with `method: manual`",
            ));
        }
        Ok(n)
    }

    /// Checks everything that needs no data; returns the labels and names of the classes.
    fn check(&self) -> Result<(usize, Vec<u8>, Vec<String>), StageError> {
        let n = self.class_count()?;
        if self.method == Method::Manual {
            let t = &self.thresholds;
            if let Some(bad) = t.iter().find(|x| !x.is_finite()) {
                return Err(StageError::param(
                    "thresholds",
                    format!("{bad} is not a finite number"),
                ));
            }
            if let Some(k) = (1..t.len()).find(|&k| t[k] <= t[k - 1]) {
                return Err(StageError::param(
                    "thresholds",
                    format!(
                        "{:?}: thresholds must be strictly ascending ({} follows {})",
                        t,
                        t[k],
                        t[k - 1]
                    ),
                ));
            }
        } else if !(2..=1 << 16).contains(&self.bins) {
            return Err(StageError::param(
                "bins",
                format!("{} bins: give 2 to 65536 (256 is usual)", self.bins),
            ));
        }
        let labels: Vec<u8> = if self.labels.is_empty() {
            (0..n as u8).collect()
        } else {
            self.labels.clone()
        };
        if labels.len() != n {
            return Err(StageError::param(
                "labels",
                format!(
                    "{} labels for {n} classes: give one label per class, darkest first",
                    labels.len()
                ),
            ));
        }
        if let Some(k) = (1..n).find(|&k| labels[..k].contains(&labels[k])) {
            return Err(StageError::param(
                "labels",
                format!(
                    "label {} is given to two classes; use `segment.clean` with `relabel` to \
                     merge phases afterwards",
                    labels[k]
                ),
            ));
        }
        let names: Vec<String> = if self.names.is_empty() {
            default_names(n)
        } else {
            self.names.clone()
        };
        if names.len() != n {
            return Err(StageError::param(
                "names",
                format!(
                    "{} names for {n} classes: give one name per class, darkest first",
                    names.len()
                ),
            ));
        }
        Ok((n, labels, names))
    }
}

/// The default phase names of `n` classes, darkest first: the brightest class of a granular
/// CT is the grain (quartz), a middle one the binder (less dense than quartz, denser than
/// air). Four or more classes (`manual`) the stage cannot tell apart: `pore`, then
/// `phase<k>`.
pub fn default_names(n: usize) -> Vec<String> {
    use grainpipe_core::phases::{unnamed, BINDER, GRAIN, PORE};
    (0..n)
        .map(|k| match (k, n) {
            (0, _) => PORE.to_string(),
            (1, 2) | (2, 3) => GRAIN.to_string(),
            (1, 3) => BINDER.to_string(),
            _ => unnamed(k as u8),
        })
        .collect()
}

/// What preflight settled: the labels and names of the classes.
pub struct ThresholdPlan {
    labels: Vec<u8>,
    names: Vec<String>,
}

pub struct Threshold;

impl TypedStage for Threshold {
    type Params = ThresholdParams;
    type Plan = ThresholdPlan;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "segment.threshold",
            "1.1.0",
            "Segments a scalar grey-value field into phases by thresholds, given or found \
             on its histogram (Otsu 1979; Liao, Chen & Chung 2001). A voxel of value v gets \
             class k = the number of thresholds <= v, labelled and named by \
             `labels` / `names`. `manual` takes the thresholds given; `otsu` (Otsu 1979) \
             picks the threshold maximising the between-class variance over a histogram of \
             `bins` equal bins between the field's smallest and largest finite value; \
             `multi_otsu` searches every pair of thresholds for \
             three classes. Automatic thresholds lie on bin edges; when several score the same \
             (an empty gap between modes) the lowest is taken, just above the darker \
             values. The thresholds used are \
             reported in the `classes` table (`lower`, `upper` of each class, in the \
             field's unit; the darkest class starts at the smallest value, the brightest \
             ends at the largest) and in the log. Values that are not finite (NaN) go to the \
             darkest class, with a warning.",
        )
        .inputs(vec![PortSpec::new(
            "field",
            ArtifactKind::Field,
            "scalar grey values (one component), e.g. from `import.* as: field`",
        )])
        .outputs(vec![
            PortSpec::new(
                "image",
                ArtifactKind::PhaseImage,
                "the class labels, named by `names` (default pore, grain; or pore, binder, grain)",
            ),
            PortSpec::new(
                "classes",
                ArtifactKind::Table,
                "one row per class: label, phase, value range (the thresholds), voxels, fraction",
            ),
        ])
    }

    fn preflight(
        &self,
        p: &ThresholdParams,
        i: &InputMetas,
    ) -> Result<Preflight<ThresholdPlan>, StageError> {
        let (n, labels, names) = p.check()?;
        let meta = i.get("field");
        let grid = meta.and_then(|m| m.grid.clone());
        let voxels = meta
            .map(|m| {
                grid.as_ref()
                    .map_or(m.count_estimate, |g| g.voxel_count() as u64)
            })
            .unwrap_or(0);
        // A copy of the values in f64 and the labels.
        let image = match grid {
            Some(g) => ArtifactMeta::on_grid(ArtifactKind::PhaseImage, g),
            None => ArtifactMeta::of(ArtifactKind::PhaseImage),
        }
        // The phase table is known now: downstream `materials` keys are checked against it.
        .with_phases(
            labels
                .iter()
                .zip(&names)
                .map(|(&id, name)| Phase {
                    id,
                    name: name.clone(),
                })
                .collect(),
        );
        let rows = n as u64;
        Ok(
            Preflight::from_info(&self.info(), 9 * voxels + TABLES_BYTES)
                .announce("image", image)
                .announce(
                    "classes",
                    ArtifactMeta::of(ArtifactKind::Table).with_count(rows, Some([rows, rows])),
                )
                .with_plan(ThresholdPlan { labels, names }),
        )
    }

    fn run(
        &self,
        p: &ThresholdParams,
        plan: &ThresholdPlan,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let f = input(inputs, "field", Artifact::as_field)?;
        let values = scalar_values(f, "field")?;
        let n = plan.labels.len();
        let range = finite_range(&values);
        let thresholds: Vec<f64> = match p.method {
            Method::Manual => p.thresholds.clone(),
            Method::Otsu | Method::MultiOtsu => {
                let (lo, hi) = range.ok_or_else(|| {
                    StageError::input("field", "the field holds no finite value to threshold")
                })?;
                if lo == hi {
                    return Err(StageError::input(
                        "field",
                        format!(
                            "every value is {lo} {}: there is nothing to separate; use \
                             `method: manual`",
                            f.unit
                        ),
                    ));
                }
                let h = histogram(&values, lo, hi, p.bins);
                let edge = |k: usize| lo + (k + 1) as f64 * (hi - lo) / p.bins as f64;
                match n {
                    2 => vec![edge(otsu(&h).expect("two bins and counts"))],
                    _ => multi_otsu3(&h)
                        .expect("three bins and counts")
                        .map(edge)
                        .to_vec(),
                }
            }
        };
        ctx.progress(1, 2)?;
        let nan = values.par_iter().filter(|v| v.is_nan()).count();
        if nan > 0 {
            ctx.warn(&format!(
                "{nan} voxels hold NaN; they went to the darkest class (label {})",
                plan.labels[0]
            ));
        }
        let lut = &plan.labels;
        let labels: Vec<u8> = values
            .par_iter()
            .map(|&v| lut[thresholds.iter().take_while(|&&t| v >= t).count()])
            .collect();
        let mut voxels = vec![0u64; n];
        let mut count = [0u64; 256];
        for &l in &labels {
            count[l as usize] += 1;
        }
        for (k, l) in lut.iter().enumerate() {
            voxels[k] = count[*l as usize];
        }
        let total = labels.len().max(1) as f64;
        // The darkest class starts at the smallest value, the brightest ends at the largest.
        let (lo, hi) = range.unwrap_or((f64::NAN, f64::NAN));
        let lower: Vec<f64> = (0..n)
            .map(|k| if k == 0 { lo } else { thresholds[k - 1] })
            .collect();
        let upper: Vec<f64> = (0..n)
            .map(|k| if k + 1 == n { hi } else { thresholds[k] })
            .collect();
        let method = match p.method {
            Method::Manual => "manual",
            Method::Otsu => "otsu",
            Method::MultiOtsu => "multi_otsu",
        };
        ctx.info(&format!(
            "segment.threshold ({method}): thresholds {thresholds:?} {}",
            f.unit
        ));
        let table = Table::new("classes")
            .with_i64("label", "", lut.iter().map(|&l| l as i64).collect())
            .with_str("phase", plan.names.clone())
            .with_f64("lower", &f.unit, lower)
            .with_f64("upper", &f.unit, upper)
            .with_i64("voxels", "", voxels.iter().map(|&v| v as i64).collect())
            .with_f64(
                "fraction",
                "1",
                voxels.iter().map(|&v| v as f64 / total).collect(),
            );
        let image = PhaseImage {
            grid: f.grid.clone(),
            labels,
            phases: lut
                .iter()
                .zip(&plan.names)
                .map(|(&id, name)| Phase {
                    id,
                    name: name.clone(),
                })
                .collect(),
        };
        ctx.progress(2, 2)?;
        let mut out = Outputs::new();
        out.insert("image".into(), Artifact::PhaseImage(image));
        out.insert("classes".into(), Artifact::Table(table));
        Ok(out)
    }
}
