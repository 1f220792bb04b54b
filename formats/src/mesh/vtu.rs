//! VTK XML UnstructuredGrid (`.vtu`) writer, streaming.
//!
//! Layout per "VTK File Formats" (VTK User's Guide, XML formats): `<Piece NumberOfPoints
//! NumberOfCells>` with `<PointData>`, `<CellData>`, `<Points>` (one Float64 array of three
//! components) and `<Cells>` (`connectivity`, `offsets` = end of each cell's run in
//! `connectivity`, `types` = VTK cell type ids). Binary arrays carry a UInt64 header: the
//! byte count for uncompressed data; for zlib data `[#blocks, block size, size of the last
//! partial block (0 if full), compressed size of each block]`, then the blocks. Inline
//! (`format="binary"`) data is base64; for compressed data the header is encoded separately
//! from the blocks (what VTK writes and meshio's `read_compressed_binary` decodes: it reads
//! the header's base64 characters first, then decodes the rest). Appended data is raw
//! (`<AppendedData encoding="raw">`, `_` then the arrays back to back, `offset` = byte
//! position after the `_`), which both VTK and meshio (`_parse_raw_binary`) read.
//!
//! meshio reads no string arrays (`type="String"`), so field data holds numbers only and the
//! provenance is an XML comment at the top of the file.

use super::{Chunk, Column, Dtype, Mesh};
use base64::Engine;
use std::fs::File;
use std::io::{self, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::Path;

const B64: base64::engine::GeneralPurpose = base64::engine::general_purpose::STANDARD;
/// Uncompressed bytes per zlib block (VTK's default).
pub const BLOCK: usize = 1 << 15;
/// Blocks compressed together (in parallel) before they are written.
const BATCH_BLOCKS: usize = 64;

/// Where and how array values are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VtuEncoding {
    /// Raw binary in `<AppendedData encoding="raw">` (smallest and fastest).
    Appended,
    /// base64 inside each `<DataArray format="binary">`.
    Binary,
    /// Text inside each `<DataArray format="ascii">`.
    Ascii,
}

impl VtuEncoding {
    pub const NAMES: [&'static str; 3] = ["appended", "binary", "ascii"];

    pub fn from_name(s: &str) -> Option<Self> {
        match s {
            "appended" => Some(Self::Appended),
            "binary" => Some(Self::Binary),
            "ascii" => Some(Self::Ascii),
            _ => None,
        }
    }
}

pub(crate) fn vtk_type_name(d: Dtype) -> &'static str {
    match d {
        Dtype::U8 => "UInt8",
        Dtype::I32 => "Int32",
        Dtype::I64 => "Int64",
        Dtype::F32 => "Float32",
        Dtype::F64 => "Float64",
    }
}

fn esc(s: &str) -> String {
    quick_xml::escape::escape(s).into_owned()
}

/// An XML comment holding `text` (`--` may not appear inside a comment).
pub(crate) fn xml_comment(text: &str) -> String {
    format!("<!-- {} -->\n", text.replace("--", "- -"))
}

/// Streams a column's values as little-endian bytes into `w`.
pub(crate) fn stream_le(col: &Column, w: &mut impl Write) -> io::Result<()> {
    let mut buf = Vec::new();
    col.produce(&mut |c: Chunk<'_>| {
        buf.clear();
        c.put_bytes(true, &mut buf);
        w.write_all(&buf)
    })
}

/// Compresses what is written to it into zlib blocks of [`BLOCK`] bytes, written to `inner`
/// in order; [`BlockCompressor::finish`] gives VTK's header for them.
pub(crate) struct BlockCompressor<W: Write> {
    inner: W,
    pending: Vec<u8>,
    sizes: Vec<u64>,
    total: u64,
    level: u32,
}

impl<W: Write> BlockCompressor<W> {
    pub fn new(inner: W, level: u32) -> Self {
        BlockCompressor {
            inner,
            pending: Vec::with_capacity(BLOCK * BATCH_BLOCKS),
            sizes: Vec::new(),
            total: 0,
            level,
        }
    }

    fn compress_pending(&mut self, all: bool) -> io::Result<()> {
        use rayon::prelude::*;
        let full = if all {
            self.pending.len()
        } else {
            self.pending.len() / BLOCK * BLOCK
        };
        if full == 0 {
            return Ok(());
        }
        let level = flate2::Compression::new(self.level);
        let blocks: Vec<Vec<u8>> = self.pending[..full]
            .par_chunks(BLOCK)
            .map(|b| {
                let mut e = flate2::write::ZlibEncoder::new(Vec::new(), level);
                e.write_all(b).and_then(|()| e.finish())
            })
            .collect::<io::Result<_>>()?;
        for b in blocks {
            self.sizes.push(b.len() as u64);
            self.inner.write_all(&b)?;
        }
        self.pending.drain(..full);
        Ok(())
    }

    /// Flushes the last block; returns the inner writer and the header.
    pub fn finish(mut self) -> io::Result<(W, Vec<u64>)> {
        self.compress_pending(true)?;
        let mut header = vec![
            self.sizes.len() as u64,
            BLOCK as u64,
            self.total % BLOCK as u64,
        ];
        header.extend_from_slice(&self.sizes);
        Ok((self.inner, header))
    }

    /// Number of blocks `bytes` bytes make.
    pub fn block_count(bytes: u64) -> u64 {
        bytes.div_ceil(BLOCK as u64)
    }
}

impl<W: Write> Write for BlockCompressor<W> {
    fn write(&mut self, b: &[u8]) -> io::Result<usize> {
        self.pending.extend_from_slice(b);
        self.total += b.len() as u64;
        if self.pending.len() >= BLOCK * BATCH_BLOCKS {
            self.compress_pending(false)?;
        }
        Ok(b.len())
    }
    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

fn header_bytes(h: &[u64]) -> Vec<u8> {
    h.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// The generated `offsets` and `types` columns of a mesh.
fn cell_columns<'m>(mesh: &'m Mesh<'m>) -> [Column<'m>; 2] {
    let nodes = mesh.kind.nodes() as i64;
    let cells = mesh.cell_count;
    let ty = mesh.kind.vtk_type();
    [
        Column::generated::<i64>("offsets", 1, cells, move |sink| {
            super::emit(sink, (1..=cells as i64).map(|i| i * nodes))
        }),
        Column::generated::<u8>("types", 1, cells, move |sink| {
            super::emit(sink, std::iter::repeat_n(ty, cells))
        }),
    ]
}

fn array_open(tag: &str, c: &Column, format: &str) -> String {
    let mut s = format!(
        "<{tag} type=\"{}\" Name=\"{}\" NumberOfComponents=\"{}\" NumberOfTuples=\"{}\"",
        vtk_type_name(c.dtype),
        esc(&c.name),
        c.components,
        c.tuples
    );
    for (k, n) in c.component_names.iter().enumerate() {
        s.push_str(&format!(" ComponentName{k}=\"{}\"", esc(n)));
    }
    s.push_str(&format!(" format=\"{format}\""));
    s
}

fn ascii_array(tag: &str, c: &Column, w: &mut impl Write) -> io::Result<()> {
    w.write_all(array_open(tag, c, "ascii").as_bytes())?;
    w.write_all(b">\n")?;
    let mut s = String::new();
    c.produce(&mut |ch: Chunk<'_>| {
        s.clear();
        ch.put_text(&mut s, ' ');
        s.push('\n');
        w.write_all(s.as_bytes())
    })?;
    w.write_all(format!("</{tag}>\n").as_bytes())
}

/// Writes `mesh` as a `.vtu` file at `path` (a plain file; the caller makes it atomic).
/// `level` 0 writes uncompressed arrays, 1-9 zlib blocks at that level. `comment` goes into
/// an XML comment at the top (provenance).
pub fn write_vtu(
    path: &Path,
    mesh: &Mesh,
    encoding: VtuEncoding,
    level: u32,
    comment: &str,
) -> io::Result<()> {
    let mut w = BufWriter::with_capacity(1 << 20, File::create(path)?);
    let compressed = level > 0 && encoding != VtuEncoding::Ascii;
    let [offsets, types] = cell_columns(mesh);
    // Arrays in file order, with the section each opens or closes.
    let mut sections: Vec<(&str, Vec<&Column>)> = vec![
        ("PointData", mesh.point_data.iter().collect()),
        ("CellData", mesh.cell_data.iter().collect()),
        ("Points", vec![&mesh.points]),
        ("Cells", vec![&mesh.connectivity, &offsets, &types]),
    ];
    sections.retain(|(name, cols)| !cols.is_empty() || matches!(*name, "PointData" | "CellData"));

    // Appended, compressed: the blocks' sizes must be known for the offsets in the XML, so
    // the arrays are compressed into a spill file first (on disk, not in memory).
    let spill_path = grainpipe_core::fsutil::temp_path_for(path);
    let mut spilled: Vec<(Vec<u64>, u64)> = Vec::new();
    if encoding == VtuEncoding::Appended && compressed {
        let spill = BufWriter::new(File::create(&spill_path)?);
        let mut comp_sink = Some(spill);
        for (_, cols) in &sections {
            for c in cols.iter().filter(|c| c.values() > 0) {
                let mut bc = BlockCompressor::new(comp_sink.take().expect("spill"), level);
                stream_le(c, &mut bc)?;
                let (inner, header) = bc.finish()?;
                let len: u64 = header[3..].iter().sum();
                spilled.push((header, len));
                comp_sink = Some(inner);
            }
        }
        comp_sink.expect("spill").flush()?;
    }
    let result = (|| -> io::Result<()> {
        let mut head = String::from("<?xml version=\"1.0\"?>\n");
        head.push_str(&xml_comment(comment));
        head.push_str(
            "<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\" \
             header_type=\"UInt64\"",
        );
        if compressed {
            head.push_str(" compressor=\"vtkZLibDataCompressor\"");
        }
        head.push_str(">\n<UnstructuredGrid>\n");
        w.write_all(head.as_bytes())?;
        if !mesh.field_data.is_empty() {
            w.write_all(b"<FieldData>\n")?;
            for c in &mesh.field_data {
                ascii_array("Array", c, &mut w)?;
            }
            w.write_all(b"</FieldData>\n")?;
        }
        w.write_all(
            format!(
                "<Piece NumberOfPoints=\"{}\" NumberOfCells=\"{}\">\n",
                mesh.point_count, mesh.cell_count
            )
            .as_bytes(),
        )?;
        let mut offset = 0u64;
        let mut spilled_iter = spilled.iter();
        for (name, cols) in &sections {
            w.write_all(format!("<{name}>\n").as_bytes())?;
            for c in cols {
                if c.values() == 0 || encoding == VtuEncoding::Ascii {
                    // An empty compressed array has no blocks, which readers misread.
                    ascii_array("DataArray", c, &mut w)?;
                    continue;
                }
                match encoding {
                    VtuEncoding::Appended => {
                        w.write_all(array_open("DataArray", c, "appended").as_bytes())?;
                        w.write_all(format!(" offset=\"{offset}\"/>\n").as_bytes())?;
                        offset += if compressed {
                            let (h, len) = spilled_iter.next().expect("one per array");
                            8 * h.len() as u64 + len
                        } else {
                            8 + c.bytes()
                        };
                    }
                    VtuEncoding::Binary => {
                        w.write_all(array_open("DataArray", c, "binary").as_bytes())?;
                        w.write_all(b">\n")?;
                        if compressed {
                            inline_compressed(c, level, &mut w)?;
                        } else {
                            let mut enc = base64::write::EncoderWriter::new(&mut w, &B64);
                            enc.write_all(&c.bytes().to_le_bytes())?;
                            stream_le(c, &mut enc)?;
                            enc.finish()?;
                        }
                        w.write_all(b"\n</DataArray>\n")?;
                    }
                    VtuEncoding::Ascii => unreachable!("handled above"),
                }
            }
            w.write_all(format!("</{name}>\n").as_bytes())?;
        }
        w.write_all(b"</Piece>\n</UnstructuredGrid>\n")?;
        if encoding == VtuEncoding::Appended {
            w.write_all(b"<AppendedData encoding=\"raw\">\n_")?;
            if compressed {
                let mut spill = io::BufReader::new(File::open(&spill_path)?);
                for (h, len) in &spilled {
                    w.write_all(&header_bytes(h))?;
                    let copied = io::copy(&mut (&mut spill).take(*len), &mut w)?;
                    if copied != *len {
                        return Err(io::Error::other("spill file shorter than written"));
                    }
                }
            } else {
                for (_, cols) in &sections {
                    for c in cols.iter().filter(|c| c.values() > 0) {
                        w.write_all(&c.bytes().to_le_bytes())?;
                        stream_le(c, &mut w)?;
                    }
                }
            }
            w.write_all(b"\n</AppendedData>\n")?;
        }
        w.write_all(b"</VTKFile>\n")?;
        w.flush()
    })();
    if encoding == VtuEncoding::Appended && compressed {
        let _ = std::fs::remove_file(&spill_path);
    }
    result
}

/// One compressed inline array: base64(header) then base64(blocks). The header's length is
/// fixed by the number of blocks, so a placeholder is written first and filled in after the
/// blocks have been streamed.
fn inline_compressed(c: &Column, level: u32, w: &mut BufWriter<File>) -> io::Result<()> {
    let blocks = BlockCompressor::<Vec<u8>>::block_count(c.bytes());
    let header_len = 8 * (3 + blocks as usize);
    let placeholder = B64.encode(vec![0u8; header_len]);
    let at = w.stream_position()?;
    w.write_all(placeholder.as_bytes())?;
    let enc = base64::write::EncoderWriter::new(&mut *w, &B64);
    let mut bc = BlockCompressor::new(enc, level);
    stream_le(c, &mut bc)?;
    let (mut enc, header) = bc.finish()?;
    enc.finish()?;
    drop(enc);
    let end = w.stream_position()?;
    w.seek(SeekFrom::Start(at))?;
    let text = B64.encode(header_bytes(&header));
    debug_assert_eq!(text.len(), placeholder.len());
    w.write_all(text.as_bytes())?;
    w.seek(SeekFrom::Start(end))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{Column, Mesh, VoxelHexMesh};
    use crate::volume::VolumeData;
    use crate::vtk_xml::{Node, VtkFile};

    fn walk<'n>(n: &'n Node, name: &str, out: &mut Vec<&'n Node>) {
        if n.name == "DataArray" && n.attr("Name") == Some(name) {
            out.push(n);
        }
        for c in &n.children {
            walk(c, name, out);
        }
    }

    fn values(f: &VtkFile, name: &str) -> Vec<f64> {
        let mut found = Vec::new();
        walk(&f.root, name, &mut found);
        let v = f.array_values(found[0]).unwrap();
        (0..v.len()).map(|i| v.get(i)).collect()
    }

    /// Every encoding and compression reads back (through the `.vti` reader's decoder, which
    /// was written against VTK's own files) to the points, cells and labels of the mesh.
    #[test]
    fn every_encoding_reads_back_to_the_mesh() {
        let dims = [5, 4, 3];
        // More than one zlib block for the connectivity at 33 KiB+: use a bigger image too.
        for dims in [dims, [40, 30, 20]] {
            let n = dims[0] * dims[1] * dims[2];
            let labels: Vec<u8> = (0..n).map(|v| (v * 7 % 5) as u8).collect();
            let mut sel = [false; 256];
            sel[1] = true;
            sel[3] = true;
            let vm = VoxelHexMesh::new(
                dims,
                [1e-3, -2e-3, 0.5],
                [1e-6, 2e-6, 3e-6],
                Some(&labels),
                sel,
            )
            .unwrap();
            let mut mesh = Mesh::of_voxels(&vm);
            let (l, v) = (&labels, &vm);
            mesh.cell_data.push(Column::generated::<u8>(
                "phase",
                1,
                vm.cell_count(),
                move |s| crate::mesh::emit(s, v.voxels().map(|x| l[x])),
            ));
            let expect_labels: Vec<f64> = vm.voxels().map(|x| labels[x] as f64).collect();
            let expect_points: Vec<f64> = vm.point_corners().flat_map(|c| vm.position(c)).collect();
            let expect_conn: Vec<f64> = vm.cells().flat_map(|(_, n)| n.map(|p| p as f64)).collect();
            let dir = tempfile::tempdir().unwrap();
            for enc in [
                VtuEncoding::Appended,
                VtuEncoding::Binary,
                VtuEncoding::Ascii,
            ] {
                for level in [0, 1, 6] {
                    let p = dir.path().join(format!("m_{enc:?}_{level}.vtu"));
                    write_vtu(&p, &mesh, enc, level, "test -- comment").unwrap();
                    let f = VtkFile::open(&p).unwrap();
                    assert_eq!(values(&f, "phase"), expect_labels, "{enc:?} {level}");
                    assert_eq!(values(&f, "Points"), expect_points, "{enc:?} {level}");
                    assert_eq!(values(&f, "connectivity"), expect_conn, "{enc:?} {level}");
                    let off = values(&f, "offsets");
                    assert_eq!(off.len(), vm.cell_count());
                    assert_eq!(*off.last().unwrap(), 8.0 * vm.cell_count() as f64);
                    assert!(values(&f, "types").iter().all(|&t| t == 12.0));
                    let mut typ = Vec::new();
                    walk(&f.root, "phase", &mut typ);
                    assert!(matches!(f.array_values(typ[0]).unwrap(), VolumeData::U8(_)));
                }
            }
            // No spill file is left behind.
            let left: Vec<_> = std::fs::read_dir(dir.path())
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .filter(|n| !n.ends_with(".vtu"))
                .collect();
            assert!(left.is_empty(), "{left:?}");
        }
    }
}
