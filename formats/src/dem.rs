//! Inputs for DEM codes: LAMMPS data files (`atom_style sphere`, or `hybrid sphere
//! molecular` when bodies are clumps), LAMMPS molecule templates of a clump library, and the
//! sphere text files Yade's `ymport.text` / `ymport.textClumps` read. All lengths SI (LAMMPS
//! `units si`; Yade is SI).

use grainpipe_core::fsutil::{atomic_write, atomic_write_bytes};
use grainpipe_core::registry::{ExportOption, ExportOptions};
use grainpipe_core::{Artifact, BodyShape, Clump, Packing, Provenance};
use std::f64::consts::PI;
use std::fmt::Write as _;
use std::path::Path;

/// Quartz, the grains grainpipe mostly builds.
const DEFAULT_DENSITY: f64 = 2650.0;

fn density_option() -> ExportOption {
    ExportOption {
        name: "density",
        doc: "grain density [kg/m^3] written per atom; a clump's spheres share its mass \
              (density x clump volume) in proportion to their volumes",
        default: serde_json::json!(DEFAULT_DENSITY),
    }
}

fn density(o: &ExportOptions) -> Result<f64, String> {
    match o.get("density").and_then(|v| v.as_f64()) {
        Some(d) if d.is_finite() && d > 0.0 => Ok(d),
        None if !o.contains_key("density") => Ok(DEFAULT_DENSITY),
        _ => Err(format!(
            "{}: give a positive density in kg/m^3, e.g. `density: 2650`",
            o["density"]
        )),
    }
}

fn header_comment(prov: &Provenance, prefix: &str) -> String {
    let mut s = String::new();
    for (k, v) in &prov.entries {
        let _ = writeln!(s, "{prefix}{k}: {}", v.replace(['\n', '\r'], " "));
    }
    s
}

/// Per-sphere density that gives a clump the mass density x clump volume: the spheres
/// overlap, so their summed volume exceeds the clump's.
fn sphere_density(clump: &Clump, rho: f64) -> f64 {
    let sum: f64 = clump
        .spheres
        .iter()
        .map(|s| 4.0 / 3.0 * PI * s.radius.powi(3))
        .sum();
    if sum > 0.0 {
        rho * clump.volume / sum
    } else {
        rho
    }
}

/// Wraps a coordinate into [lo, hi) on a periodic axis (LAMMPS refuses atoms outside).
fn wrap(x: f64, lo: f64, hi: f64) -> f64 {
    let l = hi - lo;
    let y = lo + (x - lo).rem_euclid(l);
    if y >= hi {
        lo
    } else {
        y
    }
}

// ---------------------------------------------------------------------------------------
// LAMMPS data

/// The text of a LAMMPS data file: one atom per sphere (clumps expanded), box = the
/// packing's domain. Spheres only: `atom_style sphere` (id type diameter density x y z).
/// With clumps: `atom_style hybrid sphere molecular` (id type x y z diameter density
/// molecule), molecule = body index + 1, for `fix rigid/small molecule`.
pub fn lammps_data_text(p: &Packing, prov: &Provenance, rho: f64) -> Result<String, String> {
    Artifact::Packing(p.clone()).validate()?;
    let clumps = p
        .bodies
        .iter()
        .any(|b| matches!(b.shape, BodyShape::Clump { .. }));
    let spheres = p.world_spheres();
    let d = &p.domain;
    let mut s = String::from("LAMMPS data file from grainpipe (units si)\n");
    s.push_str(&header_comment(prov, "# "));
    let _ = writeln!(s, "\n{} atoms\n1 atom types\n", spheres.len());
    for (a, ax) in ["x", "y", "z"].iter().enumerate() {
        let _ = writeln!(s, "{:e} {:e} {ax}lo {ax}hi", d.min[a], d.max[a]);
    }
    let _ = writeln!(
        s,
        "\nAtoms # {}\n",
        if clumps { "hybrid" } else { "sphere" }
    );
    for (i, sp) in spheres.iter().enumerate() {
        let c = [0, 1, 2].map(|a| {
            if d.periodic[a] {
                wrap(sp.center[a], d.min[a], d.max[a])
            } else {
                sp.center[a]
            }
        });
        let body = &p.bodies[sp.body];
        let rho_i = match (&body.shape, &p.library) {
            (BodyShape::Clump { index }, Some(lib)) => sphere_density(&lib.clumps[*index], rho),
            _ => rho,
        };
        let diam = 2.0 * sp.radius;
        if clumps {
            let _ = writeln!(
                s,
                "{} 1 {:e} {:e} {:e} {diam:e} {rho_i:e} {}",
                i + 1,
                c[0],
                c[1],
                c[2],
                sp.body + 1
            );
        } else {
            let _ = writeln!(
                s,
                "{} 1 {diam:e} {rho_i:e} {:e} {:e} {:e}",
                i + 1,
                c[0],
                c[1],
                c[2]
            );
        }
    }
    Ok(s)
}

crate::vtk_xml::exporter!(
    LammpsDataExporter,
    "lammps-data",
    &["data", "lmp"],
    [Packing],
    "LAMMPS data file (`units si`, `read_data`): one atom per sphere, box = the packing's \
     domain (coordinates wrapped on periodic axes). Sphere packings: `atom_style sphere`, \
     columns id type diameter density x y z. Clump packings: `atom_style hybrid sphere \
     molecular`, columns id type x y z diameter density molecule, one molecule per body \
     for `fix rigid/small molecule`.",
    options: vec![density_option()],
    check: check_density,
    write: write_lammps_data
);

fn check_density(o: &ExportOptions) -> Result<(), (String, String)> {
    density(o).map(|_| ()).map_err(|m| ("density".into(), m))
}

fn write_lammps_data(
    a: &Artifact,
    path: &Path,
    prov: &Provenance,
    o: &ExportOptions,
) -> Result<(), String> {
    let Artifact::Packing(p) = a else {
        return Err(format!("lammps-data takes a Packing, not a {}", a.kind()));
    };
    let text = lammps_data_text(p, prov, density(o)?)?;
    atomic_write_bytes(path, text.as_bytes())
}

// ---------------------------------------------------------------------------------------
// LAMMPS molecule templates

/// One LAMMPS molecule file for a clump: body-frame coordinates about the centroid,
/// diameters, and masses summing to density x clump volume.
pub fn lammps_molecule_text(c: &Clump, prov: &Provenance, rho: f64) -> String {
    let mut s = format!(
        "LAMMPS molecule from grainpipe: {}\n",
        c.source.replace('\n', " ")
    );
    s.push_str(&header_comment(prov, "# "));
    let _ = writeln!(s, "\n{} atoms\n\nCoords\n", c.spheres.len());
    for (i, sp) in c.spheres.iter().enumerate() {
        let o = sp.offset;
        let _ = writeln!(s, "{} {:e} {:e} {:e}", i + 1, o[0], o[1], o[2]);
    }
    s.push_str("\nTypes\n\n");
    for i in 0..c.spheres.len() {
        let _ = writeln!(s, "{} 1", i + 1);
    }
    s.push_str("\nDiameters\n\n");
    for (i, sp) in c.spheres.iter().enumerate() {
        let _ = writeln!(s, "{} {:e}", i + 1, 2.0 * sp.radius);
    }
    s.push_str("\nMasses\n\n");
    let rho_i = sphere_density(c, rho);
    for (i, sp) in c.spheres.iter().enumerate() {
        let _ = writeln!(
            s,
            "{} {:e}",
            i + 1,
            rho_i * 4.0 / 3.0 * PI * sp.radius.powi(3)
        );
    }
    s
}

/// The molecule files of a library export to `path`: `<stem>_0000.mol`, ... beside it.
pub fn molecule_paths(path: &Path, n: usize) -> Vec<std::path::PathBuf> {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "clump".into());
    (0..n)
        .map(|k| path.with_file_name(format!("{stem}_{k:04}.mol")))
        .collect()
}

crate::vtk_xml::exporter!(
    LammpsMoleculeExporter,
    "lammps-molecule",
    &[],
    [ClumpLibrary, Packing],
    "LAMMPS molecule templates of a clump library (or a packing's library): one molecule \
     file per clump, `<stem>_0000.mol`, ... beside `to:` (Coords in the body frame about \
     the centroid, Types, Diameters, Masses summing to density x clump volume), and at \
     `to:` an input snippet `molecule grains <files>` to `include`. Select it with \
     `format: lammps-molecule`, e.g. `to: out/grains.in`.",
    options: vec![density_option()],
    check: check_density,
    write: write_lammps_molecules
);

fn write_lammps_molecules(
    a: &Artifact,
    path: &Path,
    prov: &Provenance,
    o: &ExportOptions,
) -> Result<(), String> {
    let lib = match a {
        Artifact::ClumpLibrary(l) => l,
        Artifact::Packing(p) => p.library.as_ref().ok_or_else(|| {
            "the packing has no clump library (sphere packings: use `lammps-data`)".to_string()
        })?,
        other => {
            return Err(format!(
                "lammps-molecule takes a ClumpLibrary, not a {}",
                other.kind()
            ))
        }
    };
    if lib.clumps.is_empty() {
        return Err("the clump library is empty".into());
    }
    let rho = density(o)?;
    let files = molecule_paths(path, lib.clumps.len());
    for (c, f) in lib.clumps.iter().zip(&files) {
        atomic_write_bytes(f, lammps_molecule_text(c, prov, rho).as_bytes())?;
    }
    let names: Vec<String> = files
        .iter()
        .map(|f| f.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    let script = format!(
        "# LAMMPS: include this file from the directory holding it\n{}molecule grains {}\n",
        header_comment(prov, "# "),
        names.join(" ")
    );
    atomic_write(path, |tmp| std::fs::write(tmp, script))
}

// ---------------------------------------------------------------------------------------
// Yade

/// `x y z r clump` per sphere (clumps expanded; clump = body index, shared by a clump's
/// spheres), `#` comment lines first: `ymport.text` takes the first four columns,
/// `ymport.textClumps` the fifth as the clump id.
pub fn yade_text(p: &Packing, prov: &Provenance) -> Result<String, String> {
    Artifact::Packing(p.clone()).validate()?;
    let mut s = String::from("# grainpipe packing for Yade: x y z r clump_id [m]\n");
    s.push_str(&header_comment(prov, "# "));
    for sp in p.world_spheres() {
        let c = sp.center;
        let _ = writeln!(
            s,
            "{:e} {:e} {:e} {:e} {}",
            c[0], c[1], c[2], sp.radius, sp.body
        );
    }
    Ok(s)
}

crate::vtk_xml::exporter!(
    YadeExporter,
    "yade",
    &[],
    [Packing],
    "Sphere text file for Yade: one line `x y z r clump_id` per sphere [m] (clumps \
     expanded, clump_id = body index), `#` comments first. `ymport.text(file)` reads the \
     spheres, `ymport.textClumps(file)` builds one clump per clump_id. Select it with \
     `format: yade` (e.g. `to: out/bed.txt`).",
    write_yade
);

fn write_yade(a: &Artifact, path: &Path, prov: &Provenance) -> Result<(), String> {
    let Artifact::Packing(p) = a else {
        return Err(format!("yade takes a Packing, not a {}", a.kind()));
    };
    atomic_write_bytes(path, yade_text(p, prov)?.as_bytes())
}
