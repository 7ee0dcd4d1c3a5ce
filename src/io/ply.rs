//! PLY point clouds, read and written in one place: the model of a SLAM run (`model.ply` of a
//! run folder), exports of the viewer, and clouds from other tools.
//!
//! The writer produces binary little-endian PLY with one `vertex` element of `float x y z`
//! and `uchar red green blue`. The reader takes binary (little- or big-endian) and ASCII
//! files with any scalar property types and extra elements (faces are skipped when they come
//! after the vertices); it needs `x`, `y` and `z`, and uses `red`, `green`, `blue` when present.
//! [`read_mesh_ply`] reads the faces too (the meshes of [`write_mesh_ply`] and other tools).

use std::io::Write;
use std::path::Path;

use glam::DVec3;

use super::IoError;

/// Colour given to points of a file without colour properties.
pub const DEFAULT_COLOUR: [u8; 3] = [200, 200, 200];

/// Writes `points` (world positions in metres, RGB colour) as binary little-endian PLY
/// (overwrites `path`). Positions are stored as 32-bit floats.
pub fn write_ply(path: &Path, points: &[(DVec3, [u8; 3])]) -> Result<(), IoError> {
    write_iter(path, points.len(), points.iter().copied())
}

/// Writes grey points (`(position, intensity)`, as the SLAM model holds them) as PLY with
/// red = green = blue = intensity.
pub fn write_ply_grey(path: &Path, points: &[(DVec3, u8)]) -> Result<(), IoError> {
    write_iter(
        path,
        points.len(),
        points.iter().map(|(p, g)| (*p, [*g; 3])),
    )
}

/// Writes a triangle mesh as binary little-endian PLY (overwrites `path`): a `vertex`
/// element with `float x y z` (metres), `float nx ny nz` (unit normals) and `uchar red green
/// blue`, and a `face` element of `uchar`-counted `int` index lists. `normals` and `colours`
/// must have one entry per vertex and triangle indices must be below the vertex count.
pub fn write_mesh_ply(
    path: &Path,
    vertices: &[[f32; 3]],
    normals: &[[f32; 3]],
    colours: &[[u8; 3]],
    triangles: &[[u32; 3]],
) -> Result<(), IoError> {
    let n = vertices.len();
    if normals.len() != n || colours.len() != n {
        return Err(IoError::Malformed {
            path: path.to_path_buf(),
            message: format!(
                "mesh has {n} vertices, {} normals and {} colours",
                normals.len(),
                colours.len()
            ),
        });
    }
    if let Some(t) = triangles
        .iter()
        .find(|t| t.iter().any(|&i| i as usize >= n))
    {
        return Err(IoError::Malformed {
            path: path.to_path_buf(),
            message: format!("triangle {t:?} indexes past {n} vertices"),
        });
    }
    let io = |e| IoError::file(path, e);
    let f = std::fs::File::create(path).map_err(io)?;
    let mut w = std::io::BufWriter::new(f);
    write!(
        w,
        "ply\nformat binary_little_endian 1.0\ncomment rgbid mesh\nelement vertex {n}\n\
         property float x\nproperty float y\nproperty float z\n\
         property float nx\nproperty float ny\nproperty float nz\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        triangles.len()
    )
    .map_err(io)?;
    let mut record = [0u8; 27];
    for ((p, q), c) in vertices.iter().zip(normals).zip(colours) {
        for (k, v) in p.iter().chain(q).enumerate() {
            record[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
        }
        record[24..].copy_from_slice(c);
        w.write_all(&record).map_err(io)?;
    }
    let mut face = [0u8; 13];
    face[0] = 3;
    for t in triangles {
        for (k, &i) in t.iter().enumerate() {
            face[1 + 4 * k..5 + 4 * k].copy_from_slice(&(i as i32).to_le_bytes());
        }
        w.write_all(&face).map_err(io)?;
    }
    w.flush().map_err(io)
}

fn write_iter(
    path: &Path,
    count: usize,
    points: impl Iterator<Item = (DVec3, [u8; 3])>,
) -> Result<(), IoError> {
    // Replaced atomically: a crash mid-write leaves the previous file, never half of one.
    super::write_atomic(path, |w| {
        write!(
            w,
            "ply\nformat binary_little_endian 1.0\ncomment rgbid model\nelement vertex {count}\n\
             property float x\nproperty float y\nproperty float z\n\
             property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
        )?;
        let mut record = [0u8; 15];
        for (p, c) in points {
            for (k, v) in [p.x as f32, p.y as f32, p.z as f32].iter().enumerate() {
                record[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
            }
            record[12..].copy_from_slice(&c);
            w.write_all(&record)?;
        }
        Ok(())
    })
}

/// Reads a PLY point cloud: positions and RGB colours ([`DEFAULT_COLOUR`] when the file has
/// none). Errors name the file and what is wrong.
pub fn read_ply(path: &Path) -> Result<Vec<(DVec3, [u8; 3])>, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::file(path, e))?;
    parse_ply(&bytes).map_err(|message| IoError::Malformed {
        path: path.to_path_buf(),
        message,
    })
}

/// Reads a PLY point cloud as grey points (the mean of red, green and blue).
pub fn read_ply_grey(path: &Path) -> Result<Vec<(DVec3, u8)>, IoError> {
    Ok(read_ply(path)?
        .into_iter()
        .map(|(p, c)| (p, grey(c)))
        .collect())
}

/// Grey value of an RGB colour: the rounded mean of the channels.
pub fn grey(c: [u8; 3]) -> u8 {
    ((u16::from(c[0]) + u16::from(c[1]) + u16::from(c[2]) + 1) / 3) as u8
}

#[derive(Clone, Copy, PartialEq)]
enum Format {
    Ascii,
    Little,
    Big,
}

#[derive(Clone, Copy)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(t: &str) -> Result<Self, String> {
        Ok(match t {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return Err(format!("unsupported property type {t}")),
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    /// The value at the start of `b` (at least `size()` bytes).
    fn read(self, b: &[u8], big: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                if big {
                    f64::from(<$t>::from_be_bytes(a))
                } else {
                    f64::from(<$t>::from_le_bytes(a))
                }
            }};
        }
        match self {
            Scalar::I8 => f64::from(b[0] as i8),
            Scalar::U8 => f64::from(b[0]),
            Scalar::I16 => get!(i16, 2),
            Scalar::U16 => get!(u16, 2),
            Scalar::I32 => get!(i32, 4),
            Scalar::U32 => get!(u32, 4),
            Scalar::F32 => get!(f32, 4),
            Scalar::F64 => get!(f64, 8),
        }
    }
}

/// One property of an element: a named scalar, or a named list with its count and item types
/// (lists are read only in faces; elsewhere they are skipped, in ASCII files).
enum Property {
    Scalar(String, Scalar),
    List(String, Scalar, Scalar),
}

struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

/// Parses the bytes of a PLY file (see [`read_ply`]); the error says what is wrong.
pub fn parse_ply(bytes: &[u8]) -> Result<Vec<(DVec3, [u8; 3])>, String> {
    let h = parse_header(bytes)?;
    finish_parse(bytes, h.header, h.body, h.body_start, h.format, &h.elements)
}

/// A parsed PLY header and where its body starts.
struct Header<'a> {
    header: &'a str,
    body: &'a [u8],
    body_start: usize,
    format: Option<Format>,
    elements: Vec<Element>,
}

fn parse_header(bytes: &[u8]) -> Result<Header<'_>, String> {
    const END: &[u8] = b"end_header";
    let Some(end) = bytes.windows(END.len()).position(|w| w == END) else {
        return Err("no end_header line".into());
    };
    let header = std::str::from_utf8(&bytes[..end]).map_err(|_| "header is not UTF-8")?;
    // The body starts after the end_header line's newline (\n or \r\n).
    let mut body_start = end + END.len();
    while body_start < bytes.len() && bytes[body_start] != b'\n' {
        body_start += 1;
    }
    let body = bytes.get(body_start + 1..).unwrap_or_default();
    let mut lines = header.lines();
    if lines.next().map(str::trim) != Some("ply") {
        return Err("not a PLY file (no 'ply' on the first line)".into());
    }
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    // The first line (`ply`) is line 1.
    for (i, l) in lines.enumerate() {
        header_line(l, &mut format, &mut elements).map_err(|e| format!("line {}: {e}", i + 2))?;
    }
    Ok(Header {
        header,
        body,
        body_start: body_start + 1,
        format,
        elements,
    })
}

/// Reads one header line after the first into `format` and `elements`.
fn header_line(
    l: &str,
    format: &mut Option<Format>,
    elements: &mut Vec<Element>,
) -> Result<(), String> {
    {
        let w: Vec<&str> = l.split_whitespace().collect();
        match w.as_slice() {
            ["format", "ascii", _] => *format = Some(Format::Ascii),
            ["format", "binary_little_endian", _] => *format = Some(Format::Little),
            ["format", "binary_big_endian", _] => *format = Some(Format::Big),
            ["format", f, ..] => return Err(format!("unsupported PLY format {f}")),
            ["element", name, n] => elements.push(Element {
                name: name.to_string(),
                count: n
                    .parse()
                    .map_err(|_| format!("element {name}: count '{n}' is not a number"))?,
                properties: Vec::new(),
            }),
            ["property", "list", c, t, name] => {
                let e = elements.last_mut().ok_or("property before any element")?;
                e.properties.push(Property::List(
                    name.to_string(),
                    Scalar::parse(c)?,
                    Scalar::parse(t)?,
                ));
            }
            ["property", t, name] => {
                let e = elements.last_mut().ok_or("property before any element")?;
                e.properties
                    .push(Property::Scalar(name.to_string(), Scalar::parse(t)?));
            }
            _ => {}
        }
    }
    Ok(())
}

/// The vertices of a PLY file whose header has been read: `body_offset` is the byte offset
/// of `body` in `bytes`.
fn finish_parse(
    bytes: &[u8],
    header: &str,
    body: &[u8],
    body_offset: usize,
    format: Option<Format>,
    elements: &[Element],
) -> Result<Vec<(DVec3, [u8; 3])>, String> {
    let format = format.ok_or("no format line")?;
    let Some(vi) = elements.iter().position(|e| e.name == "vertex") else {
        return Err("no vertex element".into());
    };
    // Elements before the vertices must be skipped, which needs fixed-size records.
    let mut skip_bytes = 0usize;
    let mut skip_lines = 0usize;
    for e in &elements[..vi] {
        skip_lines += e.count;
        for p in &e.properties {
            match p {
                Property::Scalar(_, s) => {
                    skip_bytes = skip_bytes.saturating_add(e.count.saturating_mul(s.size()))
                }
                Property::List(..) if format != Format::Ascii => {
                    return Err(format!(
                        "element {} with a list property comes before the vertices",
                        e.name
                    ))
                }
                Property::List(..) => {}
            }
        }
    }
    let vertex = &elements[vi];
    let mut names = Vec::new();
    let mut types = Vec::new();
    for p in &vertex.properties {
        match p {
            Property::Scalar(n, t) => {
                names.push(n.as_str());
                types.push(*t);
            }
            Property::List(..) => return Err("list property in the vertex element".into()),
        }
    }
    let find = |n: &str| names.iter().position(|&m| m == n);
    let (Some(ix), Some(iy), Some(iz)) = (find("x"), find("y"), find("z")) else {
        return Err("the vertex element needs x, y and z".into());
    };
    let rgb = match (find("red"), find("green"), find("blue")) {
        (Some(r), Some(g), Some(b)) => Some([r, g, b]),
        _ => None,
    };
    let count = vertex.count;
    let colour = |v: &dyn Fn(usize) -> f64| match rgb {
        Some(k) => k.map(|k| v(k).clamp(0.0, 255.0) as u8),
        None => DEFAULT_COLOUR,
    };
    // The declared count is only a claim: the reservation is bounded by what the body can
    // hold (a vertex takes at least two bytes in any format).
    let mut out = Vec::with_capacity(count.min(body.len() / 2 + 1));
    if format == Format::Ascii {
        let text = std::str::from_utf8(body).map_err(|_| "ASCII body is not UTF-8")?;
        // Body line `i` is file line `first_line + i` (the header ends with `end_header`).
        let first_line = header.lines().count() + 2;
        let mut rows = text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
            .skip(skip_lines);
        for n in 0..count {
            let (i, line) = rows.next().ok_or_else(|| {
                format!(
                    "line {}: file ends early: {n} of {count} vertices",
                    first_line + text.lines().count()
                )
            })?;
            let at = first_line + i;
            let v: Vec<f64> = line
                .split_whitespace()
                .map(str::parse::<f64>)
                .collect::<Result<_, _>>()
                .map_err(|e| format!("line {at}: vertex {n}: {e}"))?;
            if v.len() < names.len() {
                return Err(format!(
                    "line {at}: vertex {n}: {} values, expected {}",
                    v.len(),
                    names.len()
                ));
            }
            let p = DVec3::new(v[ix], v[iy], v[iz]);
            if !p.is_finite() {
                return Err(format!("line {at}: vertex {n}: {}", not_finite(p)));
            }
            out.push((p, colour(&|k| v[k])));
        }
    } else {
        let big = format == Format::Big;
        let mut offsets = Vec::with_capacity(types.len());
        let mut stride = 0usize;
        for t in &types {
            offsets.push(stride);
            stride += t.size();
        }
        let need = count.saturating_mul(stride).saturating_add(skip_bytes);
        if body.len() < need {
            return Err(format!(
                "file ends early at byte {}: {count} vertices of {stride} bytes need the body \
                 (from byte {body_offset}) to hold {need} bytes",
                bytes.len()
            ));
        }
        for (n, rec) in body[skip_bytes..]
            .chunks_exact(stride.max(1))
            .take(count)
            .enumerate()
        {
            let v = |k: usize| types[k].read(&rec[offsets[k]..], big);
            let p = DVec3::new(v(ix), v(iy), v(iz));
            if !p.is_finite() {
                return Err(format!(
                    "byte {}: vertex {n}: {}",
                    body_offset + skip_bytes + n * stride,
                    not_finite(p)
                ));
            }
            out.push((p, colour(&v)));
        }
    }
    Ok(out)
}

/// A triangle mesh read from PLY: coloured vertices and triangles.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlyMesh {
    /// Vertex positions (metres, the file's frame) and RGB colours ([`DEFAULT_COLOUR`] when
    /// the file has none).
    pub vertices: Vec<(DVec3, [u8; 3])>,
    /// Triangles as indices into `vertices`; faces of more than three corners are split into
    /// a fan of triangles, faces of fewer are left out.
    pub triangles: Vec<[u32; 3]>,
}

/// Reads a PLY triangle mesh: the vertices as [`read_ply`] reads them and the `face`
/// element's `vertex_indices` (or `vertex_index`) lists. A file without faces gives a mesh
/// without triangles. Errors name the file and what is wrong (e.g. an index past the
/// vertices, or a file that ends inside the faces).
pub fn read_mesh_ply(path: &Path) -> Result<PlyMesh, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::file(path, e))?;
    parse_mesh_ply(&bytes).map_err(|message| IoError::Malformed {
        path: path.to_path_buf(),
        message,
    })
}

/// Parses the bytes of a PLY mesh (see [`read_mesh_ply`]); the error says what is wrong.
pub fn parse_mesh_ply(bytes: &[u8]) -> Result<PlyMesh, String> {
    let vertices = parse_ply(bytes)?;
    let h = parse_header(bytes)?;
    let format = h.format.ok_or("no format line")?;
    let n = vertices.len();
    let Some(fi) = h.elements.iter().position(|e| e.name == "face") else {
        return Ok(PlyMesh {
            vertices,
            triangles: Vec::new(),
        });
    };
    let Some(vi) = h.elements.iter().position(|e| e.name == "vertex") else {
        return Err("no vertex element".into());
    };
    if fi < vi {
        return Err("the face element comes before the vertices".into());
    }
    let face = &h.elements[fi];
    let target = face
        .properties
        .iter()
        .position(|p| {
            matches!(p, Property::List(name, ..) if name == "vertex_indices" || name == "vertex_index")
        })
        .ok_or("the face element has no vertex_indices list")?;
    // Faces claim at least one byte each: bound the reservation by the body.
    let mut triangles = Vec::with_capacity(face.count.min(h.body.len()));
    // `at` says where the face is (a line or byte), for errors.
    let emit = |at: &str, f: usize, corners: &[f64], triangles: &mut Vec<[u32; 3]>| {
        let mut idx = Vec::with_capacity(corners.len());
        for &c in corners {
            if !(c >= 0.0 && c < n as f64 && c.fract() == 0.0) {
                return Err(format!(
                    "{at}: face {f}: vertex index {c} is not one of the {n} vertices"
                ));
            }
            idx.push(c as u32);
        }
        for k in 2..idx.len() {
            triangles.push([idx[0], idx[k - 1], idx[k]]);
        }
        Ok(())
    };
    let mut corners: Vec<f64> = Vec::new();
    if format == Format::Ascii {
        let text = std::str::from_utf8(h.body).map_err(|_| "ASCII body is not UTF-8")?;
        let before: usize = h.elements[..fi].iter().map(|e| e.count).sum();
        // Body line `i` is file line `first_line + i` (the header ends with `end_header`).
        let first_line = h.header.lines().count() + 2;
        let mut rows = text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
            .skip(before);
        for f in 0..face.count {
            let (i, line) = rows.next().ok_or_else(|| {
                format!(
                    "line {}: file ends early: {f} of {} faces",
                    first_line + text.lines().count(),
                    face.count
                )
            })?;
            let at = format!("line {}", first_line + i);
            let mut values = line.split_whitespace().map(str::parse::<f64>);
            let mut next = || -> Result<f64, String> {
                values
                    .next()
                    .ok_or_else(|| format!("{at}: face {f}: too few values"))?
                    .map_err(|e| format!("{at}: face {f}: {e}"))
            };
            for (k, p) in face.properties.iter().enumerate() {
                match p {
                    Property::Scalar(..) => {
                        next()?;
                    }
                    Property::List(..) => {
                        let count = next()?;
                        if !(0.0..=1e6).contains(&count) {
                            return Err(format!("{at}: face {f}: list of {count} items"));
                        }
                        corners.clear();
                        for _ in 0..count as usize {
                            corners.push(next()?);
                        }
                        if k == target {
                            emit(&at, f, &corners, &mut triangles)?;
                        }
                    }
                }
            }
        }
    } else {
        let big = format == Format::Big;
        // Everything before the faces has fixed-size records (lists there are refused).
        let mut pos = 0usize;
        for e in &h.elements[..fi] {
            for p in &e.properties {
                match p {
                    Property::Scalar(_, s) => {
                        pos = pos.saturating_add(e.count.saturating_mul(s.size()))
                    }
                    Property::List(..) => {
                        return Err(format!(
                            "element {} with a list property comes before the faces",
                            e.name
                        ))
                    }
                }
            }
        }
        let body = h.body;
        let ends_early = |f: usize| {
            format!(
                "file ends early at byte {}: {f} of {} faces",
                bytes.len(),
                face.count
            )
        };
        let read = |s: Scalar, pos: &mut usize, f: usize| -> Result<f64, String> {
            let end = pos.checked_add(s.size()).ok_or_else(|| ends_early(f))?;
            let b = body.get(*pos..end).ok_or_else(|| ends_early(f))?;
            *pos = end;
            Ok(s.read(b, big))
        };
        for f in 0..face.count {
            let at = format!("byte {}", h.body_start.saturating_add(pos));
            for (k, p) in face.properties.iter().enumerate() {
                match p {
                    Property::Scalar(_, s) => {
                        read(*s, &mut pos, f)?;
                    }
                    Property::List(_, c, t) => {
                        let count = read(*c, &mut pos, f)?;
                        if !(0.0..=1e6).contains(&count) {
                            return Err(format!("{at}: face {f}: list of {count} items"));
                        }
                        corners.clear();
                        for _ in 0..count as usize {
                            corners.push(read(*t, &mut pos, f)?);
                        }
                        if k == target {
                            emit(&at, f, &corners, &mut triangles)?;
                        }
                    }
                }
            }
        }
    }
    Ok(PlyMesh {
        vertices,
        triangles,
    })
}

/// What is wrong with a vertex position that is not finite.
fn not_finite(p: DVec3) -> String {
    format!(
        "position ({}, {}, {}) is not finite (NaN or infinite coordinates are no point)",
        p.x, p.y, p.z
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_colour_and_grey() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        let pts = vec![
            (DVec3::new(1.0, -2.0, 3.5), [7u8, 8, 9]),
            (DVec3::new(0.25, 0.5, 0.75), [200, 100, 0]),
        ];
        write_ply(&p, &pts).unwrap();
        assert_eq!(read_ply(&p).unwrap(), pts);
        let grey_pts = vec![(DVec3::new(1.0, 2.0, 3.0), 77u8)];
        write_ply_grey(&p, &grey_pts).unwrap();
        assert_eq!(read_ply_grey(&p).unwrap(), grey_pts);
        write_ply(&p, &[]).unwrap();
        assert!(read_ply(&p).unwrap().is_empty());
    }

    #[test]
    fn errors_say_where() {
        let e = parse_ply(b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n").unwrap_err();
        assert!(e.contains("at byte 124"), "{e}");
        let e = parse_ply(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n1 x 3\n").unwrap_err();
        assert!(e.starts_with("line 9: vertex 1"), "{e}");
        let e = parse_ply(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n").unwrap_err();
        assert!(e.starts_with("line 9: file ends early"), "{e}");
        let e =
            parse_ply(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty blob x\nend_header\n")
                .unwrap_err();
        assert!(e.starts_with("line 4: unsupported property type"), "{e}");
    }

    #[test]
    fn non_finite_positions_are_errors_that_say_where() {
        let head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
        for bad in ["nan", "inf", "-inf", "1e999"] {
            let text = format!("{head}1 2 3\n4 5 6\n7 {bad} 9\n");
            let e = parse_ply(text.as_bytes()).unwrap_err();
            assert!(e.starts_with("line 10: vertex 2: position"), "{e}");
            assert!(e.contains("not finite"), "{e}");
        }
        // Binary: the vertex's byte offset (header 124 bytes, 12 bytes per vertex).
        let mut b = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n".to_vec();
        let header = b.len();
        for v in [1.0f32, 2.0, 3.0, 4.0, f32::NAN, 6.0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        let e = parse_ply(&b).unwrap_err();
        assert!(
            e.starts_with(&format!("byte {}: vertex 1:", header + 12)),
            "{e}"
        );
        // Through the file reader, the error names the file.
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("cloud.ply");
        std::fs::write(&p, &b).unwrap();
        let e = read_ply(&p).unwrap_err().to_string();
        assert!(e.contains("cloud.ply") && e.contains("vertex 1"), "{e}");
    }

    #[test]
    fn other_layouts() {
        // ASCII with a face element after the vertices and no colour.
        let ok = parse_ply(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n1 2 3\n3 0 0 0\n").unwrap();
        assert_eq!(ok, vec![(DVec3::new(1.0, 2.0, 3.0), DEFAULT_COLOUR)]);
        // Big-endian doubles with colour, CRLF header.
        let mut b = b"ply\r\nformat binary_big_endian 1.0\r\nelement vertex 1\r\nproperty double x\r\nproperty double y\r\nproperty double z\r\nproperty uchar red\r\nproperty uchar green\r\nproperty uchar blue\r\nend_header\r\n".to_vec();
        for v in [1.5f64, -2.0, 4.0] {
            b.extend_from_slice(&v.to_be_bytes());
        }
        b.extend_from_slice(&[1, 2, 3]);
        assert_eq!(
            parse_ply(&b).unwrap(),
            vec![(DVec3::new(1.5, -2.0, 4.0), [1, 2, 3])]
        );
    }

    #[test]
    fn errors_instead_of_panics() {
        assert!(parse_ply(b"").is_err());
        let short = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n\0\0";
        assert!(parse_ply(short).unwrap_err().contains("ends early"));
        let no_y = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n";
        assert!(parse_ply(no_y).unwrap_err().contains("x, y and z"));
        let bad = b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n";
        assert!(parse_ply(bad).unwrap_err().contains("1 of 2"));
        let dir = tempfile::tempdir().unwrap();
        let e = read_ply(&dir.path().join("none.ply")).unwrap_err();
        assert!(e.to_string().contains("none.ply"), "{e}");
    }

    #[test]
    fn mesh_round_trip_and_other_layouts() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("mesh.ply");
        let vertices = [
            [0.0f32, 0.0, 1.0],
            [1.0, 0.0, 1.0],
            [0.0, 1.0, 1.0],
            [1.0, 1.0, 1.0],
        ];
        let normals = [[0.0f32, 0.0, -1.0]; 4];
        let colours = [[255u8, 0, 0], [0, 255, 0], [0, 0, 255], [9, 9, 9]];
        let triangles = [[0u32, 1, 2], [2, 1, 3]];
        write_mesh_ply(&p, &vertices, &normals, &colours, &triangles).unwrap();
        let m = read_mesh_ply(&p).unwrap();
        assert_eq!(m.triangles, triangles);
        assert_eq!(m.vertices.len(), 4);
        assert_eq!(m.vertices[3], (DVec3::new(1.0, 1.0, 1.0), [9, 9, 9]));
        // ASCII: a quad becomes a fan of two triangles; an extra face property is skipped.
        let quad = parse_mesh_ply(b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty uchar flags\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n7 4 0 1 2 3\n").unwrap();
        assert_eq!(quad.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        // A point cloud is a mesh without triangles.
        let cloud = dir.path().join("cloud.ply");
        write_ply(&cloud, &[(DVec3::ONE, [1, 2, 3])]).unwrap();
        assert!(read_mesh_ply(&cloud).unwrap().triangles.is_empty());
    }

    #[test]
    fn mesh_errors_say_what_is_wrong() {
        let head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n";
        let e = parse_mesh_ply(format!("{head}3 0 1 2\n3 0 1 3\n").as_bytes()).unwrap_err();
        assert!(e.contains("face 1: vertex index 3"), "{e}");
        let e = parse_mesh_ply(format!("{head}3 0 1 2\n").as_bytes()).unwrap_err();
        assert!(e.contains("1 of 2 faces"), "{e}");
        // Binary, cut inside the second face.
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        let v = [[0.0f32; 3]; 3];
        write_mesh_ply(&p, &v, &v, &[[0u8; 3]; 3], &[[0, 1, 2], [2, 1, 0]]).unwrap();
        let mut b = std::fs::read(&p).unwrap();
        b.truncate(b.len() - 5);
        let e = parse_mesh_ply(&b).unwrap_err();
        assert!(
            e.contains("ends early") && e.contains("1 of 2 faces"),
            "{e}"
        );
        std::fs::write(&p, &b).unwrap();
        assert!(read_mesh_ply(&p).unwrap_err().to_string().contains("m.ply"));
    }
}
