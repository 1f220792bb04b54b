//! Pictures for reports: mid-plane slices of phase images and fields, an orthographic
//! depth-shaded rendering of packings, PNG encoding. They are plain pixel maps, one pixel per
//! voxel; the page frames them with axes, scale and colour bars drawn by grainpipe-charts.

use grainpipe_core::model::{Grid, Packing, PhaseImage};

/// An RGB picture, rows from the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Rgb {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<u8>,
}

impl Rgb {
    pub fn new(width: usize, height: usize, fill: [u8; 3]) -> Self {
        Rgb {
            width,
            height,
            pixels: fill.repeat(width * height),
        }
    }
    pub fn set(&mut self, x: usize, y: usize, c: [u8; 3]) {
        let i = 3 * (y * self.width + x);
        self.pixels[i..i + 3].copy_from_slice(&c);
    }
    pub fn get(&self, x: usize, y: usize) -> [u8; 3] {
        let i = 3 * (y * self.width + x);
        [self.pixels[i], self.pixels[i + 1], self.pixels[i + 2]]
    }

    /// PNG bytes (8-bit RGB).
    pub fn png(&self) -> Vec<u8> {
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, self.width as u32, self.height as u32);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut w = enc.write_header().expect("in-memory PNG header");
            w.write_image_data(&self.pixels)
                .expect("in-memory PNG data of the right length");
        }
        out
    }
}

/// A mid-plane through a voxel grid. The picture's horizontal axis is the first named axis
/// (rightwards), its vertical axis the second (upwards).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Plane {
    Xy,
    Xz,
    Yz,
}

impl Plane {
    pub const ALL: [Plane; 3] = [Plane::Xy, Plane::Xz, Plane::Yz];
    pub fn name(self) -> &'static str {
        match self {
            Plane::Xy => "xy",
            Plane::Xz => "xz",
            Plane::Yz => "yz",
        }
    }
    /// (horizontal axis, vertical axis, normal axis).
    pub fn axes(self) -> (usize, usize, usize) {
        match self {
            Plane::Xy => (0, 1, 2),
            Plane::Xz => (0, 2, 1),
            Plane::Yz => (1, 2, 0),
        }
    }
    /// "x-y plane at z = 140 um" for a grid.
    pub fn caption(self, grid: &Grid) -> String {
        let (h, v, n) = self.axes();
        let k = grid.dims[n] / 2;
        let pos = grid.origin[n] + (k as f64 + 0.5) * grid.spacing[n];
        format!(
            "{}-{} plane at {} = {} (voxel {k} of {})",
            AXIS[h],
            AXIS[v],
            AXIS[n],
            crate::html::length(pos),
            grid.dims[n]
        )
    }
}

pub const AXIS: [&str; 3] = ["x", "y", "z"];

/// The voxel index of picture pixel (px, py) on the mid-plane.
fn voxel_of(grid: &Grid, plane: Plane, px: usize, py: usize) -> usize {
    let (h, v, n) = plane.axes();
    let mut ijk = [0usize; 3];
    ijk[h] = px;
    ijk[v] = grid.dims[v] - 1 - py;
    ijk[n] = grid.dims[n] / 2;
    grid.index(ijk[0], ijk[1], ijk[2])
}

fn plane_size(grid: &Grid, plane: Plane) -> (usize, usize) {
    let (h, v, _) = plane.axes();
    (grid.dims[h], grid.dims[v])
}

/// Colour of a phase: pore light grey, grain tan, binder blue, then distinct hues.
pub fn phase_color(label: u8, name: &str) -> [u8; 3] {
    match (label, name) {
        (0, _) | (_, "pore") => [236, 236, 236],
        // `sand` was the binder stages' name for the grains: runs made before keep their look.
        (_, "grain" | "sand") => [214, 166, 92],
        (_, "binder") => [46, 104, 180],
        _ => {
            const P: [[u8; 3]; 8] = [
                [214, 166, 92],
                [46, 104, 180],
                [200, 70, 60],
                [80, 160, 90],
                [140, 90, 170],
                [230, 140, 40],
                [60, 170, 180],
                [120, 120, 120],
            ];
            P[(label as usize - 1) % P.len()]
        }
    }
}

/// The phase image on a mid-plane, one pixel per voxel.
pub fn phase_slice(img: &PhaseImage, plane: Plane) -> Rgb {
    let (w, h) = plane_size(&img.grid, plane);
    let name = |l: u8| {
        img.phases
            .iter()
            .find(|p| p.id == l)
            .map(|p| p.name.as_str())
            .unwrap_or("")
    };
    let colors: Vec<[u8; 3]> = (0..=255u8).map(|l| phase_color(l, name(l))).collect();
    let mut out = Rgb::new(w, h, [0, 0, 0]);
    for py in 0..h {
        for px in 0..w {
            let l = img.labels[voxel_of(&img.grid, plane, px, py)];
            out.set(px, py, colors[l as usize]);
        }
    }
    out
}

/// The colour map of fields (grainpipe-charts' viridis, as on the colour bars).
pub fn colormap(t: f64) -> [u8; 3] {
    grainpipe_charts::style::viridis(t)
}

/// A scalar per voxel on a mid-plane, mapped linearly from [lo, hi] to the colour map.
pub fn scalar_slice(
    grid: &Grid,
    value: &dyn Fn(usize) -> f64,
    plane: Plane,
    lo: f64,
    hi: f64,
) -> Rgb {
    let (w, h) = plane_size(grid, plane);
    let mut out = Rgb::new(w, h, [0, 0, 0]);
    let span = if hi > lo { hi - lo } else { 1.0 };
    for py in 0..h {
        for px in 0..w {
            let v = value(voxel_of(grid, plane, px, py));
            out.set(px, py, colormap((v - lo) / span));
        }
    }
    out
}

/// The view of a packing rendering.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum View {
    /// Looking down the z axis: x rightwards, y upwards.
    Top,
    /// Looking along +y: x rightwards, z upwards.
    Side,
}

/// Distinct, light colours per body so neighbouring grains can be told apart.
fn body_color(body: usize) -> [f64; 3] {
    // Golden-ratio hue steps, fixed saturation and value.
    let h = (body as f64 * 0.618_033_988_75).fract() * 6.0;
    let (s, v) = (0.45, 0.95);
    let c = v * s;
    let x = c * (1.0 - ((h % 2.0) - 1.0).abs());
    let (r, g, b) = match h as usize {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r + m, g + m, b + m]
}

/// Orthographic rendering of a packing's spheres (clumps expanded), depth-buffered and
/// Lambert-shaded with a little depth cueing, clipped to the domain box; `size` pixels along
/// the longer side of the view.
pub fn render_packing(p: &Packing, view: View, size: usize) -> Rgb {
    let (h, v, d) = match view {
        View::Top => (0, 1, 2),
        View::Side => (0, 2, 1),
    };
    // Viewer on the +z side for the top view and on the -y side for the side view.
    let toward = match view {
        View::Top => 1.0,
        View::Side => -1.0,
    };
    let ext = p.domain.size();
    let scale = size as f64 / ext[h].max(ext[v]).max(f64::MIN_POSITIVE);
    let w = ((ext[h] * scale).round() as usize).max(1);
    let hh = ((ext[v] * scale).round() as usize).max(1);
    let mut depth = vec![f64::NEG_INFINITY; w * hh];
    let mut out = Rgb::new(w, hh, [250, 250, 250]);
    let light = {
        let l: [f64; 3] = [-0.4, 0.5, 0.77];
        let n = l[0] * l[0] + l[1] * l[1] + l[2] * l[2];
        l.map(|x: f64| x / n.sqrt())
    };
    let (dmin, dspan) = (p.domain.min[d], ext[d].max(f64::MIN_POSITIVE));
    for s in p.world_spheres() {
        let cx = (s.center[h] - p.domain.min[h]) * scale;
        let cy = (p.domain.max[v] - s.center[v]) * scale;
        let r = s.radius * scale;
        let x0 = (cx - r).floor().max(0.0) as usize;
        let x1 = ((cx + r).ceil().max(0.0) as usize).min(w);
        let y0 = (cy - r).floor().max(0.0) as usize;
        let y1 = ((cy + r).ceil().max(0.0) as usize).min(hh);
        let base = body_color(s.body);
        for py in y0..y1 {
            for px in x0..x1 {
                let dx = (px as f64 + 0.5 - cx) / r;
                let dy = (py as f64 + 0.5 - cy) / r;
                let q = 1.0 - dx * dx - dy * dy;
                if q <= 0.0 {
                    continue;
                }
                let dz = q.sqrt();
                // Height of the surface toward the viewer, in metres along the view axis.
                let z = toward * s.center[d] + dz * s.radius;
                let k = py * w + px;
                if z <= depth[k] {
                    continue;
                }
                depth[k] = z;
                // Picture normal: right, up, toward the viewer.
                let lambert = (dx * light[0] - dy * light[1] + dz * light[2]).max(0.0);
                let surface = toward * z - dmin;
                let cue = if toward > 0.0 {
                    surface / dspan
                } else {
                    1.0 - surface / dspan
                };
                let shade = (0.25 + 0.75 * lambert) * (0.6 + 0.4 * cue.clamp(0.0, 1.0));
                out.set(px, py, base.map(|c| (255.0 * c * shade).round() as u8));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use grainpipe_core::model::{Body, Domain, Phase};

    fn grid(d: [usize; 3]) -> Grid {
        Grid {
            dims: d,
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic: [true; 3],
        }
    }

    #[test]
    fn slices_are_oriented_with_the_second_axis_up() {
        // A 4x3x2 image labelled by x, then y, then z.
        let g = grid([4, 3, 2]);
        let mut labels = vec![0u8; 24];
        for z in 0..2 {
            for y in 0..3 {
                for x in 0..4 {
                    labels[g.index(x, y, z)] = if x == 3 && y == 2 { 1 } else { 0 };
                }
            }
        }
        let img = PhaseImage {
            grid: g,
            labels,
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
        let s = phase_slice(&img, Plane::Xy);
        assert_eq!((s.width, s.height), (4, 3));
        // (x = 3, y = 2) is the top right pixel.
        assert_eq!(s.get(3, 0), phase_color(1, "grain"));
        assert_eq!(s.get(3, 2), phase_color(0, "pore"));
        let s = phase_slice(&img, Plane::Yz);
        assert_eq!((s.width, s.height), (3, 2));
    }

    #[test]
    fn png_round_trips() {
        let mut img = Rgb::new(3, 2, [1, 2, 3]);
        img.set(2, 1, [200, 100, 50]);
        let bytes = img.png();
        let dec = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut r = dec.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size()];
        let info = r.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (3, 2));
        assert_eq!(&buf[..info.buffer_size()], &img.pixels[..]);
    }

    #[test]
    fn rendering_covers_the_projected_area_of_a_sphere() {
        // One sphere of radius 0.25 in a unit box: it covers pi/16 of the top view.
        let mut p = Packing::new(Domain::boxed([0.0; 3], [1.0; 3], [false; 3]));
        p.bodies.push(Body::sphere([0.5, 0.5, 0.5], 0.25));
        let img = render_packing(&p, View::Top, 400);
        let bg = [250, 250, 250];
        let covered = (0..400)
            .flat_map(|y| (0..400).map(move |x| (x, y)))
            .filter(|&(x, y)| img.get(x, y) != bg)
            .count();
        let expected = std::f64::consts::PI / 16.0 * 160000.0;
        assert!((covered as f64 / expected - 1.0).abs() < 0.01, "{covered}");
    }
}
