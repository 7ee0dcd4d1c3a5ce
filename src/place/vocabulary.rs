//! A DBoW2-like vocabulary tree of binary descriptors: hierarchical k-medians (bitwise
//! majority) clustering with k-means++ seeding, TF-IDF word weights, L1 (or L2) scoring, a
//! compact binary file format, and a loader for the DBoW2 / ORB-SLAM text format
//! (`ORBvoc.txt`).
//!
//! Binary format (little endian): magic `RGBIDVOC`, `u32` version (2), `u32` k, `u32` levels,
//! `u8` weighting, `u8` scoring (DBoW2 enum codes), `u16` reserved (0), `u32` node count `n`
//! (root included), then for nodes `1..n`: `u32` parent, `u8` flags (bit 0: leaf/word),
//! 32 descriptor bytes, `f64` weight; then (version 2) the `u32` CRC-32 of every byte before
//! it. A parent precedes its children; words are the leaves in node order. Version 1 (no
//! checksum) still loads. The node count is checked against the data's length before
//! anything is allocated; errors give the byte offset.

use std::collections::BTreeMap;
use std::io::{BufRead, Read, Write};
use std::path::Path;

use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use super::orb::Descriptor;
use super::PlaceError;

/// Word weighting schemes (DBoW2 codes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Weighting {
    /// Term frequency times inverse document frequency (code 0).
    TfIdf,
    /// Term frequency only (code 1).
    Tf,
    /// Inverse document frequency only (code 2).
    Idf,
    /// 1 for every present word (code 3).
    Binary,
}

impl Weighting {
    /// DBoW2 code.
    pub fn code(self) -> u32 {
        match self {
            Weighting::TfIdf => 0,
            Weighting::Tf => 1,
            Weighting::Idf => 2,
            Weighting::Binary => 3,
        }
    }
    /// From a DBoW2 code.
    pub fn from_code(c: u32) -> Result<Self, PlaceError> {
        Ok(match c {
            0 => Weighting::TfIdf,
            1 => Weighting::Tf,
            2 => Weighting::Idf,
            3 => Weighting::Binary,
            _ => {
                return Err(PlaceError::Unsupported {
                    what: "weighting",
                    code: c,
                })
            }
        })
    }
}

/// Scoring (vector normalisation and similarity) schemes implemented here (DBoW2 codes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scoring {
    /// L1-normalised vectors, `s = 1 - |v - w|_1 / 2` in `[0, 1]` (code 0).
    L1,
    /// L2-normalised vectors, `s = 1 - sqrt(1 - v.w)` (code 1).
    L2,
}

impl Scoring {
    /// DBoW2 code.
    pub fn code(self) -> u32 {
        match self {
            Scoring::L1 => 0,
            Scoring::L2 => 1,
        }
    }
    /// From a DBoW2 code (chi-square, KL, Bhattacharyya and dot product are not implemented).
    pub fn from_code(c: u32) -> Result<Self, PlaceError> {
        match c {
            0 => Ok(Scoring::L1),
            1 => Ok(Scoring::L2),
            _ => Err(PlaceError::Unsupported {
                what: "scoring",
                code: c,
            }),
        }
    }
}

/// A bag-of-words vector: `(word id, value)` sorted by word id, normalised by the
/// vocabulary's scoring norm.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BowVector(pub Vec<(u32, f64)>);

/// The direct index: for each vocabulary node at the chosen level, the indices of the
/// features that descended through it.
pub type FeatureVector = BTreeMap<u32, Vec<usize>>;

#[derive(Clone, Debug, PartialEq)]
struct Node {
    parent: u32,
    children: Vec<u32>,
    descriptor: Descriptor,
    weight: f64,
    word: Option<u32>,
    depth: u8,
}

/// Vocabulary training parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrainParams {
    /// Branching factor.
    pub k: usize,
    /// Depth of the tree (levels below the root).
    pub levels: usize,
    /// Maximum k-medians iterations per node.
    pub max_iterations: usize,
    /// Seed of the k-means++ initialisation.
    pub seed: u64,
    /// Word weighting.
    pub weighting: Weighting,
    /// Scoring.
    pub scoring: Scoring,
}

impl Default for TrainParams {
    fn default() -> Self {
        Self {
            k: 10,
            levels: 5,
            max_iterations: 15,
            seed: 7,
            weighting: Weighting::TfIdf,
            scoring: Scoring::L1,
        }
    }
}

/// A vocabulary tree of binary words.
#[derive(Clone, Debug, PartialEq)]
pub struct Vocabulary {
    k: usize,
    levels: usize,
    weighting: Weighting,
    scoring: Scoring,
    nodes: Vec<Node>,
    /// Word id -> node id.
    words: Vec<u32>,
}

const MAGIC: &[u8; 8] = b"RGBIDVOC";
const VERSION: u32 = 2;

/// Bitwise majority of a set of descriptors (the binary "median").
fn majority(set: &[&Descriptor]) -> Descriptor {
    let mut counts = [0u32; 256];
    for d in set {
        for (w, word) in d.0.iter().enumerate() {
            let mut x = *word;
            while x != 0 {
                let b = x.trailing_zeros() as usize;
                counts[w * 64 + b] += 1;
                x &= x - 1;
            }
        }
    }
    let half = set.len() as u32;
    let mut out = [0u64; 4];
    for (i, &c) in counts.iter().enumerate() {
        if 2 * c > half {
            out[i / 64] |= 1u64 << (i % 64);
        }
    }
    Descriptor(out)
}

/// k-medians clustering with k-means++ seeding; returns (centres, assignment).
fn kmedians(
    data: &[&Descriptor],
    k: usize,
    iters: usize,
    rng: &mut rand_pcg::Pcg64,
) -> (Vec<Descriptor>, Vec<usize>) {
    if data.len() <= k {
        return (
            data.iter().map(|d| **d).collect(),
            (0..data.len()).collect(),
        );
    }
    // k-means++ seeding.
    let mut centres = vec![*data[rng.random_range(0..data.len())]];
    let mut dmin: Vec<f64> = data
        .iter()
        .map(|d| f64::from(d.distance(&centres[0])))
        .collect();
    while centres.len() < k {
        let total: f64 = dmin.iter().map(|d| d * d).sum();
        let next = if total <= 0.0 {
            rng.random_range(0..data.len())
        } else {
            let mut r = rng.random_range(0.0..total);
            let mut idx = data.len() - 1;
            for (i, d) in dmin.iter().enumerate() {
                r -= d * d;
                if r <= 0.0 {
                    idx = i;
                    break;
                }
            }
            idx
        };
        let c = *data[next];
        for (dm, d) in dmin.iter_mut().zip(data.iter()) {
            *dm = dm.min(f64::from(d.distance(&c)));
        }
        centres.push(c);
    }
    let mut assign = vec![usize::MAX; data.len()];
    for _ in 0..iters.max(1) {
        let new: Vec<usize> = data
            .par_iter()
            .map(|d| {
                let mut best = (u32::MAX, 0);
                for (ci, c) in centres.iter().enumerate() {
                    let dist = d.distance(c);
                    if dist < best.0 {
                        best = (dist, ci);
                    }
                }
                best.1
            })
            .collect();
        let changed = new != assign;
        assign = new;
        if !changed {
            break;
        }
        for (ci, c) in centres.iter_mut().enumerate() {
            let members: Vec<&Descriptor> = data
                .iter()
                .zip(assign.iter())
                .filter(|(_, &a)| a == ci)
                .map(|(d, _)| *d)
                .collect();
            if !members.is_empty() {
                *c = majority(&members);
            }
        }
    }
    (centres, assign)
}

impl Vocabulary {
    /// Bytes of heap memory the tree holds (nodes, their child lists, the word table).
    pub(crate) fn heap_bytes(&self) -> usize {
        fn bytes<T>(v: &Vec<T>) -> usize {
            v.capacity() * std::mem::size_of::<T>()
        }
        bytes(&self.nodes)
            + self.nodes.iter().map(|n| bytes(&n.children)).sum::<usize>()
            + bytes(&self.words)
    }

    /// Branching factor.
    pub fn k(&self) -> usize {
        self.k
    }
    /// Tree depth below the root.
    pub fn levels(&self) -> usize {
        self.levels
    }
    /// Number of words (leaves).
    pub fn num_words(&self) -> usize {
        self.words.len()
    }
    /// Number of nodes, root included.
    pub fn num_nodes(&self) -> usize {
        self.nodes.len()
    }
    /// Weighting scheme.
    pub fn weighting(&self) -> Weighting {
        self.weighting
    }
    /// Scoring scheme.
    pub fn scoring(&self) -> Scoring {
        self.scoring
    }
    /// The weight (IDF for TF-IDF) of word `w`, `None` if out of range.
    pub fn word_weight(&self, w: u32) -> Option<f64> {
        self.words
            .get(w as usize)
            .map(|&n| self.nodes[n as usize].weight)
    }

    /// Trains a vocabulary from per-image descriptor sets (the images are the "documents"
    /// of the IDF weights).
    pub fn train(images: &[Vec<Descriptor>], params: &TrainParams) -> Result<Self, PlaceError> {
        if params.k < 2 || params.k > 255 {
            return Err(PlaceError::InvalidParameter {
                name: "k",
                why: "branching factor must be in 2..=255".into(),
            });
        }
        if params.levels == 0 || params.levels > 10 {
            return Err(PlaceError::InvalidParameter {
                name: "levels",
                why: "must be in 1..=10".into(),
            });
        }
        let all: Vec<&Descriptor> = images.iter().flatten().collect();
        if all.len() < params.k {
            return Err(PlaceError::NotEnoughTrainingData {
                got: all.len(),
                need: params.k,
            });
        }
        let mut rng = rand_pcg::Pcg64::seed_from_u64(params.seed);
        let mut nodes = vec![Node {
            parent: 0,
            children: Vec::new(),
            descriptor: Descriptor::default(),
            weight: 0.0,
            word: None,
            depth: 0,
        }];
        // Breadth-first: (node id, member descriptors).
        let mut queue = std::collections::VecDeque::from([(0u32, all)]);
        while let Some((nid, members)) = queue.pop_front() {
            let depth = nodes[nid as usize].depth as usize;
            if depth >= params.levels || members.len() <= 1 {
                continue;
            }
            let (centres, assign) = kmedians(&members, params.k, params.max_iterations, &mut rng);
            let mut groups: Vec<Vec<&Descriptor>> = vec![Vec::new(); centres.len()];
            for (d, &a) in members.iter().zip(assign.iter()) {
                groups[a].push(*d);
            }
            for (c, g) in centres.into_iter().zip(groups) {
                if g.is_empty() {
                    continue;
                }
                let id = nodes.len() as u32;
                nodes.push(Node {
                    parent: nid,
                    children: Vec::new(),
                    descriptor: c,
                    weight: 0.0,
                    word: None,
                    depth: depth as u8 + 1,
                });
                nodes[nid as usize].children.push(id);
                queue.push_back((id, g));
            }
        }
        let mut voc = Self::from_nodes(
            params.k,
            params.levels,
            params.weighting,
            params.scoring,
            nodes,
        );
        voc.set_weights(images);
        Ok(voc)
    }

    /// Marks leaves as words (in node order) and fixes depths.
    fn from_nodes(
        k: usize,
        levels: usize,
        weighting: Weighting,
        scoring: Scoring,
        mut nodes: Vec<Node>,
    ) -> Self {
        let mut words = Vec::new();
        for i in 0..nodes.len() {
            if i > 0 {
                let p = nodes[i].parent as usize;
                nodes[i].depth = nodes[p].depth.saturating_add(1);
            }
            if i > 0 && nodes[i].children.is_empty() {
                nodes[i].word = Some(words.len() as u32);
                words.push(i as u32);
            } else {
                nodes[i].word = None;
            }
        }
        Self {
            k,
            levels,
            weighting,
            scoring,
            nodes,
            words,
        }
    }

    /// Sets word weights from training documents (IDF = ln(N / n_i); 1 for TF and binary).
    fn set_weights(&mut self, images: &[Vec<Descriptor>]) {
        let n_docs = images.len() as f64;
        let mut doc_count = vec![0u32; self.words.len()];
        if matches!(self.weighting, Weighting::TfIdf | Weighting::Idf) {
            let per_image: Vec<Vec<u32>> = images
                .par_iter()
                .map(|img| {
                    let mut ws: Vec<u32> =
                        img.iter().map(|d| self.descend(d, usize::MAX).0).collect();
                    ws.sort_unstable();
                    ws.dedup();
                    ws
                })
                .collect();
            for ws in per_image {
                for w in ws {
                    doc_count[w as usize] += 1;
                }
            }
        }
        for (w, &node) in self.words.iter().enumerate() {
            self.nodes[node as usize].weight = match self.weighting {
                Weighting::TfIdf | Weighting::Idf => {
                    if doc_count[w] > 0 {
                        (n_docs / f64::from(doc_count[w])).ln()
                    } else {
                        0.0
                    }
                }
                Weighting::Tf | Weighting::Binary => 1.0,
            };
        }
    }

    /// Descends the tree; returns the word id and the node at depth `fv_depth` (or the leaf
    /// if shallower).
    fn descend(&self, d: &Descriptor, fv_depth: usize) -> (u32, u32) {
        let mut node = 0u32;
        let mut fv_node = 0u32;
        loop {
            let n = &self.nodes[node as usize];
            if n.depth as usize <= fv_depth {
                fv_node = node;
            }
            if n.children.is_empty() {
                return (n.word.unwrap_or(0), fv_node);
            }
            let mut best = (u32::MAX, n.children[0]);
            for &c in &n.children {
                let dist = d.distance(&self.nodes[c as usize].descriptor);
                if dist < best.0 {
                    best = (dist, c);
                }
            }
            node = best.1;
        }
    }

    /// The word of one descriptor.
    pub fn word_of(&self, d: &Descriptor) -> u32 {
        self.descend(d, 0).0
    }

    /// Bag-of-words vector of a descriptor set and its direct index at depth `fv_depth` below
    /// the root (ORB-SLAM uses depth `levels - 4`, e.g. 2 for a 6-level tree).
    pub fn transform(
        &self,
        descriptors: &[Descriptor],
        fv_depth: usize,
    ) -> (BowVector, FeatureVector) {
        let mut acc: BTreeMap<u32, f64> = BTreeMap::new();
        let mut fv: FeatureVector = BTreeMap::new();
        if self.words.is_empty() {
            return (BowVector::default(), fv);
        }
        let hits: Vec<(u32, u32)> = descriptors
            .par_iter()
            .map(|d| self.descend(d, fv_depth))
            .collect();
        for (i, (w, node)) in hits.into_iter().enumerate() {
            let weight = self.nodes[self.words[w as usize] as usize].weight;
            if weight > 0.0 {
                let e = acc.entry(w).or_insert(0.0);
                match self.weighting {
                    Weighting::TfIdf | Weighting::Tf => *e += weight,
                    Weighting::Idf | Weighting::Binary => *e = weight,
                }
                fv.entry(node).or_default().push(i);
            }
        }
        let mut v: Vec<(u32, f64)> = acc.into_iter().collect();
        let norm = match self.scoring {
            Scoring::L1 => v.iter().map(|(_, x)| x.abs()).sum::<f64>(),
            Scoring::L2 => v.iter().map(|(_, x)| x * x).sum::<f64>().sqrt(),
        };
        if norm > 0.0 {
            v.iter_mut().for_each(|(_, x)| *x /= norm);
        }
        (BowVector(v), fv)
    }

    /// Similarity of two normalised BoW vectors, in `[0, 1]` (1 = identical).
    pub fn score(&self, a: &BowVector, b: &BowVector) -> f64 {
        score_bow(self.scoring, a, b)
    }

    /// Writes the compact binary format (see the module docs).
    pub fn write_binary<W: Write>(&self, mut w: W) -> std::io::Result<()> {
        let mut b = Vec::with_capacity(32 + self.nodes.len() * 45);
        b.extend_from_slice(MAGIC);
        b.extend_from_slice(&VERSION.to_le_bytes());
        b.extend_from_slice(&(self.k as u32).to_le_bytes());
        b.extend_from_slice(&(self.levels as u32).to_le_bytes());
        b.extend_from_slice(&[self.weighting.code() as u8, self.scoring.code() as u8, 0, 0]);
        b.extend_from_slice(&(self.nodes.len() as u32).to_le_bytes());
        for n in &self.nodes[1..] {
            b.extend_from_slice(&n.parent.to_le_bytes());
            b.push(u8::from(n.children.is_empty()));
            b.extend_from_slice(&n.descriptor.to_bytes());
            b.extend_from_slice(&n.weight.to_le_bytes());
        }
        let crc = crc32fast::hash(&b);
        b.extend_from_slice(&crc.to_le_bytes());
        w.write_all(&b)
    }

    /// Reads the compact binary format from bytes.
    pub fn read_binary(bytes: &[u8]) -> Result<Self, PlaceError> {
        let bad = |m: &str| PlaceError::BadBinaryVocabulary(m.to_string());
        let mut pos = 0usize;
        let mut take = |n: usize| -> Result<&[u8], PlaceError> {
            let s = pos
                .checked_add(n)
                .and_then(|end| bytes.get(pos..end))
                .ok_or_else(|| bad(&format!("truncated file: ends before byte {}", pos + n)))?;
            pos += n;
            Ok(s)
        };
        let u32_at = |s: &[u8]| u32::from_le_bytes([s[0], s[1], s[2], s[3]]);
        if take(8)? != MAGIC {
            return Err(bad("not an rgbid vocabulary (bad magic)"));
        }
        let version = u32_at(take(4)?);
        if !(1..=VERSION).contains(&version) {
            return Err(bad(&format!(
                "version {version} at byte 8; this build reads versions 1 to {VERSION}"
            )));
        }
        let k = u32_at(take(4)?) as usize;
        let levels = u32_at(take(4)?) as usize;
        let codes = take(4)?;
        let at_codes = |e: PlaceError| bad(&format!("byte 20: {e}"));
        let weighting = Weighting::from_code(u32::from(codes[0])).map_err(at_codes)?;
        let scoring = Scoring::from_code(u32::from(codes[1])).map_err(at_codes)?;
        let n = u32_at(take(4)?) as usize;
        if n == 0 {
            return Err(bad("node count is 0 (the root is always present)"));
        }
        const REC: usize = 4 + 1 + 32 + 8;
        let crc_bytes = if version >= 2 { 4 } else { 0 };
        if Some(bytes.len()) != (n - 1).checked_mul(REC).map(|r| 28 + r + crc_bytes) {
            return Err(bad(&format!(
                "size {} does not match the {n} nodes declared at byte 24",
                bytes.len()
            )));
        }
        if version >= 2 {
            let (data, crc) = bytes.split_at(bytes.len() - 4);
            if crc32fast::hash(data) != u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]) {
                return Err(bad(&format!(
                    "checksum mismatch (the CRC-32 at byte {} does not match the bytes before it)",
                    data.len()
                )));
            }
        }
        let mut nodes = Vec::with_capacity(n);
        nodes.push(Node {
            parent: 0,
            children: Vec::new(),
            descriptor: Descriptor::default(),
            weight: 0.0,
            word: None,
            depth: 0,
        });
        let mut leaf_flags = vec![false; n];
        for i in 1..n {
            let rec = take(REC)?;
            let parent = u32_at(&rec[0..4]);
            let flags = rec[4];
            let mut db = [0u8; 32];
            db.copy_from_slice(&rec[5..37]);
            let mut wb = [0u8; 8];
            wb.copy_from_slice(&rec[37..45]);
            let weight = f64::from_le_bytes(wb);
            let at = 28 + (i - 1) * REC;
            if parent as usize >= i {
                return Err(bad(&format!(
                    "node {i} (byte {at}) has parent {parent}, which does not precede it"
                )));
            }
            if leaf_flags[parent as usize] {
                return Err(bad(&format!("node {i} (byte {at}) has a leaf as parent")));
            }
            if !weight.is_finite() {
                return Err(bad(&format!(
                    "node {i} (byte {at}) has a non-finite weight"
                )));
            }
            leaf_flags[i] = flags & 1 == 1;
            nodes[parent as usize].children.push(i as u32);
            nodes.push(Node {
                parent,
                children: Vec::new(),
                descriptor: Descriptor::from_bytes(&db),
                weight,
                word: None,
                depth: 0,
            });
        }
        for (i, node) in nodes.iter().enumerate().skip(1) {
            if leaf_flags[i] != node.children.is_empty() {
                let at = 28 + (i - 1) * REC;
                return Err(bad(&format!(
                    "node {i} (byte {at}): leaf flag disagrees with its children"
                )));
            }
        }
        Ok(Self::from_nodes(k, levels, weighting, scoring, nodes))
    }

    /// Saves to a binary file.
    pub fn save(&self, path: &Path) -> Result<(), PlaceError> {
        crate::io::write_atomic(path, |w| self.write_binary(w)).map_err(|e| match e {
            crate::io::IoError::File { source, .. } => PlaceError::File {
                path: path.to_path_buf(),
                source,
            },
            other => PlaceError::File {
                path: path.to_path_buf(),
                source: std::io::Error::other(other.to_string()),
            },
        })
    }

    /// The default vocabulary embedded in the library (`assets/vocab_default.rgbvoc`, trained
    /// on rgbid-rendered images).
    pub fn embedded_default() -> Result<Self, PlaceError> {
        Self::read_binary(include_bytes!("../../assets/vocab_default.rgbvoc"))
    }

    /// Loads a vocabulary file: the binary format, or (if it does not start with the magic)
    /// the DBoW2 text format.
    ///
    /// Reads at most the file's own length (a device such as `/dev/zero` is refused), and
    /// errors name the file.
    pub fn load(path: &Path) -> Result<Self, PlaceError> {
        let io = |source| PlaceError::File {
            path: path.to_path_buf(),
            source,
        };
        let file = std::fs::File::open(path).map_err(io)?;
        let meta = file.metadata().map_err(io)?;
        if !meta.is_file() {
            return Err(io(std::io::Error::other("not a regular file")));
        }
        let mut bytes = Vec::new();
        file.take(meta.len()).read_to_end(&mut bytes).map_err(io)?;
        let parsed = if bytes.starts_with(MAGIC) {
            Self::read_binary(&bytes)
        } else {
            Self::read_dbow2_text(&bytes[..])
        };
        parsed.map_err(|e| PlaceError::InFile {
            path: path.to_path_buf(),
            message: e.to_string(),
        })
    }

    /// Parses the DBoW2 text format: a header `k L scoring weighting`, then one line per node
    /// (root excluded, in id order): `parent is_leaf d0 .. d31 weight`, descriptor bytes as
    /// decimal integers.
    pub fn read_dbow2_text<R: BufRead>(reader: R) -> Result<Self, PlaceError> {
        let err = |line: usize, m: String| PlaceError::BadTextVocabulary { line, message: m };
        let mut lines = reader.lines().enumerate();
        let (_, header) = lines.next().ok_or_else(|| err(1, "empty file".into()))?;
        let header = header.map_err(|e| err(1, e.to_string()))?;
        let h: Vec<&str> = header.split_whitespace().collect();
        if h.len() < 4 {
            return Err(err(
                1,
                format!("header needs `k L scoring weighting`, got {header:?}"),
            ));
        }
        let num = |s: &str, line: usize, what: &str| -> Result<i64, PlaceError> {
            s.parse::<i64>()
                .map_err(|_| err(line, format!("{what} {s:?} is not an integer")))
        };
        let k = num(h[0], 1, "k")?;
        let levels = num(h[1], 1, "L")?;
        let sc = num(h[2], 1, "scoring")?;
        let wt = num(h[3], 1, "weighting")?;
        if !(2..=255).contains(&k)
            || !(1..=10).contains(&levels)
            || !(0..=5).contains(&sc)
            || !(0..=3).contains(&wt)
        {
            return Err(err(1, format!("header values out of range: {header:?}")));
        }
        let scoring = Scoring::from_code(sc as u32)?;
        let weighting = Weighting::from_code(wt as u32)?;
        let mut nodes = vec![Node {
            parent: 0,
            children: Vec::new(),
            descriptor: Descriptor::default(),
            weight: 0.0,
            word: None,
            depth: 0,
        }];
        let mut leaf = vec![false];
        for (i, l) in lines {
            let ln = i + 1;
            let l = l.map_err(|e| err(ln, e.to_string()))?;
            let t: Vec<&str> = l.split_whitespace().collect();
            if t.is_empty() {
                continue;
            }
            if t.len() != 2 + 32 + 1 {
                return Err(err(
                    ln,
                    format!(
                        "expected 35 fields (parent, leaf flag, 32 bytes, weight), got {}",
                        t.len()
                    ),
                ));
            }
            let parent = num(t[0], ln, "parent")?;
            if parent < 0 || parent as usize >= nodes.len() {
                return Err(err(
                    ln,
                    format!("parent {parent} does not precede this node"),
                ));
            }
            if leaf[parent as usize] {
                return Err(err(ln, format!("parent {parent} is a leaf")));
            }
            let is_leaf = num(t[1], ln, "leaf flag")? > 0;
            let mut db = [0u8; 32];
            for (j, b) in db.iter_mut().enumerate() {
                let v = num(t[2 + j], ln, "descriptor byte")?;
                *b = u8::try_from(v)
                    .map_err(|_| err(ln, format!("descriptor byte {v} out of 0..=255")))?;
            }
            let weight: f64 = t[34]
                .parse()
                .map_err(|_| err(ln, format!("weight {:?} is not a number", t[34])))?;
            if !weight.is_finite() {
                return Err(err(ln, "non-finite weight".into()));
            }
            let id = nodes.len() as u32;
            nodes[parent as usize].children.push(id);
            nodes.push(Node {
                parent: parent as u32,
                children: Vec::new(),
                descriptor: Descriptor::from_bytes(&db),
                weight,
                word: None,
                depth: 0,
            });
            leaf.push(is_leaf);
        }
        if nodes.len() == 1 {
            return Err(err(2, "no nodes".into()));
        }
        for (i, n) in nodes.iter().enumerate().skip(1) {
            if leaf[i] != n.children.is_empty() {
                return Err(err(
                    i + 1,
                    format!("node {i}: leaf flag disagrees with its children"),
                ));
            }
        }
        Ok(Self::from_nodes(
            k as usize,
            levels as usize,
            weighting,
            scoring,
            nodes,
        ))
    }

    /// Writes the DBoW2 text format (readable by DBoW2 / ORB-SLAM's `loadFromTextFile`).
    pub fn write_dbow2_text<W: Write>(&self, mut w: W) -> std::io::Result<()> {
        writeln!(
            w,
            "{} {} {} {}",
            self.k,
            self.levels,
            self.scoring.code(),
            self.weighting.code()
        )?;
        for n in &self.nodes[1..] {
            write!(w, "{} {}", n.parent, u8::from(n.children.is_empty()))?;
            for b in n.descriptor.to_bytes() {
                write!(w, " {b}")?;
            }
            writeln!(w, " {}", n.weight)?;
        }
        Ok(())
    }
}

/// Similarity of two normalised BoW vectors under `scoring`, in `[0, 1]`.
pub fn score_bow(scoring: Scoring, a: &BowVector, b: &BowVector) -> f64 {
    let (a, b) = (&a.0, &b.0);
    let (mut i, mut j) = (0, 0);
    let mut s = 0.0;
    while i < a.len() && j < b.len() {
        match a[i].0.cmp(&b[j].0) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                let (x, y) = (a[i].1, b[j].1);
                s += match scoring {
                    Scoring::L1 => x.abs() + y.abs() - (x - y).abs(),
                    Scoring::L2 => x * y,
                };
                i += 1;
                j += 1;
            }
        }
    }
    match scoring {
        Scoring::L1 => 0.5 * s,
        Scoring::L2 => {
            if s >= 1.0 {
                1.0
            } else {
                1.0 - (1.0 - s).max(0.0).sqrt()
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    fn random_desc(rng: &mut rand_pcg::Pcg64) -> Descriptor {
        Descriptor([rng.random(), rng.random(), rng.random(), rng.random()])
    }

    #[test]
    fn binary_files_are_checksummed_and_bounded() {
        let v1 = include_bytes!("../../assets/vocab_default.rgbvoc");
        // The embedded vocabulary is version 1 (no checksum): it still loads, and a write
        // gives version 2 with the same content.
        assert_eq!(u32::from_le_bytes([v1[8], v1[9], v1[10], v1[11]]), 1);
        let voc = Vocabulary::read_binary(v1).unwrap();
        let mut v2 = Vec::new();
        voc.write_binary(&mut v2).unwrap();
        assert_eq!(u32::from_le_bytes([v2[8], v2[9], v2[10], v2[11]]), 2);
        assert_eq!(Vocabulary::read_binary(&v2).unwrap(), voc);
        // Flipped bits in the node records are caught by the checksum (sampled: every
        // 97th byte of the file).
        for pos in (28..v2.len()).step_by(97) {
            let mut b = v2.clone();
            b[pos] ^= 0x10;
            let e = Vocabulary::read_binary(&b).unwrap_err().to_string();
            assert!(e.contains("checksum"), "byte {pos}: {e}");
        }
        // A huge node count is refused from the length, before allocating.
        let mut b = v2.clone();
        b[24..28].copy_from_slice(&u32::MAX.to_le_bytes());
        let e = Vocabulary::read_binary(&b).unwrap_err().to_string();
        assert!(e.contains("declared at byte 24"), "{e}");
        if std::path::Path::new("/dev/zero").exists() {
            let e = Vocabulary::load(std::path::Path::new("/dev/zero")).unwrap_err();
            assert!(e.to_string().contains("not a regular file"), "{e}");
        }
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("v.rgbvoc");
        std::fs::write(&p, &v2[..v2.len() - 9]).unwrap();
        let e = Vocabulary::load(&p).unwrap_err().to_string();
        assert!(e.starts_with(&format!("{}: ", p.display())), "{e}");
    }

    #[test]
    fn majority_is_bitwise_median() {
        let a = Descriptor([0b111, 0, 0, 0]);
        let b = Descriptor([0b011, 0, 0, 0]);
        let c = Descriptor([0b001, 0, 0, 1]);
        assert_eq!(majority(&[&a, &b, &c]), Descriptor([0b011, 0, 0, 0]));
    }

    #[test]
    fn l1_score_of_identical_is_one_and_disjoint_is_zero() {
        let a = BowVector(vec![(1, 0.5), (3, 0.5)]);
        let b = BowVector(vec![(2, 0.5), (4, 0.5)]);
        assert!((score_bow(Scoring::L1, &a, &a) - 1.0).abs() < 1e-12);
        assert_eq!(score_bow(Scoring::L1, &a, &b), 0.0);
        let c = BowVector(vec![(1, 0.25), (2, 0.75)]);
        // 1 - |a - c|_1 / 2 = 1 - (0.25 + 0.75 + 0.5) / 2 = 0.25
        assert!((score_bow(Scoring::L1, &a, &c) - 0.25).abs() < 1e-12);
    }

    #[test]
    fn training_finds_planted_clusters() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
        let centres: Vec<Descriptor> = (0..4).map(|_| random_desc(&mut rng)).collect();
        let mut images = Vec::new();
        for _ in 0..8 {
            let mut img = Vec::new();
            for c in &centres {
                for _ in 0..10 {
                    let mut d = *c;
                    for _ in 0..8 {
                        let b = rng.random_range(0..256);
                        d.0[b / 64] ^= 1 << (b % 64);
                    }
                    img.push(d);
                }
            }
            images.push(img);
        }
        let p = TrainParams {
            k: 4,
            levels: 1,
            ..Default::default()
        };
        let voc = Vocabulary::train(&images, &p).unwrap();
        assert_eq!(voc.num_words(), 4);
        let words: std::collections::BTreeSet<u32> =
            centres.iter().map(|c| voc.word_of(c)).collect();
        assert_eq!(words.len(), 4, "each planted centre gets its own word");
    }
}
