//! The png exporter draws a top view of a contact graph: checked pixel by pixel.

use grainpipe_core::model::{Artifact, ArtifactKind, Contact, ContactGraph, Provenance};
use grainpipe_core::Exporter;
use grainpipe_sintering::BondGraphPng;

#[test]
fn top_view_png_shows_bonds_and_particles() {
    // Four particles on a 100 um square; one bond along the bottom edge.
    let pos = vec![
        [0.0, 0.0, 0.0],
        [100e-6, 0.0, 0.0],
        [0.0, 100e-6, 5e-6],
        [100e-6, 100e-6, 0.0],
    ];
    let c = |i, j| Contact { i, j, gap: 0.0 };
    let g = ContactGraph {
        contacts: vec![c(0, 1), c(0, 2), c(1, 3), c(2, 3)],
        bonds: vec![[0, 1]],
        positions: pos,
        radii: Vec::new(),
        ..Default::default()
    };
    let ex = BondGraphPng;
    assert!(ex.accepts(ArtifactKind::ContactGraph) && !ex.accepts(ArtifactKind::Packing));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bonds.png");
    ex.write_defaults(&Artifact::ContactGraph(g), &path, &Provenance::default())
        .unwrap();
    let img = image::open(&path).unwrap().to_rgb8();
    // Square extent: 1600 px with 20 px margins -> 1560 px for 100 um, and the legend band.
    assert_eq!(
        img.dimensions(),
        (1600, 1600 + grainpipe_sintering::png::LEGEND)
    );
    let px = |x: u32, y: u32| img.get_pixel(x, y).0;
    // Bond midpoint (50 um, 0) -> pixel (800, 1580): black line.
    assert_eq!(px(800, 1580), [0, 0, 0]);
    // No bond along the top edge, between the circles: white background.
    assert_eq!(px(800, 20), [255, 255, 255]);
    // Bonded particle 0 at (20, 1580) is filled orange a few pixels off the line.
    assert_eq!(px(20, 1560), [230, 120, 30]);
    // Unbonded particle 3 at (1580, 20): grey outline of radius 780 px (half the
    // 100 um contact distance), white inside.
    assert_eq!(px(1580, 300), [255, 255, 255]);
    // The write was atomic: only the final file is left in the directory.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    // Anything but a contact graph is refused.
    let t = Artifact::Table(Default::default());
    assert!(ex
        .write_defaults(&t, &dir.path().join("x.png"), &Provenance::default())
        .is_err());
}

#[test]
fn png_carries_the_provenance_as_text_chunks() {
    // Issue 17: every exported file carries its provenance; PNG in iTXt chunks.
    let g = ContactGraph {
        contacts: vec![Contact {
            i: 0,
            j: 1,
            gap: 0.0,
        }],
        positions: vec![[0.0; 3], [1e-4, 0.0, 0.0]],
        radii: Vec::new(),
        ..Default::default()
    };
    let mut prov = Provenance::default();
    prov.entries.insert("seed".into(), "42".into());
    prov.entries
        .insert("pipeline_yaml".into(), "name: µ-bed\nseed: 42\n".into());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("b.png");
    BondGraphPng
        .write_defaults(&Artifact::ContactGraph(g), &path, &prov)
        .unwrap();
    let dec = png::Decoder::new(std::fs::File::open(&path).unwrap());
    let reader = dec.read_info().unwrap();
    let text: Vec<(String, String)> = reader
        .info()
        .utf8_text
        .iter()
        .map(|t| (t.keyword.clone(), t.get_text().unwrap()))
        .collect();
    assert!(text.contains(&("seed".into(), "42".into())), "{text:?}");
    assert!(
        text.contains(&("pipeline_yaml".into(), "name: µ-bed\nseed: 42\n".into())),
        "{text:?}"
    );
}

fn square() -> ContactGraph {
    let c = |i, j| Contact { i, j, gap: 0.0 };
    ContactGraph {
        contacts: vec![c(0, 1), c(0, 2), c(1, 3), c(2, 3)],
        bonds: vec![[0, 1]],
        positions: vec![
            [0.0, 0.0, 0.0],
            [100e-6, 0.0, 0.0],
            [0.0, 100e-6, 5e-6],
            [100e-6, 100e-6, 0.0],
        ],
        radii: Vec::new(),
        ..Default::default()
    }
}

#[test]
fn scale_bar_is_its_length_over_the_pixel_size() {
    use grainpipe_sintering::png::{ScaleBar, View};
    let g = square();
    let view = View::new(&g);
    // 100 um over 1560 px; a fifth of the width is 20 um, already a round length.
    assert!((view.pixel_size() - 100e-6 / 1560.0).abs() < 1e-18);
    let bar = ScaleBar::new(&view);
    assert!((bar.length - 20e-6).abs() < 1e-18, "{bar:?}");
    assert_eq!(bar.pixels, 312);
    assert_eq!(bar.pixels, (bar.length / view.pixel_size()).round() as u32);
    assert_eq!(bar.label(), "20 µm");
    // The drawn bar: a run of exactly `pixels` black pixels along its middle row.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bar.png");
    BondGraphPng
        .write_defaults(&Artifact::ContactGraph(g), &path, &Provenance::default())
        .unwrap();
    let img = image::open(&path).unwrap().to_rgb8();
    let y = bar.y as u32;
    let run = (bar.x as u32..img.width())
        .take_while(|&x| img.get_pixel(x, y).0 == [0, 0, 0])
        .count();
    assert_eq!(run as u32, bar.pixels);
    assert_eq!(img.get_pixel(bar.x as u32 - 1, y).0, [255, 255, 255]);
}

#[test]
fn powderbed_bond_graph_png_is_small_and_indexed() {
    // The bond graph of pipelines/powderbed.yaml (about 3,000 particles and their bonds) was
    // 4.5 MB as unfiltered RGB; palette-indexed at the strongest deflate level it must stay
    // below 400 kB.
    let root = grainpipe_core::testing::workspace_root(env!("CARGO_MANIFEST_DIR"));
    let mut doc =
        grainpipe_core::pipeline::PipelineDoc::load(&root.join("pipelines/powderbed.yaml"))
            .unwrap();
    doc.exports.clear();
    let mut reg = grainpipe_core::Registry::new();
    grainpipe_bricks::register(&mut reg);
    grainpipe_sintering::register(&mut reg);
    let r = grainpipe_core::engine::run_quietly(&doc, &reg).unwrap();
    let bonds = r
        .artifact("sinter.bonds")
        .as_contact_graph()
        .unwrap()
        .clone();
    assert!(!bonds.bonds.is_empty());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bonds_top.png");
    BondGraphPng
        .write_defaults(
            &Artifact::ContactGraph(bonds),
            &path,
            &Provenance::default(),
        )
        .unwrap();
    let size = std::fs::metadata(&path).unwrap().len();
    assert!(size < 400_000, "{size} bytes");
    let reader = png::Decoder::new(std::fs::File::open(&path).unwrap())
        .read_info()
        .unwrap();
    assert_eq!(reader.info().color_type, png::ColorType::Indexed);
}
