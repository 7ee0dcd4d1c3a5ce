//! Saved maps: keyframes (compact images), ORB features with their mask flags (the BoW
//! histograms are recomputed from them with the vocabulary), optimised poses and the graph.
//!
//! File layout, version 3 (little endian): `b"RGBIDMAP"`, `u32` version, `u64` length of a
//! JSON header, `u32` CRC-32 of the header, the header, then per keyframe `u64` block length,
//! `u32` CRC-32 of the block and the block, then `b"RGBIDEND"`. A keyframe block holds the
//! intensity (u8), inverse depth (f16), weights (u8), the keyframe's RGB colour (3 u8 per
//! pixel, only when its header entry says `"colour": true`), then its features. Version 2 (the
//! same without colour) and version 1 (no lengths or checksums either) still load, without
//! colour.
//!
//! Loading is bounded and checked: the magic is read first, the file is read up to its own
//! length, every declared size is compared with the bytes left before anything is allocated,
//! each block's checksum is verified, and every value is validated (finite, keyframes of the
//! camera's size, key points inside the image, edges between stored keyframes). Errors give
//! the byte offset of what is wrong.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use glam::{DQuat, DVec2, DVec3};
use half::f16;

use super::backend::Backend;
use super::keyframe::{Keyframe, KeyframeLink};
use super::SlamError;
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::image::ColourImage;
use crate::place::{Descriptor, KeyPoint, OrbFeatures};

/// Current map file version (2: a length and a CRC-32 per block; 3: keyframe colour).
pub const MAP_VERSION: u32 = 3;
/// The oldest map version this build still reads.
pub const MAP_VERSION_OLDEST: u32 = 1;
const MAGIC: &[u8; 8] = b"RGBIDMAP";
const END: &[u8; 8] = b"RGBIDEND";

/// Map file errors.
#[derive(Debug, thiserror::Error)]
pub enum MapError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// File.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// Not an rgbid map.
    #[error("{0}: not an rgbid map file (bad magic)")]
    Foreign(PathBuf),
    /// Written by another version.
    #[error("{path}: map version {found}, this build reads versions {MAP_VERSION_OLDEST} to {MAP_VERSION}; rebuild the map with this build (`rgbid slam ... --map-out`)")]
    Version {
        /// File.
        path: PathBuf,
        /// Version found.
        found: u32,
    },
    /// The file ends early, a checksum fails or a value is invalid.
    #[error("{path}: truncated or corrupt map at byte {offset}: {what}")]
    Corrupt {
        /// File.
        path: PathBuf,
        /// Byte offset of the block or value that is wrong.
        offset: u64,
        /// What was wrong.
        what: String,
    },
    /// The vocabulary differs from the one the map was made with.
    #[error("the map was built with a vocabulary of {map} words, this one has {current}")]
    Vocabulary {
        /// Words of the map's vocabulary.
        map: usize,
        /// Words of the current vocabulary.
        current: usize,
    },
}

/// One graph edge of the map (keyframe ids, `from_from_to`, 6x6 information row-major).
#[derive(Clone, Debug, PartialEq)]
pub struct MapEdge {
    /// Older keyframe.
    pub from: usize,
    /// Newer keyframe.
    pub to: usize,
    /// `from_from_to`.
    pub measurement: Se3,
    /// Information matrix (row-major 6x6, twist `[v; w]`).
    pub information: Vec<f64>,
}

/// A map that can be saved and loaded in a later session.
#[derive(Clone, Debug)]
pub struct Map {
    /// Camera of the keyframes.
    pub camera: PinholeCamera,
    /// Sessions that built the map.
    pub sessions: u32,
    /// Words of the vocabulary the features were described with.
    pub vocabulary_words: usize,
    /// Keyframes (their `world_from_keyframe` is the optimised pose).
    pub keyframes: Vec<Keyframe>,
    /// ORB features per keyframe (lifted to 3D).
    pub features: Vec<OrbFeatures>,
    /// Per keyframe, per mask, a flag per feature (inside the mask).
    pub mask_flags: Vec<Vec<Vec<bool>>>,
    /// Graph edges.
    pub edges: Vec<MapEdge>,
}

#[derive(serde::Serialize, serde::Deserialize)]
struct Header {
    camera: PinholeCamera,
    sessions: u32,
    vocabulary_words: usize,
    keyframes: Vec<KeyframeHeader>,
    edges: Vec<(usize, usize, [f64; 7], Vec<f64>)>,
}

#[derive(serde::Serialize, serde::Deserialize)]
struct KeyframeHeader {
    id: usize,
    frame_index: usize,
    session: u32,
    timestamp: f64,
    width: usize,
    height: usize,
    world_from_keyframe: [f64; 7],
    features: usize,
    masks: usize,
    /// The block holds the keyframe's RGB colour (version 3 on; absent in older files).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    colour: bool,
}

fn pose_to(p: &Se3) -> [f64; 7] {
    let t = p.translation;
    let q = p.rotation;
    [t.x, t.y, t.z, q.x, q.y, q.z, q.w]
}

fn pose_from(a: &[f64; 7]) -> Option<Se3> {
    let q = DQuat::from_xyzw(a[3], a[4], a[5], a[6]);
    if !a.iter().all(|v| v.is_finite()) || (q.length() - 1.0).abs() > 1e-3 {
        return None;
    }
    Some(Se3::new(q.normalize(), DVec3::new(a[0], a[1], a[2])))
}

impl Map {
    /// Moves the back-end's keyframes into a map (with their optimised poses).
    pub(crate) fn from_backend(back: &mut Backend, sessions: u32) -> Map {
        let poses = back.keyframe_poses();
        let mut keyframes = std::mem::take(&mut back.keyframes);
        for (k, p) in keyframes.iter_mut().zip(poses.iter()) {
            k.world_from_keyframe = *p;
        }
        let features = (0..keyframes.len())
            .map(|i| {
                back.detector
                    .keyframe(i)
                    .map(|d| d.features.clone())
                    .unwrap_or_default()
            })
            .collect();
        let g = &back.graph;
        let edges = g
            .edges
            .iter()
            .map(|e| MapEdge {
                from: g.ids[e.from] as usize,
                to: g.ids[e.to] as usize,
                measurement: e.measurement,
                information: e.information.clone(),
            })
            .collect();
        Map {
            camera: back.camera,
            sessions,
            vocabulary_words: back.detector.vocabulary().num_words(),
            keyframes,
            features,
            mask_flags: std::mem::take(&mut back.mask_flags),
            edges,
        }
    }

    /// Puts the map into a fresh back-end: keyframes described from the stored features,
    /// poses fixed, edges restored.
    pub(crate) fn load_into(self, back: &mut Backend) -> Result<(), SlamError> {
        let words = back.detector.vocabulary().num_words();
        if words != self.vocabulary_words {
            return Err(MapError::Vocabulary {
                map: self.vocabulary_words,
                current: words,
            }
            .into());
        }
        for ((kf, features), flags) in self
            .keyframes
            .into_iter()
            .zip(self.features)
            .zip(self.mask_flags)
        {
            let desc = back.detector.describe_features(features, &flags);
            let pose = kf.world_from_keyframe;
            back.add_map_keyframe(kf, desc, flags, pose)?;
        }
        for e in self.edges {
            back.graph
                .add_edge(e.from as i64, e.to as i64, e.measurement, e.information)?;
        }
        Ok(())
    }

    /// Bytes of the map per keyframe (images + features), averaged.
    pub fn bytes_per_keyframe(&self) -> f64 {
        if self.keyframes.is_empty() {
            return 0.0;
        }
        let total: usize = self
            .keyframes
            .iter()
            .zip(self.features.iter())
            .map(|(k, f)| k.image_bytes() + f.len() * (32 + 16 + 13 + 25))
            .sum();
        total as f64 / self.keyframes.len() as f64
    }

    /// Writes the map to `path`.
    pub fn save(&self, path: &Path) -> Result<(), MapError> {
        let io = |source| MapError::Io {
            path: path.to_path_buf(),
            source,
        };
        let header = Header {
            camera: self.camera,
            sessions: self.sessions,
            vocabulary_words: self.vocabulary_words,
            keyframes: self
                .keyframes
                .iter()
                .zip(self.features.iter())
                .zip(self.mask_flags.iter())
                .map(|((k, f), m)| KeyframeHeader {
                    id: k.id,
                    frame_index: k.frame_index,
                    session: k.session,
                    timestamp: k.timestamp,
                    width: k.width,
                    height: k.height,
                    world_from_keyframe: pose_to(&k.world_from_keyframe),
                    features: f.len(),
                    masks: m.len(),
                    colour: k.colour.is_some(),
                })
                .collect(),
            edges: self
                .edges
                .iter()
                .map(|e| (e.from, e.to, pose_to(&e.measurement), e.information.clone()))
                .collect(),
        };
        let json = serde_json::to_vec(&header).map_err(|e| io(std::io::Error::other(e)))?;
        // Replaced atomically: a crash leaves the previous map, never half of one.
        crate::io::write_atomic(path, |w| {
            w.write_all(MAGIC)?;
            w.write_all(&MAP_VERSION.to_le_bytes())?;
            w.write_all(&(json.len() as u64).to_le_bytes())?;
            w.write_all(&crc32fast::hash(&json).to_le_bytes())?;
            w.write_all(&json)?;
            for ((k, f), masks) in self
                .keyframes
                .iter()
                .zip(self.features.iter())
                .zip(self.mask_flags.iter())
            {
                let b = keyframe_block(k, f, masks);
                w.write_all(&(b.len() as u64).to_le_bytes())?;
                w.write_all(&crc32fast::hash(&b).to_le_bytes())?;
                w.write_all(&b)?;
            }
            w.write_all(END)
        })
        .map_err(|e| match e {
            crate::io::IoError::File { source, .. } => io(source),
            other => io(std::io::Error::other(other.to_string())),
        })
    }

    /// Reads a map written by [`Map::save`] (this version, or versions 1 and 2 without
    /// keyframe colour).
    pub fn load(path: &Path) -> Result<Map, MapError> {
        let bytes = read_bounded(path)?;
        parse_map(&bytes, path)
    }
}

/// A keyframe's binary block: intensity, inverse depth (f16), weights, colour (RGB, when the
/// keyframe has it), then per feature its key point, descriptor, optional 3D point and mask
/// flags.
fn keyframe_block(k: &Keyframe, f: &OrbFeatures, masks: &[Vec<bool>]) -> Vec<u8> {
    let mut b = Vec::with_capacity(k.image_bytes() + f.len() * 90);
    b.extend_from_slice(&k.intensity);
    for r in &k.inverse_depth {
        b.extend_from_slice(&r.to_bits().to_le_bytes());
    }
    b.extend_from_slice(&k.weight);
    if let Some(c) = &k.colour {
        b.extend_from_slice(c.rgb());
    }
    for i in 0..f.len() {
        let kp = &f.keypoints[i];
        b.extend_from_slice(&kp.uv.x.to_le_bytes());
        b.extend_from_slice(&kp.uv.y.to_le_bytes());
        b.push(kp.level);
        b.extend_from_slice(&kp.angle.to_le_bytes());
        b.extend_from_slice(&kp.score.to_le_bytes());
        b.extend_from_slice(&kp.size.to_le_bytes());
        b.extend_from_slice(&f.descriptors[i].to_bytes());
        match f.points.get(i).copied().flatten() {
            Some(p) => {
                b.push(1);
                for v in [p.x, p.y, p.z] {
                    b.extend_from_slice(&v.to_le_bytes());
                }
            }
            None => b.push(0),
        }
        for m in masks {
            b.push(u8::from(m.get(i).copied().unwrap_or(false)));
        }
    }
    b
}

/// Bytes of one feature without its optional point: u, v, level, angle, score, size,
/// descriptor, point flag (mask flags come on top).
const FEATURE_BYTES: usize = 8 + 8 + 1 + 4 + 4 + 4 + 32 + 1;
/// Largest distance of a stored 3D point from its keyframe, metres: anything beyond is
/// corruption, not a measurement.
const MAX_POINT_DISTANCE_M: f64 = 1e4;

/// Reads a map file whole, bounded by its own length; a file that does not start with the
/// magic is refused after 8 bytes (so `/dev/zero` or a wrong file is not read on).
fn read_bounded(path: &Path) -> Result<Vec<u8>, MapError> {
    let io = |source| MapError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let mut magic = [0u8; 8];
    let mut got = 0;
    while got < magic.len() {
        match file.read(&mut magic[got..]).map_err(io)? {
            0 => break,
            n => got += n,
        }
    }
    if got < magic.len() || &magic != MAGIC {
        return Err(MapError::Foreign(path.to_path_buf()));
    }
    let meta = file.metadata().map_err(io)?;
    if !meta.is_file() {
        return Err(MapError::Corrupt {
            path: path.to_path_buf(),
            offset: 0,
            what: "not a regular file".into(),
        });
    }
    let mut bytes = Vec::with_capacity(usize::try_from(meta.len()).unwrap_or(0).min(1 << 34));
    bytes.extend_from_slice(&magic);
    file.take(meta.len().saturating_sub(8))
        .read_to_end(&mut bytes)
        .map_err(io)?;
    Ok(bytes)
}

/// Parses and validates the bytes of a map file; `path` names it in errors.
fn parse_map(bytes: &[u8], path: &Path) -> Result<Map, MapError> {
    let p = path.to_path_buf();
    let corrupt = |offset: usize, what: String| MapError::Corrupt {
        path: p.clone(),
        offset: offset as u64,
        what,
    };
    if bytes.len() < 8 || &bytes[..8] != MAGIC {
        return Err(MapError::Foreign(p.clone()));
    }
    let mut r = Reader { b: bytes, pos: 8 };
    let version = r
        .u32()
        .ok_or_else(|| corrupt(8, "file ends in the version".into()))?;
    if !(MAP_VERSION_OLDEST..=MAP_VERSION).contains(&version) {
        return Err(MapError::Version {
            path: p.clone(),
            found: version,
        });
    }
    let checksums = version >= 2;
    let at = r.pos;
    let len = r
        .u64()
        .ok_or_else(|| corrupt(at, "file ends in the header length".into()))?;
    let header_crc = if checksums {
        Some(
            r.u32()
                .ok_or_else(|| corrupt(r.pos, "file ends in the header checksum".into()))?,
        )
    } else {
        None
    };
    let at = r.pos;
    let json = usize::try_from(len)
        .ok()
        .and_then(|n| r.take(n))
        .ok_or_else(|| {
            corrupt(
                at,
                format!(
                    "header of {len} bytes declared, {} left in the file",
                    r.remaining()
                ),
            )
        })?;
    if let Some(crc) = header_crc {
        if crc32fast::hash(json) != crc {
            return Err(corrupt(at, "header checksum mismatch".into()));
        }
    }
    let header: Header =
        serde_json::from_slice(json).map_err(|e| corrupt(at, format!("header: {e}")))?;
    header
        .camera
        .validate()
        .map_err(|e| corrupt(at, format!("camera: {e}")))?;
    let (cam_w, cam_h) = (header.camera.width as usize, header.camera.height as usize);
    let px = cam_w * cam_h;
    let mut keyframes = Vec::new();
    let mut features = Vec::new();
    let mut mask_flags = Vec::new();
    for (n, kh) in header.keyframes.iter().enumerate() {
        let block_at = r.pos;
        let bad = |what: String| corrupt(block_at, format!("keyframe {n}: {what}"));
        if kh.id != n {
            return Err(bad(format!("id {} out of order", kh.id)));
        }
        if (kh.width, kh.height) != (cam_w, cam_h) {
            return Err(bad(format!(
                "{}x{} pixels but the map's camera is {cam_w}x{cam_h}",
                kh.width, kh.height
            )));
        }
        if kh.masks > 16 {
            return Err(bad(format!("{} masks (at most 16)", kh.masks)));
        }
        if !kh.timestamp.is_finite() {
            return Err(bad("time stamp not finite".into()));
        }
        if kh.colour && version < 3 {
            return Err(bad(format!("colour in a version {version} map")));
        }
        let colour_bytes = if kh.colour { 3 * px } else { 0 };
        // The smallest block these sizes need, checked against the bytes left before
        // anything is allocated.
        let need = kh
            .features
            .checked_mul(FEATURE_BYTES + kh.masks)
            .and_then(|f| f.checked_add(4 * px + colour_bytes));
        let mut block = if checksums {
            let declared = r
                .u64()
                .ok_or_else(|| bad("file ends in the block length".into()))?;
            let crc = r
                .u32()
                .ok_or_else(|| bad("file ends in the block checksum".into()))?;
            let body_at = r.pos;
            let body = usize::try_from(declared)
                .ok()
                .and_then(|n| r.take(n))
                .ok_or_else(|| {
                    bad(format!(
                        "block of {declared} bytes declared, {} left in the file",
                        r.remaining()
                    ))
                })?;
            if crc32fast::hash(body) != crc {
                return Err(bad("block checksum mismatch".into()));
            }
            if need.is_none_or(|need| need > body.len()) {
                return Err(bad(format!(
                    "{} features need more than the block's {} bytes",
                    kh.features,
                    body.len()
                )));
            }
            Reader {
                b: &bytes[..body_at + body.len()],
                pos: body_at,
            }
        } else {
            if need.is_none_or(|need| need > r.remaining()) {
                return Err(bad(format!(
                    "{} features need more than the {} bytes left",
                    kh.features,
                    r.remaining()
                )));
            }
            Reader {
                b: bytes,
                pos: r.pos,
            }
        };
        let short = |b: &Reader| corrupt(b.pos, format!("keyframe {n}: block ends early"));
        let intensity = block.take(px).ok_or_else(|| short(&block))?.to_vec();
        let rho_at = block.pos;
        let rho_bytes = block.take(2 * px).ok_or_else(|| short(&block))?;
        let inverse_depth: Vec<f16> = rho_bytes
            .chunks_exact(2)
            .map(|c| f16::from_bits(u16::from_le_bytes([c[0], c[1]])))
            .collect();
        if let Some(k) = inverse_depth
            .iter()
            .position(|r| !(r.is_finite() && r.to_f32() >= 0.0))
        {
            return Err(corrupt(
                rho_at + 2 * k,
                format!(
                    "keyframe {n}: inverse depth {} at pixel {k} (must be finite and >= 0)",
                    inverse_depth[k]
                ),
            ));
        }
        let weight = block.take(px).ok_or_else(|| short(&block))?.to_vec();
        let colour = if kh.colour {
            let rgb = block.take(colour_bytes).ok_or_else(|| short(&block))?;
            Some(
                ColourImage::from_rgb(cam_w, cam_h, rgb.to_vec())
                    .map_err(|e| bad(format!("colour: {e}")))?,
            )
        } else {
            None
        };
        let mut f = OrbFeatures {
            width: kh.width,
            height: kh.height,
            ..Default::default()
        };
        let mut flags = vec![Vec::with_capacity(kh.features); kh.masks];
        for i in 0..kh.features {
            let feature_at = block.pos;
            let bad_feature =
                |what: &str| corrupt(feature_at, format!("keyframe {n} feature {i}: {what}"));
            let u = block.f64().ok_or_else(|| short(&block))?;
            let v = block.f64().ok_or_else(|| short(&block))?;
            let level = block.take(1).ok_or_else(|| short(&block))?[0];
            let angle = block.f32().ok_or_else(|| short(&block))?;
            let score = block.f32().ok_or_else(|| short(&block))?;
            let size = block.f32().ok_or_else(|| short(&block))?;
            let inside = u.is_finite()
                && v.is_finite()
                && (-0.5..cam_w as f64).contains(&u)
                && (-0.5..cam_h as f64).contains(&v);
            if !inside {
                return Err(bad_feature(&format!(
                    "key point ({u}, {v}) outside the image"
                )));
            }
            if !(angle.is_finite() && score.is_finite() && size.is_finite() && size >= 0.0) {
                return Err(bad_feature("angle, score or size not finite"));
            }
            let d = block.take(32).ok_or_else(|| short(&block))?;
            let mut db = [0u8; 32];
            db.copy_from_slice(d);
            let point = match block.take(1).ok_or_else(|| short(&block))?[0] {
                0 => None,
                1 => {
                    let x = block.f64().ok_or_else(|| short(&block))?;
                    let y = block.f64().ok_or_else(|| short(&block))?;
                    let z = block.f64().ok_or_else(|| short(&block))?;
                    let q = DVec3::new(x, y, z);
                    if !(q.is_finite() && q.length() <= MAX_POINT_DISTANCE_M) {
                        return Err(bad_feature(&format!(
                            "3D point {q} not finite or farther than {MAX_POINT_DISTANCE_M} m"
                        )));
                    }
                    Some(q)
                }
                other => return Err(bad_feature(&format!("point flag {other} (0 or 1)"))),
            };
            for fl in flags.iter_mut() {
                fl.push(block.take(1).ok_or_else(|| short(&block))?[0] != 0);
            }
            f.keypoints.push(KeyPoint {
                uv: DVec2::new(u, v),
                level,
                angle,
                score,
                size,
            });
            f.descriptors.push(Descriptor::from_bytes(&db));
            f.points.push(point);
        }
        if checksums {
            if block.pos != block.b.len() {
                return Err(corrupt(
                    block.pos,
                    format!(
                        "keyframe {n}: {} bytes after its features",
                        block.b.len() - block.pos
                    ),
                ));
            }
        } else {
            r.pos = block.pos;
        }
        let world_from_keyframe = pose_from(&kh.world_from_keyframe)
            .ok_or_else(|| bad("pose not finite or not a unit quaternion".into()))?;
        keyframes.push(Keyframe {
            id: kh.id,
            frame_index: kh.frame_index,
            session: kh.session,
            timestamp: kh.timestamp,
            width: kh.width,
            height: kh.height,
            intensity,
            inverse_depth,
            weight,
            colour,
            world_from_keyframe,
            link: KeyframeLink::First,
        });
        features.push(f);
        mask_flags.push(flags);
    }
    let end_at = r.pos;
    if r.take(8) != Some(END.as_slice()) || r.pos != bytes.len() {
        return Err(corrupt(end_at, "no end marker where the blocks end".into()));
    }
    let mut edges = Vec::new();
    for (k, (from, to, m, info)) in header.edges.into_iter().enumerate() {
        let bad = |what: &str| corrupt(at, format!("header: edge {k}: {what}"));
        let measurement =
            pose_from(&m).ok_or_else(|| bad("pose not finite or not a unit quaternion"))?;
        if from >= keyframes.len() || to >= keyframes.len() {
            return Err(bad(&format!(
                "keyframes {from} -> {to}, the map has {}",
                keyframes.len()
            )));
        }
        if info.len() != 36 || !info.iter().all(|v| v.is_finite()) {
            return Err(bad("information is not 36 finite numbers"));
        }
        edges.push(MapEdge {
            from,
            to,
            measurement,
            information: info,
        });
    }
    Ok(Map {
        camera: header.camera,
        sessions: header.sessions,
        vocabulary_words: header.vocabulary_words,
        keyframes,
        features,
        mask_flags,
        edges,
    })
}

struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn remaining(&self) -> usize {
        self.b.len().saturating_sub(self.pos)
    }
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.pos.checked_add(n)?;
        let s = self.b.get(self.pos..end)?;
        self.pos = end;
        Some(s)
    }
    fn u32(&mut self) -> Option<u32> {
        Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?))
    }
    fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }
    fn f32(&mut self) -> Option<f32> {
        Some(f32::from_le_bytes(self.take(4)?.try_into().ok()?))
    }
    fn f64(&mut self) -> Option<f64> {
        Some(f64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: usize = 8;
    const H: usize = 6;

    fn small_map() -> Map {
        let camera = PinholeCamera::new(10.0, 10.0, 3.5, 2.5, W as u32, H as u32);
        let keyframes = (0..2)
            .map(|id| Keyframe {
                id,
                frame_index: 3 * id,
                session: 0,
                timestamp: 0.1 * id as f64,
                width: W,
                height: H,
                intensity: (0..W * H).map(|i| i as u8).collect(),
                inverse_depth: (0..W * H)
                    .map(|i| f16::from_f32(0.5 + i as f32 * 0.01))
                    .collect(),
                weight: vec![3; W * H],
                // Keyframe 1 has colour, keyframe 0 not (a map extended by a colour session).
                colour: (id == 1).then(|| {
                    ColourImage::from_rgb(W, H, (0..3 * W * H).map(|i| (7 * i) as u8).collect())
                        .unwrap()
                }),
                world_from_keyframe: Se3::new(DQuat::IDENTITY, DVec3::new(id as f64, 0.0, 0.0)),
                link: KeyframeLink::First,
            })
            .collect();
        let features = (0..2)
            .map(|k| OrbFeatures {
                keypoints: vec![KeyPoint {
                    uv: DVec2::new(2.0 + k as f64, 3.0),
                    level: 0,
                    angle: 0.5,
                    score: 10.0,
                    size: 31.0,
                }],
                descriptors: vec![Descriptor::from_bytes(&[7 + k as u8; 32])],
                points: vec![Some(DVec3::new(0.1, 0.2, 2.0))],
                width: W,
                height: H,
            })
            .collect();
        let mut information = vec![0.0; 36];
        for i in 0..6 {
            information[i * 7] = 100.0;
        }
        Map {
            camera,
            sessions: 1,
            vocabulary_words: 1000,
            keyframes,
            features,
            mask_flags: vec![vec![vec![true]], vec![vec![false]]],
            edges: vec![MapEdge {
                from: 0,
                to: 1,
                measurement: Se3::new(DQuat::IDENTITY, DVec3::X),
                information,
            }],
        }
    }

    fn saved(map: &Map) -> (tempfile::TempDir, PathBuf, Vec<u8>) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.rgbmap");
        map.save(&path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        (dir, path, bytes)
    }

    fn offset_of(e: &MapError) -> u64 {
        match e {
            MapError::Corrupt { offset, .. } => *offset,
            other => panic!("not a corrupt-map error: {other}"),
        }
    }

    #[test]
    fn round_trip_and_every_bit_flip_is_caught() {
        let map = small_map();
        let (_dir, path, bytes) = saved(&map);
        let back = Map::load(&path).unwrap();
        assert_eq!(
            back.keyframes[1].inverse_depth,
            map.keyframes[1].inverse_depth
        );
        assert!(back.keyframes[0].colour.is_none());
        assert_eq!(back.keyframes[1].colour, map.keyframes[1].colour);
        assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), 3);
        assert_eq!(
            back.features[1].keypoints[0].uv,
            map.features[1].keypoints[0].uv
        );
        assert_eq!(back.mask_flags, map.mask_flags);
        assert_eq!(back.edges, map.edges);
        // A flipped bit anywhere after the magic and version is an error, never a map.
        let mut caught = 0;
        for pos in 12..bytes.len() {
            let mut b = bytes.clone();
            b[pos] ^= 1 << (pos % 8);
            if parse_map(&b, &path).is_err() {
                caught += 1;
            }
        }
        assert_eq!(caught, bytes.len() - 12);
    }

    #[test]
    fn invalid_values_are_refused_with_their_offset() {
        // NaN inverse depth, a NaN or far key point, a keyframe of another size than the
        // camera: each refused (the checksums are written over the bad values).
        let mut m = small_map();
        m.keyframes[1].inverse_depth[5] = f16::NAN;
        let (_d, p, _) = saved(&m);
        let e = Map::load(&p).unwrap_err();
        assert!(
            e.to_string().contains("inverse depth NaN at pixel 5"),
            "{e}"
        );
        assert!(offset_of(&e) > 0);

        let mut m = small_map();
        m.features[0].keypoints[0].uv.x = f64::NAN;
        let (_d, p, _) = saved(&m);
        let e = Map::load(&p).unwrap_err();
        assert!(e.to_string().contains("outside the image"), "{e}");

        let mut m = small_map();
        m.features[1].points[0] = Some(DVec3::splat(1e300));
        let (_d, p, _) = saved(&m);
        assert!(Map::load(&p).unwrap_err().to_string().contains("3D point"));

        let mut m = small_map();
        m.camera.width = 16;
        m.camera.cx = 7.5;
        let (_d, p, _) = saved(&m);
        let e = Map::load(&p).unwrap_err();
        assert!(
            e.to_string()
                .contains("8x6 pixels but the map's camera is 16x6"),
            "{e}"
        );
    }

    #[test]
    fn declared_sizes_are_checked_before_allocating() {
        let map = small_map();
        let (_dir, path, mut bytes) = saved(&map);
        // A header length of 2^60 bytes: refused, nothing allocated.
        bytes[12..20].copy_from_slice(&(1u64 << 60).to_le_bytes());
        let e = parse_map(&bytes, &path).unwrap_err();
        assert!(e.to_string().contains("at byte 24"), "{e}");
        assert!(e.to_string().contains("declared"), "{e}");
        // A file of zeros is refused after its first 8 bytes.
        let dir = tempfile::tempdir().unwrap();
        let zeros = dir.path().join("zeros");
        std::fs::write(&zeros, vec![0u8; 4096]).unwrap();
        assert!(matches!(Map::load(&zeros), Err(MapError::Foreign(_))));
        if Path::new("/dev/zero").exists() {
            assert!(matches!(
                Map::load(Path::new("/dev/zero")),
                Err(MapError::Foreign(_))
            ));
        }
    }

    /// A version 2 map (lengths and checksums, no colour), written byte by byte as version 2
    /// wrote it, still loads, without colour; a version 2 header that claims colour is refused.
    #[test]
    fn version_2_still_loads_without_colour() {
        let mut map = small_map();
        for k in &mut map.keyframes {
            k.colour = None;
        }
        let header = |colour: bool| {
            let (_d, _p, bytes) = saved(&map);
            let len = u64::from_le_bytes(bytes[12..20].try_into().unwrap()) as usize;
            let json = String::from_utf8(bytes[24..24 + len].to_vec()).unwrap();
            assert!(!json.contains("colour"), "{json}");
            if colour {
                json.replacen("\"masks\":1", "\"masks\":1,\"colour\":true", 1)
            } else {
                json
            }
        };
        let v2 = |json: String| {
            let mut v2 = Vec::new();
            v2.extend_from_slice(MAGIC);
            v2.extend_from_slice(&2u32.to_le_bytes());
            v2.extend_from_slice(&(json.len() as u64).to_le_bytes());
            v2.extend_from_slice(&crc32fast::hash(json.as_bytes()).to_le_bytes());
            v2.extend_from_slice(json.as_bytes());
            for ((k, f), m) in map.keyframes.iter().zip(&map.features).zip(&map.mask_flags) {
                let mut b = Vec::new();
                b.extend_from_slice(&k.intensity);
                for r in &k.inverse_depth {
                    b.extend_from_slice(&r.to_bits().to_le_bytes());
                }
                b.extend_from_slice(&k.weight);
                b.extend_from_slice(&keyframe_block(k, f, m)[4 * W * H..]);
                v2.extend_from_slice(&(b.len() as u64).to_le_bytes());
                v2.extend_from_slice(&crc32fast::hash(&b).to_le_bytes());
                v2.extend_from_slice(&b);
            }
            v2.extend_from_slice(END);
            v2
        };
        let back = parse_map(&v2(header(false)), Path::new("v2.rgbmap")).unwrap();
        assert_eq!(back.keyframes.len(), 2);
        assert!(back.keyframes.iter().all(|k| k.colour.is_none()));
        assert_eq!(back.keyframes[1].intensity, map.keyframes[1].intensity);
        assert_eq!(back.features[1].descriptors, map.features[1].descriptors);
        assert_eq!(back.edges, map.edges);
        let e = parse_map(&v2(header(true)), Path::new("v2.rgbmap")).unwrap_err();
        assert!(e.to_string().contains("colour in a version 2 map"), "{e}");
    }

    /// Version 1 (no lengths, no checksums) still loads.
    #[test]
    fn version_1_still_loads() {
        let mut map = small_map();
        for k in &mut map.keyframes {
            k.colour = None;
        }
        let header_json = {
            let (_d, _p, bytes) = saved(&map);
            let len = u64::from_le_bytes(bytes[12..20].try_into().unwrap()) as usize;
            bytes[24..24 + len].to_vec()
        };
        let mut v1 = Vec::new();
        v1.extend_from_slice(MAGIC);
        v1.extend_from_slice(&1u32.to_le_bytes());
        v1.extend_from_slice(&(header_json.len() as u64).to_le_bytes());
        v1.extend_from_slice(&header_json);
        for ((k, f), m) in map.keyframes.iter().zip(&map.features).zip(&map.mask_flags) {
            v1.extend_from_slice(&keyframe_block(k, f, m));
        }
        v1.extend_from_slice(END);
        let back = parse_map(&v1, Path::new("v1.rgbmap")).unwrap();
        assert_eq!(back.keyframes.len(), 2);
        assert_eq!(back.features[0].descriptors, map.features[0].descriptors);
        // Its corruption is still caught by the value checks and the end marker.
        let mut cut = v1.clone();
        cut.truncate(v1.len() - 3);
        assert!(parse_map(&cut, Path::new("v1.rgbmap")).is_err());
    }
}
