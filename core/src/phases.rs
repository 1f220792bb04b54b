//! The phase vocabulary: the names the image-making stages give their phases by default, and
//! the former defaults that were renamed to it (docs/ARCHITECTURE.md, "Phase names").
//!
//! Phase-keyed parameters (`materials`, `conductivities`, `exclude`, the mesh exporters'
//! `phases`) name phases by these, so a pipeline written against one stage's image works on
//! another's. The rename table lives here, once, so every stage that checks such keys at
//! preflight says the same thing about an old name.

use crate::model::Phase;
use crate::stage::StageError;
use indexmap::IndexMap;

/// Label 0, in every image: the space between the solids.
pub const PORE: &str = "pore";
/// The granular solid: packed grains, sand, the solid of a segmented granular CT.
pub const GRAIN: &str = "grain";
/// The bonding phase of the binder stages (and the middle grey class of a sand core's CT).
pub const BINDER: &str = "binder";
/// The cemented sample's particle classes and matrix (Heinze 2020's classes; the
/// peridynamics roles and defaults refer to them).
pub const LARGE: &str = "large";
pub const SMALL: &str = "small";
pub const MATRIX: &str = "matrix";

/// A phase table of `pore` (label 0) and then `solids` under labels 1, 2, ...
pub fn pore_and(solids: &[&str]) -> Vec<Phase> {
    std::iter::once(PORE)
        .chain(solids.iter().copied())
        .enumerate()
        .map(|(id, name)| Phase {
            id: id as u8,
            name: name.to_string(),
        })
        .collect()
}

/// The name of a label whose material the stage cannot know, e.g. in an imported label
/// volume, where label k may be one grain each: `phase<k>` (label 0 is still `pore`).
pub fn unnamed(label: u8) -> String {
    if label == 0 {
        PORE.to_string()
    } else {
        format!("phase{label}")
    }
}

/// A former default phase name and the vocabulary name that replaced it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Renamed {
    /// The old name as users' pipelines may still write it.
    pub old: &'static str,
    /// Its name now.
    pub new: &'static str,
    /// Whose default it was, and for which phase.
    pub was: &'static str,
    /// How to keep the old name instead.
    pub keep: &'static str,
}

impl Renamed {
    /// "`sand` is the binder stages' former name for phase 1; it is now `grain` (or ...)".
    pub fn message(&self) -> String {
        format!(
            "`{}` is {}; it is now `{}` ({})",
            self.old, self.was, self.new, self.keep
        )
    }
}

/// Every default phase name that changed when the stages moved to one vocabulary.
pub const RENAMED: &[Renamed] = &[
    Renamed {
        old: "sand",
        new: GRAIN,
        was: "the binder stages' former name for phase 1",
        keep: "or set `sand_phase: sand` on the binder step",
    },
    Renamed {
        old: "void",
        new: PORE,
        was: "the cemented stages' former name for label 0",
        keep: "or key it by its label, `0`",
    },
    Renamed {
        old: "solid",
        new: GRAIN,
        was: "segment.threshold's former name for the brighter of two classes",
        keep: "or set `names: [pore, solid]` on the segment.threshold step",
    },
    Renamed {
        old: "phase1",
        new: BINDER,
        was: "segment.threshold's former name for the middle of three classes",
        keep: "or set `names: [pore, phase1, phase2]` on the segment.threshold step",
    },
    Renamed {
        old: "phase2",
        new: GRAIN,
        was: "segment.threshold's former name for the brightest of three classes",
        keep: "or set `names: [pore, phase1, phase2]` on the segment.threshold step",
    },
];

/// The rename of `name` when it is a former default whose new name is one of `phases`
/// (only then: `phase1` is still the name of label 1 in an imported volume).
pub fn renamed_in<'a>(name: &str, phases: impl IntoIterator<Item = &'a str>) -> Option<Renamed> {
    let r = RENAMED.iter().find(|r| r.old == name)?;
    phases.into_iter().any(|p| p == r.new).then_some(*r)
}

/// Whether map key `k` names `phase`: by name or by label.
fn names(k: &str, phase: &Phase) -> bool {
    k == phase.name || k == phase.id.to_string()
}

/// Checks a phase-keyed map (`materials`, `conductivities`) at preflight: no empty key, and,
/// when the upstream stage announces its phase table, an entry for every phase but label 0
/// (which defaults to pore). A key that names no phase gets a did-you-mean, and a former
/// default name ([`RENAMED`]) is said to be one with its new name, also for label 0: a
/// `void` entry would otherwise be left out silently and the pore take the default.
pub fn check_keys<V>(
    key: &str,
    map: &IndexMap<String, V>,
    phases: Option<&[Phase]>,
) -> Result<(), StageError> {
    for k in map.keys() {
        if k.trim().is_empty() {
            return Err(StageError::param(key, "empty phase name"));
        }
    }
    let Some(phases) = phases else {
        return Ok(());
    };
    let listing = || {
        phases
            .iter()
            .map(|p| format!("`{}`", p.name))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let unmatched: Vec<&str> = map
        .keys()
        .filter(|k| !phases.iter().any(|p| names(k, p)))
        .map(String::as_str)
        .collect();
    for k in &unmatched {
        let Some(r) = renamed_in(k, phases.iter().map(|p| p.name.as_str())) else {
            continue;
        };
        let new_has_entry = phases
            .iter()
            .filter(|p| p.name == r.new)
            .any(|p| map.keys().any(|k| names(k, p)));
        if !new_has_entry {
            return Err(StageError::param(
                &format!("{key}.{k}"),
                format!("{}; the image's phases: {}", r.message(), listing()),
            ));
        }
    }
    for phase in phases.iter().filter(|p| p.id != 0) {
        if map.keys().any(|k| names(k, phase)) {
            continue;
        }
        let hint = match crate::suggest::closest(&phase.name, unmatched.iter().copied()) {
            Some(k) => format!("; did you mean `{}` for `{k}`?", phase.name),
            None => String::new(),
        };
        return Err(StageError::param(
            key,
            format!(
                "the image will have phase `{}` (label {}) and `{key}` has no entry for it \
                 (keys given: {}; the image's phases: {}){hint}",
                phase.name,
                phase.id,
                map.keys()
                    .map(|k| format!("`{k}`"))
                    .collect::<Vec<_>>()
                    .join(", "),
                listing(),
            ),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table(names: &[&str]) -> Vec<Phase> {
        names
            .iter()
            .enumerate()
            .map(|(id, n)| Phase {
                id: id as u8,
                name: n.to_string(),
            })
            .collect()
    }

    fn map(keys: &[&str]) -> IndexMap<String, f64> {
        keys.iter().map(|k| (k.to_string(), 1.0)).collect()
    }

    fn message(e: StageError) -> (String, String) {
        match e {
            StageError::InvalidParam { key, message } => (key, message),
            other => panic!("not a parameter error: {other}"),
        }
    }

    #[test]
    fn a_former_default_is_named_with_its_new_name() {
        let phases = table(&["pore", "grain", "binder"]);
        let e = check_keys("materials", &map(&["sand", "binder"]), Some(&phases)).unwrap_err();
        let (key, m) = message(e);
        assert_eq!(key, "materials.sand");
        assert!(
            m.starts_with(
                "`sand` is the binder stages' former name for phase 1; it is now `grain` \
                 (or set `sand_phase: sand` on the binder step)"
            ),
            "{m}"
        );
    }

    #[test]
    fn void_for_label_0_is_refused_though_label_0_may_be_left_out() {
        let phases = table(&["pore", "large", "small", "matrix"]);
        let e = check_keys(
            "conductivities",
            &map(&["void", "large", "small", "matrix"]),
            Some(&phases),
        )
        .unwrap_err();
        let (key, m) = message(e);
        assert_eq!(key, "conductivities.void");
        assert!(m.contains("it is now `pore`"), "{m}");
        // Without the old key label 0 still defaults.
        check_keys("c", &map(&["large", "small", "matrix"]), Some(&phases)).unwrap();
    }

    #[test]
    fn an_old_name_that_is_a_phase_of_the_image_is_no_rename() {
        // `sand_phase: sand` kept the old name: `sand` is a phase, nothing to say.
        let phases = table(&["pore", "sand", "binder"]);
        check_keys("materials", &map(&["sand", "binder"]), Some(&phases)).unwrap();
        // An imported volume still has `phase1`.
        let phases = table(&["pore", "phase1"]);
        check_keys("materials", &map(&["phase1"]), Some(&phases)).unwrap();
        // A stale old key beside the new one is no error (the run warns that it is unused).
        let phases = table(&["pore", "grain", "binder"]);
        check_keys("m", &map(&["sand", "grain", "binder"]), Some(&phases)).unwrap();
    }

    #[test]
    fn every_rename_points_into_the_vocabulary() {
        let vocabulary = [PORE, GRAIN, BINDER, LARGE, SMALL, MATRIX];
        for r in RENAMED {
            assert!(vocabulary.contains(&r.new), "{r:?}");
            assert!(!vocabulary.contains(&r.old), "{r:?}");
            assert_eq!(RENAMED.iter().filter(|q| q.old == r.old).count(), 1);
        }
        assert_eq!(unnamed(0), PORE);
        assert_eq!(unnamed(3), "phase3");
    }

    #[test]
    fn a_misspelt_key_still_gets_a_did_you_mean() {
        let phases = table(&["pore", "grain", "binder"]);
        let (key, m) =
            message(check_keys("materials", &map(&["grain", "bindr"]), Some(&phases)).unwrap_err());
        assert_eq!(key, "materials");
        assert!(m.contains("did you mean `binder` for `bindr`?"), "{m}");
    }
}
