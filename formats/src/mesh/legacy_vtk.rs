//! Legacy VTK (`.vtk`) UNSTRUCTURED_GRID writer, file version 4.2, streaming.
//!
//! Layout per "VTK File Formats" (legacy format, version 4.2): `CELLS <cells> <size>` with
//! each cell as its node count then its point ids (32-bit ints), `CELL_TYPES`, then
//! `CELL_DATA` / `POINT_DATA` with every array as a `FIELD` array (`name components tuples
//! type`). Binary data is big-endian, each block followed by a newline (which meshio's reader
//! checks). Version 4.2 rather than 5.1: VTK's 5.1 reader takes only the classic type names
//! (`unsigned_char`, ...) and meshio's 5.1 reader only the fixed-size ones (`vtktypeuint8`),
//! so no name would give uint8 labels in both; with 4.2 both read `unsigned_char` as uint8,
//! `int` as int32, `long` as int64 (VTK: on LP64 platforms such as Linux and macOS).

use super::{token, Chunk, Column, Dtype, Mesh};
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::Path;

fn type_name(d: Dtype) -> &'static str {
    match d {
        Dtype::U8 => "unsigned_char",
        Dtype::I32 => "int",
        Dtype::I64 => "long",
        Dtype::F32 => "float",
        Dtype::F64 => "double",
    }
}

fn values(c: &Column, binary: bool, w: &mut impl Write) -> io::Result<()> {
    let mut bytes = Vec::new();
    let mut text = String::new();
    c.produce(&mut |ch: Chunk<'_>| {
        if binary {
            bytes.clear();
            ch.put_bytes(false, &mut bytes);
            w.write_all(&bytes)
        } else {
            text.clear();
            ch.put_text(&mut text, '\n');
            w.write_all(text.as_bytes())
        }
    })?;
    if binary {
        w.write_all(b"\n")?;
    }
    Ok(())
}

fn field_block(cols: &[Column], binary: bool, w: &mut impl Write) -> io::Result<()> {
    w.write_all(format!("FIELD FieldData {}\n", cols.len()).as_bytes())?;
    for c in cols {
        w.write_all(
            format!(
                "{} {} {} {}\n",
                token(&c.name),
                c.components,
                c.tuples,
                type_name(c.dtype)
            )
            .as_bytes(),
        )?;
        values(c, binary, w)?;
    }
    Ok(())
}

/// Writes `mesh` as a legacy `.vtk` file at `path` (a plain file; the caller makes it
/// atomic). `title` is the header line (cut to 255 characters, one line).
pub fn write_legacy_vtk(path: &Path, mesh: &Mesh, binary: bool, title: &str) -> io::Result<()> {
    let mut w = BufWriter::with_capacity(1 << 20, File::create(path)?);
    let title: String = title
        .chars()
        .map(|c| if c.is_control() { ' ' } else { c })
        .take(255)
        .collect();
    w.write_all(
        format!(
            "# vtk DataFile Version 4.2\n{title}\n{}\nDATASET UNSTRUCTURED_GRID\n",
            if binary { "BINARY" } else { "ASCII" }
        )
        .as_bytes(),
    )?;
    if !mesh.field_data.is_empty() {
        field_block(&mesh.field_data, binary, &mut w)?;
    }
    w.write_all(format!("POINTS {} double\n", mesh.point_count).as_bytes())?;
    values(&mesh.points, binary, &mut w)?;
    let nodes = mesh.kind.nodes();
    let cells = mesh.cell_count;
    if mesh.point_count > i32::MAX as usize {
        return Err(io::Error::other(format!(
            "{} points: legacy VTK cells hold 32-bit point ids; export .vtu",
            mesh.point_count
        )));
    }
    w.write_all(format!("CELLS {cells} {}\n", cells * (nodes + 1)).as_bytes())?;
    // Each cell: its node count, then its point ids.
    let mut pending: Vec<i64> = Vec::new();
    let mut bytes = Vec::new();
    let mut text = String::new();
    mesh.connectivity.produce(&mut |ch: Chunk<'_>| {
        if let Chunk::I64(v) = ch {
            pending.extend_from_slice(v);
        }
        let whole = pending.len() / nodes * nodes;
        let mut run: Vec<i32> = Vec::with_capacity(whole / nodes * (nodes + 1));
        for cell in pending[..whole].chunks_exact(nodes) {
            run.push(nodes as i32);
            run.extend(cell.iter().map(|&p| p as i32));
        }
        pending.drain(..whole);
        if binary {
            bytes.clear();
            Chunk::I32(&run).put_bytes(false, &mut bytes);
            w.write_all(&bytes)
        } else {
            text.clear();
            for cell in run.chunks(nodes + 1) {
                Chunk::I32(cell).put_text(&mut text, ' ');
                text.push('\n');
            }
            w.write_all(text.as_bytes())
        }
    })?;
    if binary {
        w.write_all(b"\n")?;
    }
    // Cell types are always 32-bit ints (VTK reads them as `int`).
    w.write_all(format!("CELL_TYPES {cells}\n").as_bytes())?;
    let ty = i32::from(mesh.kind.vtk_type());
    let types = Column::generated::<i32>("types", 1, cells, move |sink| {
        super::emit(sink, std::iter::repeat_n(ty, cells))
    });
    values(&types, binary, &mut w)?;
    if !mesh.cell_data.is_empty() {
        w.write_all(format!("CELL_DATA {cells}\n").as_bytes())?;
        field_block(&mesh.cell_data, binary, &mut w)?;
    }
    if !mesh.point_data.is_empty() {
        w.write_all(format!("POINT_DATA {}\n", mesh.point_count).as_bytes())?;
        field_block(&mesh.point_data, binary, &mut w)?;
    }
    w.flush()
}
