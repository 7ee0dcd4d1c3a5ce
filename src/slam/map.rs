//! Saved maps: keyframes (compact images), ORB features with their mask flags (the BoW
//! histograms are recomputed from them with the vocabulary), optimised poses and the graph.
//!
//! File layout (little endian): `b"RGBIDMAP"`, `u32` version, `u64` length of a JSON header,
//! the header, then per keyframe its binary block, then `b"RGBIDEND"`. A truncated or
//! foreign file is an error naming the cause.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use glam::{DQuat, DVec2, DVec3};
use half::f16;

use super::backend::Backend;
use super::keyframe::{Keyframe, KeyframeLink};
use super::SlamError;
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::place::{Descriptor, KeyPoint, OrbFeatures};

/// Current map file version.
pub const MAP_VERSION: u32 = 1;
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
    #[error("{path}: map version {found}, this build reads version {MAP_VERSION}")]
    Version {
        /// File.
        path: PathBuf,
        /// Version found.
        found: u32,
    },
    /// The file ends early or a block is inconsistent.
    #[error("{path}: truncated or corrupt map ({what})")]
    Corrupt {
        /// File.
        path: PathBuf,
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
                })
                .collect(),
            edges: self
                .edges
                .iter()
                .map(|e| (e.from, e.to, pose_to(&e.measurement), e.information.clone()))
                .collect(),
        };
        let json = serde_json::to_vec(&header).map_err(|e| io(std::io::Error::other(e)))?;
        let file = std::fs::File::create(path).map_err(io)?;
        let mut w = std::io::BufWriter::new(file);
        let mut put = |b: &[u8]| w.write_all(b);
        put(MAGIC).map_err(io)?;
        put(&MAP_VERSION.to_le_bytes()).map_err(io)?;
        put(&(json.len() as u64).to_le_bytes()).map_err(io)?;
        put(&json).map_err(io)?;
        for ((k, f), masks) in self
            .keyframes
            .iter()
            .zip(self.features.iter())
            .zip(self.mask_flags.iter())
        {
            let mut b = Vec::with_capacity(k.image_bytes() + f.len() * 90);
            b.extend_from_slice(&k.intensity);
            for r in &k.inverse_depth {
                b.extend_from_slice(&r.to_bits().to_le_bytes());
            }
            b.extend_from_slice(&k.weight);
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
            put(&b).map_err(io)?;
        }
        put(END).map_err(io)?;
        w.flush().map_err(io)?;
        Ok(())
    }

    /// Reads a map written by [`Map::save`].
    pub fn load(path: &Path) -> Result<Map, MapError> {
        let p = path.to_path_buf();
        let mut bytes = Vec::new();
        std::fs::File::open(path)
            .and_then(|mut f| f.read_to_end(&mut bytes))
            .map_err(|source| MapError::Io {
                path: p.clone(),
                source,
            })?;
        let corrupt = |what: &str| MapError::Corrupt {
            path: p.clone(),
            what: what.to_string(),
        };
        if bytes.len() < 8 || &bytes[..8] != MAGIC {
            return Err(MapError::Foreign(p.clone()));
        }
        let mut r = Reader { b: &bytes, pos: 8 };
        let version = r.u32().ok_or_else(|| corrupt("header"))?;
        if version != MAP_VERSION {
            return Err(MapError::Version {
                path: p.clone(),
                found: version,
            });
        }
        let len = r.u64().ok_or_else(|| corrupt("header length"))? as usize;
        let json = r.take(len).ok_or_else(|| corrupt("header"))?;
        let header: Header =
            serde_json::from_slice(json).map_err(|e| corrupt(&format!("header: {e}")))?;
        let mut keyframes = Vec::new();
        let mut features = Vec::new();
        let mut mask_flags = Vec::new();
        for (n, kh) in header.keyframes.iter().enumerate() {
            if kh.id != n || kh.width * kh.height == 0 || kh.masks > 16 {
                return Err(corrupt(&format!("keyframe {n} header")));
            }
            let px = kh.width * kh.height;
            let what = format!("keyframe {n} block");
            let intensity = r.take(px).ok_or_else(|| corrupt(&what))?.to_vec();
            let rho_bytes = r.take(2 * px).ok_or_else(|| corrupt(&what))?;
            let inverse_depth = rho_bytes
                .chunks_exact(2)
                .map(|c| f16::from_bits(u16::from_le_bytes([c[0], c[1]])))
                .collect();
            let weight = r.take(px).ok_or_else(|| corrupt(&what))?.to_vec();
            let mut f = OrbFeatures {
                width: kh.width,
                height: kh.height,
                ..Default::default()
            };
            let mut flags = vec![Vec::new(); kh.masks];
            for _ in 0..kh.features {
                let u = r.f64().ok_or_else(|| corrupt(&what))?;
                let v = r.f64().ok_or_else(|| corrupt(&what))?;
                let level = r.take(1).ok_or_else(|| corrupt(&what))?[0];
                let angle = r.f32().ok_or_else(|| corrupt(&what))?;
                let score = r.f32().ok_or_else(|| corrupt(&what))?;
                let size = r.f32().ok_or_else(|| corrupt(&what))?;
                let d = r.take(32).ok_or_else(|| corrupt(&what))?;
                let mut db = [0u8; 32];
                db.copy_from_slice(d);
                let has = r.take(1).ok_or_else(|| corrupt(&what))?[0];
                let point = if has == 1 {
                    let x = r.f64().ok_or_else(|| corrupt(&what))?;
                    let y = r.f64().ok_or_else(|| corrupt(&what))?;
                    let z = r.f64().ok_or_else(|| corrupt(&what))?;
                    Some(DVec3::new(x, y, z))
                } else {
                    None
                };
                for fl in flags.iter_mut() {
                    fl.push(r.take(1).ok_or_else(|| corrupt(&what))?[0] != 0);
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
            let world_from_keyframe = pose_from(&kh.world_from_keyframe)
                .ok_or_else(|| corrupt(&format!("keyframe {n} pose")))?;
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
                world_from_keyframe,
                link: KeyframeLink::First,
            });
            features.push(f);
            mask_flags.push(flags);
        }
        if r.take(8) != Some(END.as_slice()) || r.pos != bytes.len() {
            return Err(corrupt("end marker"));
        }
        let mut edges = Vec::new();
        for (k, (from, to, m, info)) in header.edges.into_iter().enumerate() {
            let measurement = pose_from(&m).ok_or_else(|| corrupt(&format!("edge {k}")))?;
            if from >= keyframes.len() || to >= keyframes.len() || info.len() != 36 {
                return Err(corrupt(&format!("edge {k}")));
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
}

struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
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
