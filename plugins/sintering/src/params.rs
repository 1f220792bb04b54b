//! Parameters of `sintering.laser`, defaulting to the paper's section 5.1 values in SI.

use grainpipe_core::units::{
    Conductance, Density, Length, Power, SpecificEnergy, SpecificHeat, Temperature, Time, Velocity,
    Q,
};
use grainpipe_core::{params, ParamChoice};
use serde::{Deserialize, Serialize};

/// Where the laser goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum PathKind {
    /// Serpentine (or unidirectional) raster of a rectangle, see the `raster_*` keys.
    Raster,
    /// A polyline read from `path_csv`.
    Csv,
}

/// Which particles are candidates for absorbing laser power.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum TopSurface {
    /// `face` when the contact graph lists bodies on the zmax face, else `depth`.
    Auto,
    /// The bodies of the contact graph's zmax face list (the paper's ListZmax).
    Face,
    /// Bodies whose top (z + r) is within `surface_depth` of the highest top in the bed.
    Depth,
    /// Every body (combine with `shadowing: true` for a pure line-of-sight rule).
    All,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum BeamProfile {
    /// Uniform disc of radius r_L: q_i = Q r_i^2 / r_L^2 (the paper's model).
    TopHat,
    /// Gaussian with 1/e^2 radius r_L and the same total power.
    Gaussian,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Integrator {
    /// Forward Euler, the paper's update T += dt q / (m C_p).
    Explicit,
    /// Backward Euler solved by preconditioned conjugate gradients.
    Implicit,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum ScanAxis {
    /// Scan lines along x.
    X,
    /// Scan lines along y.
    Y,
}

#[params]
pub struct LaserParams {
    /// total laser power Q (paper: 100 W)
    #[param(default = Q::new(100.0))]
    pub power: Q<Power>,
    /// fraction of the beam power the particles absorb (paper: 1, all of Q; 316L powder beds under a 1 um fibre laser absorb about 0.3-0.7)
    // Default 1 keeps the paper's model literal; shipped pipelines state a physical value.
    #[param(default = 1.0, ty = "number in [0, 1]")]
    pub absorptivity: f64,
    /// laser beam radius r_L (paper: 50 um)
    #[param(default = Q::new(50e-6))]
    pub beam_radius: Q<Length>,
    /// top_hat: q_i = Q r_i^2/r_L^2 within r_L of the spot (paper); gaussian: q_i = 2 Q r_i^2/r_L^2 exp(-2 d^2/r_L^2), d < 2 r_L
    #[param(default = BeamProfile::TopHat)]
    pub beam_profile: BeamProfile,
    /// C_p (paper: 0.5 J/(g K) = 500 J/(kg K))
    #[param(default = Q::new(500.0))]
    pub specific_heat: Q<SpecificHeat>,
    /// particle density rho, m_i = 4/3 pi rho r_i^3 (paper: 8e-12 g/um^3 = 8000 kg/m^3)
    #[param(default = Q::new(8000.0))]
    pub density: Q<Density>,
    /// k_b, per-particle heat loss k_b (T_R - T_i) (paper: 2.9090e-5 W/K)
    #[param(default = Q::new(2.9090e-5))]
    pub convection_conductance: Q<Conductance>,
    /// k_t, conduction k_t (T_j - T_i) across each contact (paper: 3.3309e-4 W/K)
    #[param(default = Q::new(3.3309e-4))]
    pub contact_conductance: Q<Conductance>,
    /// conductance of a bonded (sintered) pair; default k_t as in the paper
    // The paper does not change conduction on bonding.
    #[param(default = Q::new(3.3309e-4))]
    pub bonded_conductance: Q<Conductance>,
    /// T_R, surrounding air temperature (paper: 300 K)
    #[param(default = Q::new(300.0))]
    pub ambient_temperature: Q<Temperature>,
    /// initial temperature of every particle; null = the packing's `temperature` attribute when present (continue a previous run), else ambient_temperature
    pub initial_temperature: Option<Q<Temperature>>,
    /// T_S: a contact bonds when both particles exceed it (paper: 1000 K)
    #[param(default = Q::new(1000.0))]
    pub sintering_temperature: Q<Temperature>,
    /// laser path: raster of a rectangle or polyline from path_csv
    // Section 5.2 "small square in the middle": five scan lines 2 r_L apart, 500 um long.
    #[param(default = PathKind::Raster)]
    pub path: PathKind,
    /// centre of the rastered rectangle; null = middle of the packing domain
    pub raster_center: Option<[Q<Length>; 2]>,
    /// length of each scan line
    #[param(default = Q::new(500e-6))]
    pub raster_length: Q<Length>,
    /// distance between neighbouring scan lines
    #[param(default = Q::new(100e-6))]
    pub hatch_spacing: Q<Length>,
    /// number of scan lines (the paper's five passes); the rectangle is raster_length x passes*hatch_spacing; 0 = no laser (cooldown only)
    #[param(default = 5)]
    pub passes: u32,
    /// true: serpentine, every other line reversed; false: all lines in the same direction
    #[param(default = true)]
    pub alternate: bool,
    /// direction of the scan lines
    #[param(default = ScanAxis::X)]
    pub scan_axis: ScanAxis,
    /// laser travel speed along the path (the beam jumps between lines with the laser off in zero time)
    // Not given in the paper; a typical powder-bed-fusion scan speed.
    #[param(default = Q::new(1.0))]
    pub scan_speed: Q<Velocity>,
    /// CSV polyline for path: csv; columns x,y[,on]; on=0 travels to the vertex with the laser off
    #[param(file, ty = "file path")]
    pub path_csv: String,
    /// length unit of the CSV coordinates (e.g. 1 um)
    #[param(default = Q::new(1.0))]
    pub path_csv_unit: Q<Length>,
    /// simulated time after the path ends
    #[param(default = Q::new(1e-3))]
    pub cooldown: Q<Time>,
    /// candidate absorbers: auto = zmax face list if present else depth; face = contact graph zmax list; depth = top within surface_depth of the highest top; all = every particle
    #[param(default = TopSurface::Auto)]
    pub top_surface: TopSurface,
    /// depth of the absorbing top layer for top_surface: depth
    #[param(default = Q::new(30e-6))]
    pub surface_depth: Q<Length>,
    /// only candidates whose centre is not covered from above by a higher particle absorb
    pub shadowing: bool,
    /// latent heat of melting: temperature holds at melting_temperature until latent_heat m_i is absorbed (explicit integrator only)
    pub melting: bool,
    /// melting temperature for melting: true
    // 316L stainless steel: liquidus about 1700 K, latent heat about 2.7e5 J/kg.
    #[param(default = Q::new(1700.0))]
    pub melting_temperature: Q<Temperature>,
    /// temperature above which the model leaves its range of validity (no evaporation, recoil or melt flow): a peak above it is reported as a warning (316L boils near 3090 K)
    #[param(default = Q::new(3090.0))]
    pub boiling_temperature: Q<Temperature>,
    /// true: a peak above boiling_temperature fails the step instead of warning
    pub refuse_invalid: bool,
    /// latent heat of melting for melting: true
    #[param(default = Q::new(2.7e5))]
    pub latent_heat: Q<SpecificEnergy>,
    /// explicit forward Euler (paper) or implicit backward Euler
    #[param(default = Integrator::Explicit)]
    pub integrator: Integrator,
    /// time step; null = dt_safety x stability limit (explicit) or r_L/(5 scan_speed) (implicit)
    pub dt: Option<Q<Time>>,
    /// explicit: split a dt above the stability limit into stable sub-steps (or sub-cycle only the particles that need it, see multirate); false = refuse it
    #[param(default = true)]
    pub substep: bool,
    /// explicit with substep: true: particles whose own limit m_i C_p/(sum_j k_ij + k_b) is below the global step are sub-cycled at their own stable step inside it (energy-conserving flux accumulation); the global step is chosen to minimise the work. false = one global step at the smallest limit
    #[param(default = true)]
    pub multirate: bool,
    /// fraction of the explicit stability limit used for automatic (sub-)steps
    #[param(default = 0.9, ty = "number in (0, 1]")]
    pub dt_safety: f64,
    /// implicit: relative residual at which conjugate gradients stop
    #[param(default = 1e-12)]
    pub cg_tolerance: f64,
    /// interval between temperature snapshots (0 = initial and final only)
    #[param(default = Q::new(250e-6))]
    pub snapshot_interval: Q<Time>,
    /// interval between history rows (0 = every step)
    #[param(default = Q::new(10e-6))]
    pub history_interval: Q<Time>,
    /// limit on (sub-)steps; the run fails with the time reached beyond it
    #[param(default = 20_000_000)]
    pub max_steps: u64,
}
