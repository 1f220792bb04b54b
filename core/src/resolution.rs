//! `voxel_size: auto`: the parameter type and the settings an image maker shares when it lets
//! the runner choose its resolution. The core only declares them; the choice itself (a
//! resolution study of cheap levels, Richardson extrapolation, the coarsest level meeting the
//! target) is made by the runner before planning (crate grainpipe-sweep, `auto` module), so
//! a stage never sees `auto`.
//!
//! The contract a stage signs by flattening [`AutoVoxel`] into its parameters: it has a
//! `voxel_size` of type [`VoxelSize`] and a `voxels_per_diameter` that sets the voxel when
//! `voxel_size` is 0 (the runner's levels are voxels per mean grain diameter, so they mean the
//! same thing whatever the grain size).

use crate::params::ParamType;
use crate::units::{Length, Q};
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use serde_json::{json, Value};

/// A voxel edge, or `auto` (chosen by the runner for a target error).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum VoxelSize {
    /// `auto`: resolved by the runner before the stage is planned.
    Auto,
    /// A length (0 = use voxels_per_diameter).
    Size(Q<Length>),
}

impl Default for VoxelSize {
    fn default() -> Self {
        VoxelSize::Size(Q::new(0.0))
    }
}

impl VoxelSize {
    /// The edge in metres; NaN for `auto` (which every check refuses as not a length).
    pub fn si(&self) -> f64 {
        match self {
            VoxelSize::Auto => f64::NAN,
            VoxelSize::Size(q) => q.si(),
        }
    }
    pub fn is_auto(&self) -> bool {
        matches!(self, VoxelSize::Auto)
    }
}

impl Serialize for VoxelSize {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            VoxelSize::Auto => s.serialize_str(AUTO),
            VoxelSize::Size(q) => q.serialize(s),
        }
    }
}

impl<'de> Deserialize<'de> for VoxelSize {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let v = Value::deserialize(d)?;
        if v.as_str().map(str::trim) == Some(AUTO) {
            return Ok(VoxelSize::Auto);
        }
        serde_json::from_value::<Q<Length>>(v)
            .map(VoxelSize::Size)
            .map_err(|e| serde::de::Error::custom(format!("{e}, or `auto`")))
    }
}

impl ParamType for VoxelSize {
    fn type_name() -> String {
        "length, or auto".into()
    }
    fn unit() -> &'static str {
        "m"
    }
    fn schema() -> Value {
        json!({"anyOf": [Q::<Length>::schema(), {"const": AUTO}]})
    }
}

/// The word that asks for an automatic voxel size.
pub const AUTO: &str = "auto";

/// The parameter whose value may be `auto`, and the one the runner's levels set.
pub const SIZE_KEY: &str = "voxel_size";
pub const LEVEL_KEY: &str = "voxels_per_diameter";

/// The settings of `voxel_size: auto` (ignored otherwise), shared by the image makers.
#[crate::params]
pub struct AutoVoxel {
    /// With voxel_size: auto, the largest relative error (Richardson estimate) allowed on
    /// every auto_quantities value: the run uses the coarsest voxel predicted to meet it.
    #[param(default = 0.03)]
    pub target_error: f64,
    /// With voxel_size: auto, the values whose error is controlled, named as `pipe study
    /// --metric` names them: step.port.column for a table (e.g. stiffness.constants.E_x),
    /// step.port.index or step.port.<component> for a tensor (e.g. flow.permeability.8 or
    /// flow.permeability.kappa_zz).
    #[param(default = Vec::new())]
    pub auto_quantities: Vec<String>,
    /// With voxel_size: auto, the cheap levels run first, in voxels per mean grain diameter,
    /// coarse to fine (three or more give the observed order of convergence; two use
    /// auto_order).
    #[param(default = vec![6.0, 12.0, 24.0])]
    pub auto_levels: Vec<f64>,
    /// With voxel_size: auto, the formal order of convergence (1 for voxelized interfaces):
    /// assumed with two auto_levels; with three or more an observed order above it is
    /// capped to it (pre-asymptotic coarse levels would underestimate the error).
    #[param(default = 1.0)]
    pub auto_order: f64,
}

impl AutoVoxel {
    /// Checks the settings when `voxel_size` is `auto` (they are not read otherwise, so
    /// they are not refused otherwise either). `(key, message)` on error.
    pub fn check(&self, voxel_size: &VoxelSize) -> Result<(), (String, String)> {
        if !voxel_size.is_auto() {
            return Ok(());
        }
        let t = self.target_error;
        if !(t > 0.0 && t < 1.0) {
            return Err((
                "target_error".into(),
                format!("must be a relative error above 0 and below 1 (0.03 is 3 %), got {t}"),
            ));
        }
        if self.auto_quantities.is_empty() {
            return Err((
                "auto_quantities".into(),
                "voxel_size: auto needs the values whose error it controls, e.g. \
                 [stiffness.constants.E_x]"
                    .into(),
            ));
        }
        for q in &self.auto_quantities {
            if q.split('.').filter(|s| !s.is_empty()).count() != 3 {
                return Err((
                    "auto_quantities".into(),
                    format!("`{q}` is not of the form step.port.column (or step.port.index)"),
                ));
            }
        }
        let l = &self.auto_levels;
        if l.len() < 2
            || l.iter().any(|x| !(x.is_finite() && *x >= 2.0))
            || l.windows(2).any(|w| w[1] <= w[0])
        {
            return Err((
                "auto_levels".into(),
                format!(
                    "must be two or more increasing voxel counts per diameter, each at least 2 \
                     (e.g. [6, 12, 24]), got {l:?}"
                ),
            ));
        }
        let p = self.auto_order;
        if !(0.25..=8.0).contains(&p) {
            return Err((
                "auto_order".into(),
                format!("must be between 0.25 and 8, got {p}"),
            ));
        }
        Ok(())
    }
}

/// The message of a stage that received `auto` unresolved (an entry point that runs the
/// pipeline as given, e.g. a sweep child): the stage cannot choose its own resolution.
pub const UNRESOLVED: &str = "`auto` is chosen by `pipe run` / `pipe validate` before the \
     pipeline runs (a study of cheap levels); it reached the stage unresolved here: give a \
     length, or a voxels_per_diameter with voxel_size 0 (pipe sweep and pipe study vary it \
     themselves)";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_or_a_length() {
        let a: VoxelSize = serde_json::from_value(json!("auto")).unwrap();
        assert!(a.is_auto() && a.si().is_nan());
        let s: VoxelSize = serde_json::from_value(json!("4 um")).unwrap();
        assert!((s.si() - 4e-6).abs() < 1e-18);
        assert_eq!(serde_json::to_value(a).unwrap(), json!("auto"));
        let e = serde_json::from_value::<VoxelSize>(json!("fine")).unwrap_err();
        assert!(e.to_string().contains("or `auto`"), "{e}");
    }

    #[test]
    fn settings_are_checked_only_for_auto() {
        let mut a = AutoVoxel {
            target_error: f64::NAN,
            ..Default::default()
        };
        assert!(a.check(&VoxelSize::default()).is_ok());
        for t in [f64::NAN, 0.0, -0.1, 1.0] {
            a.target_error = t;
            assert_eq!(a.check(&VoxelSize::Auto).unwrap_err().0, "target_error");
        }
        a.target_error = 0.03;
        assert_eq!(a.check(&VoxelSize::Auto).unwrap_err().0, "auto_quantities");
        a.auto_quantities = vec!["stiffness.E_x".into()];
        assert_eq!(a.check(&VoxelSize::Auto).unwrap_err().0, "auto_quantities");
        a.auto_quantities = vec!["stiffness.constants.E_x".into()];
        assert!(a.check(&VoxelSize::Auto).is_ok());
        a.auto_levels = vec![12.0, 6.0];
        assert_eq!(a.check(&VoxelSize::Auto).unwrap_err().0, "auto_levels");
    }
}
