//! Parameters of `sintering.laser`, defaulting to the paper's section 5.1 values in SI.

use grainpipe_core::units::{
    Conductance, Density, Length, Power, SpecificEnergy, SpecificHeat, Temperature, Time, Velocity,
    Q,
};
use grainpipe_core::ParamSpec;
use serde::{Deserialize, Serialize};

/// Where the laser goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PathKind {
    /// Serpentine (or unidirectional) raster of a rectangle, see the `raster_*` keys.
    Raster,
    /// A polyline read from `path_csv`.
    Csv,
}

/// Which particles are candidates for absorbing laser power.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
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

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BeamProfile {
    /// Uniform disc of radius r_L: q_i = Q r_i^2 / r_L^2 (the paper's model).
    TopHat,
    /// Gaussian with 1/e^2 radius r_L and the same total power.
    Gaussian,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Integrator {
    /// Forward Euler, the paper's update T += dt q / (m C_p).
    Explicit,
    /// Backward Euler solved by preconditioned conjugate gradients.
    Implicit,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScanAxis {
    X,
    Y,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LaserParams {
    pub power: Q<Power>,
    pub beam_radius: Q<Length>,
    pub beam_profile: BeamProfile,
    pub specific_heat: Q<SpecificHeat>,
    pub density: Q<Density>,
    pub convection_conductance: Q<Conductance>,
    pub contact_conductance: Q<Conductance>,
    pub bonded_conductance: Q<Conductance>,
    pub ambient_temperature: Q<Temperature>,
    pub initial_temperature: Option<Q<Temperature>>,
    pub sintering_temperature: Q<Temperature>,
    pub path: PathKind,
    pub raster_center: Option<[Q<Length>; 2]>,
    pub raster_length: Q<Length>,
    pub hatch_spacing: Q<Length>,
    pub passes: u32,
    pub alternate: bool,
    pub scan_axis: ScanAxis,
    pub scan_speed: Q<Velocity>,
    pub path_csv: String,
    pub path_csv_unit: Q<Length>,
    pub cooldown: Q<Time>,
    pub top_surface: TopSurface,
    pub surface_depth: Q<Length>,
    pub shadowing: bool,
    pub melting: bool,
    pub melting_temperature: Q<Temperature>,
    pub latent_heat: Q<SpecificEnergy>,
    pub integrator: Integrator,
    pub dt: Option<Q<Time>>,
    pub substep: bool,
    pub multirate: bool,
    pub dt_safety: f64,
    pub cg_tolerance: f64,
    pub snapshot_interval: Q<Time>,
    pub history_interval: Q<Time>,
    pub max_steps: u64,
}

impl Default for LaserParams {
    fn default() -> Self {
        LaserParams {
            // Section 5.1 values.
            power: Q::new(100.0),
            beam_radius: Q::new(50e-6),
            beam_profile: BeamProfile::TopHat,
            specific_heat: Q::new(500.0),
            density: Q::new(8000.0),
            convection_conductance: Q::new(2.9090e-5),
            contact_conductance: Q::new(3.3309e-4),
            // The paper does not change conduction on bonding.
            bonded_conductance: Q::new(3.3309e-4),
            ambient_temperature: Q::new(300.0),
            initial_temperature: None,
            sintering_temperature: Q::new(1000.0),
            // Section 5.2 "small square in the middle": five scan lines 2 r_L apart, 500 um long.
            path: PathKind::Raster,
            raster_center: None,
            raster_length: Q::new(500e-6),
            hatch_spacing: Q::new(100e-6),
            passes: 5,
            alternate: true,
            scan_axis: ScanAxis::X,
            // Not given in the paper; a typical powder-bed-fusion scan speed.
            scan_speed: Q::new(1.0),
            path_csv: String::new(),
            path_csv_unit: Q::new(1.0),
            cooldown: Q::new(1e-3),
            top_surface: TopSurface::Auto,
            surface_depth: Q::new(30e-6),
            shadowing: false,
            melting: false,
            // 316L stainless steel: liquidus about 1700 K, latent heat about 2.7e5 J/kg.
            melting_temperature: Q::new(1700.0),
            latent_heat: Q::new(2.7e5),
            integrator: Integrator::Explicit,
            dt: None,
            substep: true,
            multirate: true,
            dt_safety: 0.9,
            cg_tolerance: 1e-12,
            snapshot_interval: Q::new(250e-6),
            history_interval: Q::new(10e-6),
            max_steps: 20_000_000,
        }
    }
}

pub fn param_specs() -> Vec<ParamSpec> {
    let p = |name, ty, unit, doc| ParamSpec {
        name,
        ty,
        unit,
        doc,
    };
    vec![
        p("power", "power", "W", "total laser power Q (paper: 100 W)"),
        p("beam_radius", "length", "m", "laser beam radius r_L (paper: 50 um)"),
        p("beam_profile", "one of: top_hat, gaussian", "", "top_hat: q_i = Q r_i^2/r_L^2 within r_L of the spot (paper); gaussian: q_i = 2 Q r_i^2/r_L^2 exp(-2 d^2/r_L^2), d < 2 r_L"),
        p("specific_heat", "specific heat", "J/(kg K)", "C_p (paper: 0.5 J/(g K) = 500 J/(kg K))"),
        p("density", "density", "kg/m^3", "particle density rho, m_i = 4/3 pi rho r_i^3 (paper: 8e-12 g/um^3 = 8000 kg/m^3)"),
        p("convection_conductance", "conductance", "W/K", "k_b, per-particle heat loss k_b (T_R - T_i) (paper: 2.9090e-5 W/K)"),
        p("contact_conductance", "conductance", "W/K", "k_t, conduction k_t (T_j - T_i) across each contact (paper: 3.3309e-4 W/K)"),
        p("bonded_conductance", "conductance", "W/K", "conductance of a bonded (sintered) pair; default k_t as in the paper"),
        p("ambient_temperature", "temperature", "K", "T_R, surrounding air temperature (paper: 300 K)"),
        p("initial_temperature", "temperature or null", "K", "initial temperature of every particle; null = the packing's `temperature` attribute when present (continue a previous run), else ambient_temperature"),
        p("sintering_temperature", "temperature", "K", "T_S: a contact bonds when both particles exceed it (paper: 1000 K)"),
        p("path", "one of: raster, csv", "", "laser path: raster of a rectangle or polyline from path_csv"),
        p("raster_center", "[x, y] or null", "m", "centre of the rastered rectangle; null = middle of the packing domain"),
        p("raster_length", "length", "m", "length of each scan line"),
        p("hatch_spacing", "length", "m", "distance between neighbouring scan lines"),
        p("passes", "integer", "", "number of scan lines (the paper's five passes); the rectangle is raster_length x passes*hatch_spacing; 0 = no laser (cooldown only)"),
        p("alternate", "bool", "", "true: serpentine, every other line reversed; false: all lines in the same direction"),
        p("scan_axis", "one of: x, y", "", "direction of the scan lines"),
        p("scan_speed", "velocity", "m/s", "laser travel speed along the path (the beam jumps between lines with the laser off in zero time)"),
        p("path_csv", "file path", "", "CSV polyline for path: csv; columns x,y[,on]; on=0 travels to the vertex with the laser off"),
        p("path_csv_unit", "length", "m", "length unit of the CSV coordinates (e.g. 1 um)"),
        p("cooldown", "time", "s", "simulated time after the path ends"),
        p("top_surface", "one of: auto, face, depth, all", "", "candidate absorbers: auto = zmax face list if present else depth; face = contact graph zmax list; depth = top within surface_depth of the highest top; all = every particle"),
        p("surface_depth", "length", "m", "depth of the absorbing top layer for top_surface: depth"),
        p("shadowing", "bool", "", "only candidates whose centre is not covered from above by a higher particle absorb"),
        p("melting", "bool", "", "latent heat of melting: temperature holds at melting_temperature until latent_heat m_i is absorbed (explicit integrator only)"),
        p("melting_temperature", "temperature", "K", "melting temperature for melting: true"),
        p("latent_heat", "specific energy", "J/kg", "latent heat of melting for melting: true"),
        p("integrator", "one of: explicit, implicit", "", "explicit forward Euler (paper) or implicit backward Euler"),
        p("dt", "time or null", "s", "time step; null = dt_safety x stability limit (explicit) or r_L/(5 scan_speed) (implicit)"),
        p("substep", "bool", "", "explicit: split a dt above the stability limit into stable sub-steps (or sub-cycle only the particles that need it, see multirate); false = refuse it"),
        p("multirate", "bool", "", "explicit with substep: true: particles whose own limit m_i C_p/(sum_j k_ij + k_b) is below the global step are sub-cycled at their own stable step inside it (energy-conserving flux accumulation); the global step is chosen to minimise the work. false = one global step at the smallest limit"),
        p("dt_safety", "number in (0, 1]", "", "fraction of the explicit stability limit used for automatic (sub-)steps"),
        p("cg_tolerance", "number", "", "implicit: relative residual at which conjugate gradients stop"),
        p("snapshot_interval", "time", "s", "interval between temperature snapshots (0 = initial and final only)"),
        p("history_interval", "time", "s", "interval between history rows (0 = every step)"),
        p("max_steps", "integer", "", "limit on (sub-)steps; the run fails with the time reached beyond it"),
    ]
}
