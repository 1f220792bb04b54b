//! `segment.clean`: removes specks, fills holes and relabels a phase image (kernels in
//! [`crate::morph`]).

use crate::common::{VoxelsOr, TABLES_BYTES};
use crate::morph::{fill_holes, relabel, remove_specks, Reassigned};
use grainpipe_core::units::Volume;
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, InputMetas, Inputs, Outputs, Phase,
    PhaseImage, PortSpec, Preflight, RunContext, StageError, StageInfo, Table, TypedStage,
};

#[params]
pub struct CleanParams {
    /// components smaller than this are specks and join the surrounding phase: a number of
    /// voxels, or a volume with a unit (`"1000 um^3"`); 0 keeps every component
    #[param(default = VoxelsOr::Voxels(0.0))]
    pub min_size: VoxelsOr<Volume>,
    /// the labels whose specks are removed (default: every label)
    pub speck_labels: Vec<u8>,
    /// the labels whose holes are filled: components that touch no face of a non-periodic
    /// axis and do not wind around a periodic one take the enclosing phase (default: none)
    pub fill_holes: Vec<u8>,
    /// label changes applied last, as [old, new] pairs, e.g. [[2, 1]] merges phase 2 into 1
    #[param(ty = "list of [old, new] label pairs")]
    pub relabel: Vec<[u8; 2]>,
}

/// What preflight settled: the label map of `relabel`.
pub struct CleanPlan {
    map: [u8; 256],
}

pub struct Clean;

impl TypedStage for Clean {
    type Params = CleanParams;
    type Plan = CleanPlan;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "segment.clean",
            "1.0.0",
            "Removes specks, fills holes and relabels a segmented image, in that order, \
             each step on the result of the one before. Specks: connected components \
             (6-connectivity, periodic axes wrap) of the `speck_labels` smaller than \
             `min_size` take the label most of their face neighbours carry (ties to the \
             smallest label). Holes: components of the `fill_holes` labels that are enclosed \
             (touch neither face of a non-periodic axis, do not wind around a periodic one; \
             axes of one voxel are ignored) take the majority label of their face \
             neighbours, i.e. the enclosing phase. Then `relabel` applies its [old, new] \
             pairs. The speck and hole steps judge every component on their input, so the \
             result does not depend on the order of the components; a component without \
             neighbours of another label keeps its label. The `summary` table counts the \
             components and voxels changed.",
        )
        .inputs(vec![PortSpec::new(
            "image",
            ArtifactKind::PhaseImage,
            "a segmented image, e.g. from `segment.threshold`",
        )])
        .outputs(vec![
            PortSpec::new("image", ArtifactKind::PhaseImage, "the cleaned image"),
            PortSpec::new(
                "summary",
                ArtifactKind::Table,
                "one row per step (specks, holes): components and voxels reassigned",
            ),
        ])
    }

    fn preflight(
        &self,
        p: &CleanParams,
        i: &InputMetas,
    ) -> Result<Preflight<CleanPlan>, StageError> {
        if !p.min_size.is_finite_non_negative() {
            return Err(StageError::param(
                "min_size",
                "give a non-negative number of voxels (e.g. 10) or a volume (\"1000 um^3\")",
            ));
        }
        let mut map: [u8; 256] = std::array::from_fn(|l| l as u8);
        for (k, [old, new]) in p.relabel.iter().enumerate() {
            if p.relabel[..k].iter().any(|[o, _]| o == old) {
                return Err(StageError::param(
                    "relabel",
                    format!("label {old} is mapped twice; give one [old, new] pair per label"),
                ));
            }
            map[*old as usize] = *new;
        }
        let grid = i.get("image").and_then(|m| m.grid.clone());
        let voxels = i
            .get("image")
            .map(|m| {
                grid.as_ref()
                    .map_or(m.count_estimate, |g| g.voxel_count() as u64)
            })
            .unwrap_or(0);
        // Two label copies and the component ids.
        let mut meta = match grid {
            Some(g) => ArtifactMeta::on_grid(ArtifactKind::PhaseImage, g),
            None => ArtifactMeta::of(ArtifactKind::PhaseImage),
        };
        // The input's phase table after `relabel`, so downstream keys are still checked.
        meta.phases = i
            .get("image")
            .and_then(|m| m.phases.as_deref())
            .map(|ph| phase_table(ph, &map));
        Ok(
            Preflight::from_info(&self.info(), 6 * voxels + TABLES_BYTES)
                .announce("image", meta)
                .announce(
                    "summary",
                    ArtifactMeta::of(ArtifactKind::Table).with_count(2, Some([2, 2])),
                )
                .with_plan(CleanPlan { map }),
        )
    }

    fn run(
        &self,
        p: &CleanParams,
        plan: &CleanPlan,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let im = input(inputs, "image", Artifact::as_phase_image)?;
        let g = &im.grid;
        let voxel_volume = g.spacing.iter().product::<f64>();
        // A component of v voxels is a speck when v < min_size (in voxels).
        let min = p.min_size.in_voxels(voxel_volume);
        let min_voxels = min.ceil().min(u64::MAX as f64) as u64;
        let mut labels = im.labels.clone();
        let mut specks = Reassigned::default();
        if min_voxels > 1 {
            let (l, r) = remove_specks(&labels, g.dims, g.periodic, min_voxels, |l| {
                p.speck_labels.is_empty() || p.speck_labels.contains(&l)
            });
            labels = l;
            specks = r;
        }
        ctx.progress(1, 3)?;
        let mut holes = Reassigned::default();
        if !p.fill_holes.is_empty() {
            let (l, r) = fill_holes(&labels, g.dims, g.periodic, |l| p.fill_holes.contains(&l));
            labels = l;
            holes = r;
        }
        ctx.progress(2, 3)?;
        relabel(&mut labels, &plan.map);
        ctx.info(&format!(
            "segment.clean: {} specks ({} voxels) and {} holes ({} voxels) reassigned",
            specks.components, specks.voxels, holes.components, holes.voxels
        ));
        let image = PhaseImage {
            grid: g.clone(),
            labels,
            phases: phase_table(&im.phases, &plan.map),
        };
        let summary = Table::new("summary")
            .with_str("step", vec!["specks".into(), "holes".into()])
            .with_i64(
                "components",
                "",
                vec![specks.components as i64, holes.components as i64],
            )
            .with_i64(
                "voxels",
                "",
                vec![specks.voxels as i64, holes.voxels as i64],
            );
        ctx.progress(3, 3)?;
        let mut out = Outputs::new();
        out.insert("image".into(), Artifact::PhaseImage(image));
        out.insert("summary".into(), Artifact::Table(summary));
        Ok(out)
    }
}

/// The phase table after `map`: each label that remains a target keeps its name; a new
/// label takes the name of the first label mapped to it. Sorted by label.
pub fn phase_table(phases: &[Phase], map: &[u8; 256]) -> Vec<Phase> {
    let mut out: Vec<Phase> = Vec::new();
    // Names of labels that map to themselves first, so they win over renamed ones.
    let fixed = phases.iter().filter(|ph| map[ph.id as usize] == ph.id);
    let moved = phases.iter().filter(|ph| map[ph.id as usize] != ph.id);
    for ph in fixed.chain(moved) {
        let id = map[ph.id as usize];
        if !out.iter().any(|q| q.id == id) {
            out.push(Phase {
                id,
                name: ph.name.clone(),
            });
        }
    }
    out.sort_by_key(|ph| ph.id);
    out
}
