//! The volume's file format: a small versioned little-endian binary file.
//!
//! ```text
//! offset  size        content
//! 0       8           magic "RGBIDTSD"
//! 8       4           version (u32) = 1
//! 12      52          TsdfParams: voxel_size, rho_sigma, trunc_min_voxels, trunc_sigmas (f64),
//!                     max_weight (f32), min_depth, max_depth (f64)
//! 64      40          camera of the integrated frames: fx, fy, cx, cy (f64, pixels),
//!                     width, height (u32, pixels)
//! 104     8           frames integrated (u64)
//! 112     8           blocks B (u64)
//! 120     12 B        block coordinates, slot after slot ([i32; 3], in block edges)
//! ...     6144 B      voxels, slot after slot, 512 per block in the order x, then y, then z:
//!                     tsdf (f32, metres), weight (f32), colour (u32, 0x00BBGGRR)
//! ...     4           CRC-32 (IEEE) of every byte before it
//! ```
//!
//! Blocks keep their slots, so a loaded volume has the same block map, extracts the same mesh
//! and continues integrating exactly as the saved one would have. The block count is checked
//! against the file's length before anything is allocated, so a corrupt header cannot ask for
//! absurd amounts of memory.

use std::io::{Read, Write};
use std::path::Path;

use super::integrate::Voxel;
use super::volume::TsdfParams;
use super::{TsdfError, BLOCK_VOXELS};
use crate::camera::PinholeCamera;
use crate::io::IoError;

/// First bytes of a volume file.
const MAGIC: &[u8; 8] = b"RGBIDTSD";
/// The format version this code writes and reads.
pub(crate) const VERSION: u32 = 1;
/// Bytes before the block coordinates.
const HEADER_BYTES: u64 = 120;
/// Bytes of one voxel in the file.
const VOXEL_BYTES: usize = 12;
/// Bytes per block: its coordinates and its voxels.
const BLOCK_BYTES: u64 = 12 + (BLOCK_VOXELS * VOXEL_BYTES) as u64;
/// Block keys reach `2^20` block edges from the origin along each axis (as the volume's
/// packed keys).
const COORD_LIMIT: i32 = 1 << 20;

/// What a file holds besides the voxels.
pub(crate) struct Header {
    pub(crate) params: TsdfParams,
    pub(crate) camera: PinholeCamera,
    pub(crate) frames: u64,
}

/// A writer that keeps the CRC of everything written through it.
struct CrcWriter<'a, W: Write> {
    inner: &'a mut W,
    crc: crc32fast::Hasher,
}

impl<W: Write> CrcWriter<'_, W> {
    fn put(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.crc.update(bytes);
        self.inner.write_all(bytes)
    }
}

/// Writes the whole file to `w`.
pub(crate) fn write<W: Write>(
    w: &mut W,
    header: &Header,
    coords: &[[i32; 3]],
    voxels: &[Voxel],
) -> std::io::Result<()> {
    let mut out = CrcWriter {
        inner: w,
        crc: crc32fast::Hasher::new(),
    };
    let p = &header.params;
    let c = &header.camera;
    let mut head = Vec::with_capacity(HEADER_BYTES as usize);
    head.extend_from_slice(MAGIC);
    head.extend_from_slice(&VERSION.to_le_bytes());
    for v in [
        p.voxel_size,
        p.rho_sigma,
        p.trunc_min_voxels,
        p.trunc_sigmas,
    ] {
        head.extend_from_slice(&v.to_le_bytes());
    }
    head.extend_from_slice(&p.max_weight.to_le_bytes());
    for v in [p.min_depth, p.max_depth, c.fx, c.fy, c.cx, c.cy] {
        head.extend_from_slice(&v.to_le_bytes());
    }
    head.extend_from_slice(&c.width.to_le_bytes());
    head.extend_from_slice(&c.height.to_le_bytes());
    head.extend_from_slice(&header.frames.to_le_bytes());
    head.extend_from_slice(&(coords.len() as u64).to_le_bytes());
    debug_assert_eq!(head.len() as u64, HEADER_BYTES);
    out.put(&head)?;
    let mut buf: Vec<u8> = Vec::with_capacity(1 << 16);
    for chunk in coords.chunks(4096) {
        buf.clear();
        for b in chunk {
            for v in b {
                buf.extend_from_slice(&v.to_le_bytes());
            }
        }
        out.put(&buf)?;
    }
    for chunk in voxels.chunks(BLOCK_VOXELS * 8) {
        buf.clear();
        for v in chunk {
            buf.extend_from_slice(&v.tsdf.to_le_bytes());
            buf.extend_from_slice(&v.weight.to_le_bytes());
            buf.extend_from_slice(&v.rgb.to_le_bytes());
        }
        out.put(&buf)?;
    }
    let crc = out.crc.finalize();
    out.inner.write_all(&crc.to_le_bytes())
}

/// A reader that keeps the CRC of everything read through it and names the file in errors.
struct CrcReader<'a, R: Read> {
    inner: R,
    crc: crc32fast::Hasher,
    path: &'a Path,
}

impl<R: Read> CrcReader<'_, R> {
    fn fill(&mut self, buf: &mut [u8], what: &str) -> Result<(), TsdfError> {
        self.inner.read_exact(buf).map_err(|e| {
            if e.kind() == std::io::ErrorKind::UnexpectedEof {
                malformed(self.path, format!("truncated in the {what}"))
            } else {
                IoError::file(self.path, e).into()
            }
        })?;
        self.crc.update(buf);
        Ok(())
    }
}

fn malformed(path: &Path, message: impl Into<String>) -> TsdfError {
    TsdfError::Io(IoError::Malformed {
        path: path.to_path_buf(),
        message: message.into(),
    })
}

/// Little-endian fields from a byte slice, in order.
struct Fields<'a>(&'a [u8]);

impl Fields<'_> {
    fn take<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0u8; N];
        let (head, rest) = self.0.split_at(N.min(self.0.len()));
        out[..head.len()].copy_from_slice(head);
        self.0 = rest;
        out
    }
    fn f64(&mut self) -> f64 {
        f64::from_le_bytes(self.take())
    }
    fn f32(&mut self) -> f32 {
        f32::from_le_bytes(self.take())
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
}

/// A file's content: header, block coordinates per slot, voxels slot after slot.
pub(crate) type Contents = (Header, Vec<[i32; 3]>, Vec<Voxel>);

/// Reads and checks a whole file: header, block coordinates (within the key range, no block
/// twice) and voxels (finite distance, finite non-negative weight, 24-bit colour), and the
/// CRC. Errors name `path` and the cause.
pub(crate) fn read(path: &Path) -> Result<Contents, TsdfError> {
    let file = std::fs::File::open(path).map_err(|e| IoError::file(path, e))?;
    let len = file.metadata().map_err(|e| IoError::file(path, e))?.len();
    let mut r = CrcReader {
        inner: std::io::BufReader::with_capacity(1 << 16, file),
        crc: crc32fast::Hasher::new(),
        path,
    };
    let mut head = [0u8; HEADER_BYTES as usize];
    if len < 12 {
        return Err(malformed(
            path,
            format!("{len} bytes, too short for a TSDF volume file"),
        ));
    }
    r.fill(&mut head[..12], "header")?;
    if &head[..8] != MAGIC {
        return Err(malformed(
            path,
            "not a TSDF volume file (no RGBIDTSD magic)",
        ));
    }
    let version = u32::from_le_bytes([head[8], head[9], head[10], head[11]]);
    if version != VERSION {
        return Err(malformed(
            path,
            format!("TSDF volume format version {version}; this build reads version {VERSION}"),
        ));
    }
    r.fill(&mut head[12..], "header")?;
    let mut f = Fields(&head[12..]);
    let params = TsdfParams {
        voxel_size: f.f64(),
        rho_sigma: f.f64(),
        trunc_min_voxels: f.f64(),
        trunc_sigmas: f.f64(),
        max_weight: f.f32(),
        min_depth: f.f64(),
        max_depth: f.f64(),
        // A property of the run that loads the file (`TsdfVolume::set_device_blocks`).
        device_blocks: None,
    };
    let (fx, fy, cx, cy) = (f.f64(), f.f64(), f.f64(), f.f64());
    let (width, height) = (f.u32(), f.u32());
    let camera = PinholeCamera::new(fx, fy, cx, cy, width, height);
    let frames = f.u64();
    let blocks = f.u64();
    params
        .validate()
        .map_err(|e| malformed(path, format!("bad volume parameters: {e}")))?;
    camera
        .validate()
        .map_err(|e| malformed(path, format!("bad camera: {e}")))?;
    let expected = blocks
        .checked_mul(BLOCK_BYTES)
        .and_then(|b| b.checked_add(HEADER_BYTES + 4));
    if expected != Some(len) {
        return Err(malformed(
            path,
            format!(
                "the header announces {blocks} blocks, which need {} bytes; the file has {len} \
                 (truncated or corrupt)",
                expected.map_or_else(|| "more than 2^64".to_string(), |e| e.to_string())
            ),
        ));
    }
    // The length matches the file, so these sizes are bounded by what is on disk.
    let blocks = blocks as usize;
    let mut coords = Vec::with_capacity(blocks);
    let mut buf = vec![0u8; 12 * 4096];
    let mut left = blocks;
    while left > 0 {
        let n = left.min(4096);
        let bytes = &mut buf[..12 * n];
        r.fill(bytes, "block coordinates")?;
        for b in bytes.chunks_exact(12) {
            let mut f = Fields(b);
            let c = [f.u32() as i32, f.u32() as i32, f.u32() as i32];
            if c.iter().any(|&v| !(-COORD_LIMIT..COORD_LIMIT).contains(&v)) {
                return Err(malformed(
                    path,
                    format!(
                        "block {} has coordinates {c:?}, beyond the volume's range of 2^20 \
                         blocks",
                        coords.len()
                    ),
                ));
            }
            coords.push(c);
        }
        left -= n;
    }
    let mut voxels: Vec<Voxel> = Vec::with_capacity(blocks * BLOCK_VOXELS);
    let mut buf = vec![0u8; VOXEL_BYTES * BLOCK_VOXELS * 8];
    let mut left = blocks;
    while left > 0 {
        let n = left.min(8);
        let bytes = &mut buf[..VOXEL_BYTES * BLOCK_VOXELS * n];
        r.fill(bytes, "voxels")?;
        for b in bytes.chunks_exact(VOXEL_BYTES) {
            let mut f = Fields(b);
            let v = Voxel {
                tsdf: f.f32(),
                weight: f.f32(),
                rgb: f.u32(),
            };
            if !(v.tsdf.is_finite()
                && v.weight.is_finite()
                && v.weight >= 0.0
                && v.rgb <= 0xFF_FFFF)
            {
                return Err(malformed(
                    path,
                    format!(
                        "voxel {} of block {} is invalid (tsdf {}, weight {}, colour {:#x})",
                        voxels.len() % BLOCK_VOXELS,
                        voxels.len() / BLOCK_VOXELS,
                        v.tsdf,
                        v.weight,
                        v.rgb
                    ),
                ));
            }
            voxels.push(v);
        }
        left -= n;
    }
    let crc = r.crc.clone().finalize();
    let mut tail = [0u8; 4];
    r.inner.read_exact(&mut tail).map_err(|e| {
        if e.kind() == std::io::ErrorKind::UnexpectedEof {
            malformed(path, "truncated before the checksum")
        } else {
            IoError::file(path, e).into()
        }
    })?;
    if u32::from_le_bytes(tail) != crc {
        return Err(malformed(path, "checksum mismatch: the file is corrupt"));
    }
    Ok((
        Header {
            params,
            camera,
            frames,
        },
        coords,
        voxels,
    ))
}

#[cfg(test)]
mod tests {
    use std::path::Path;
    use std::sync::Arc;

    use super::{BLOCK_BYTES, HEADER_BYTES};
    use crate::camera::PinholeCamera;
    use crate::geometry::Se3;
    use crate::gpu::{test_gpu, ComputeBackend};
    use crate::image::RgbdFrame;
    use crate::io::IoError;
    use crate::synth::{
        CameraModel, RenderBackend, Scene, Sequence, SequenceConfig, Trajectory, TrajectoryKind,
    };
    use crate::tsdf::{TsdfError, TsdfParams, TsdfVolume};

    fn camera() -> PinholeCamera {
        PinholeCamera::new(131.25, 131.25, 79.5, 59.5, 160, 120)
    }

    /// Eight noisy frames of a generated office along a handheld path, with colour.
    fn frames() -> Vec<(RgbdFrame, Se3)> {
        let scene = Arc::new(Scene::preset("office", 3).unwrap_or_else(|e| panic!("{e}")));
        let traj = Trajectory::new(TrajectoryKind::Handheld, &scene, 1.0, 3)
            .unwrap_or_else(|e| panic!("{e}"));
        let config = SequenceConfig {
            frames: 8,
            seed: 3,
            ..Default::default()
        };
        Sequence::new(
            scene,
            CameraModel::Pinhole(camera()),
            traj,
            config,
            &RenderBackend::Cpu,
        )
        .unwrap_or_else(|e| panic!("{e}"))
        .map(|f| {
            let f = f.unwrap_or_else(|e| panic!("{e}"));
            (f.frame.to_rgbd_frame(f.timestamp), f.world_from_camera)
        })
        .collect()
    }

    fn params() -> TsdfParams {
        TsdfParams {
            voxel_size: 0.02,
            ..Default::default()
        }
    }

    /// Saving half-way and loading gives the same mesh, ray cast and file; integrating the
    /// rest into the saved and into the loaded volume gives the same voxels and mesh.
    fn round_trip(backend: &ComputeBackend) {
        let frames = frames();
        let (first, rest) = frames.split_at(4);
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let path = dir.path().join("volume.tsdf");
        let mut saved =
            TsdfVolume::new(params(), camera(), backend).unwrap_or_else(|e| panic!("{e}"));
        for (f, p) in first {
            saved.integrate(f, p).unwrap_or_else(|e| panic!("{e}"));
        }
        saved.save(&path).unwrap_or_else(|e| panic!("{e}"));
        let mut loaded = TsdfVolume::load(&path, None, backend).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(loaded.params(), saved.params());
        assert_eq!(loaded.camera(), saved.camera());
        assert_eq!(loaded.frames(), 4);
        assert_eq!(loaded.block_count(), saved.block_count());
        let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
        assert_eq!(
            bytes,
            HEADER_BYTES + 4 + saved.block_count() as u64 * BLOCK_BYTES
        );
        let mesh = saved.extract_mesh().unwrap_or_else(|e| panic!("{e}"));
        assert!(
            mesh.triangles.len() > 1000,
            "{} triangles",
            mesh.triangles.len()
        );
        assert_eq!(
            loaded.extract_mesh().unwrap_or_else(|e| panic!("{e}")),
            mesh
        );
        let pose = &rest[0].1;
        let a = saved
            .ray_cast(&camera(), pose)
            .unwrap_or_else(|e| panic!("{e}"));
        let b = loaded
            .ray_cast(&camera(), pose)
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(a.depth.data().iter().filter(|&&d| d > 0.0).count() > 5000);
        assert_eq!(a.depth.data(), b.depth.data());
        assert_eq!(a.normals, b.normals);
        assert_eq!(a.colours, b.colours);
        // Saving the loaded volume writes the same bytes.
        let again = dir.path().join("again.tsdf");
        loaded.save(&again).unwrap_or_else(|e| panic!("{e}"));
        assert!(std::fs::read(&path).ok() == std::fs::read(&again).ok());
        for (f, p) in rest {
            saved.integrate(f, p).unwrap_or_else(|e| panic!("{e}"));
            loaded.integrate(f, p).unwrap_or_else(|e| panic!("{e}"));
        }
        assert_eq!(loaded.frames(), 8);
        assert_eq!(loaded.block_count(), saved.block_count());
        let va = saved.kernels_voxels();
        let vb = loaded.kernels_voxels();
        assert_eq!(va.len(), vb.len());
        assert!(va == vb, "voxels differ after further integration");
        assert_eq!(
            saved.extract_mesh().unwrap_or_else(|e| panic!("{e}")),
            loaded.extract_mesh().unwrap_or_else(|e| panic!("{e}"))
        );
    }

    #[test]
    fn tsdf_volume_save_load_round_trip_continues_exactly() {
        round_trip(&ComputeBackend::Cpu);
    }

    #[test]
    #[ignore = "needs a GPU adapter"]
    fn gpu_tsdf_volume_save_load_round_trip_continues_exactly() {
        let Some(ctx) = test_gpu("gpu_tsdf_volume_save_load_round_trip_continues_exactly") else {
            return;
        };
        round_trip(&ComputeBackend::Gpu(ctx));
    }

    fn load_err(path: &Path) -> String {
        match TsdfVolume::load(path, None, &ComputeBackend::Cpu) {
            Ok(_) => panic!("{} loaded", path.display()),
            Err(e @ TsdfError::Io(IoError::Malformed { .. } | IoError::File { .. })) => {
                let m = e.to_string();
                assert!(m.contains(&path.display().to_string()), "{m}");
                m
            }
            Err(e) => panic!("unexpected error {e:?}"),
        }
    }

    #[test]
    fn corrupt_tsdf_volume_files_are_errors_naming_file_and_cause() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let good = dir.path().join("good.tsdf");
        let mut vol = TsdfVolume::new(params(), camera(), &ComputeBackend::Cpu)
            .unwrap_or_else(|e| panic!("{e}"));
        for (f, p) in frames().iter().take(1) {
            vol.integrate(f, p).unwrap_or_else(|e| panic!("{e}"));
        }
        vol.save(&good).unwrap_or_else(|e| panic!("{e}"));
        let bytes = std::fs::read(&good).unwrap_or_else(|e| panic!("{e}"));
        assert!(vol.block_count() > 10);
        let write = |name: &str, b: &[u8]| {
            let p = dir.path().join(name);
            std::fs::write(&p, b).unwrap_or_else(|e| panic!("{e}"));
            p
        };
        let m = load_err(&dir.path().join("missing.tsdf"));
        assert!(m.contains("No such file") || m.contains("not found"), "{m}");
        let m = load_err(&write("empty.tsdf", &[]));
        assert!(m.contains("too short"), "{m}");
        let m = load_err(&write(
            "ply.tsdf",
            b"ply\nformat binary_little_endian 1.0\n",
        ));
        assert!(m.contains("magic"), "{m}");
        let mut v2 = bytes.clone();
        v2[8] = 2;
        let m = load_err(&write("version.tsdf", &v2));
        assert!(m.contains("version 2"), "{m}");
        for cut in [
            100,
            HEADER_BYTES as usize + 5,
            bytes.len() / 2,
            bytes.len() - 1,
        ] {
            let m = load_err(&write("cut.tsdf", &bytes[..cut]));
            assert!(m.contains("truncated"), "{cut}: {m}");
        }
        // A header asking for 2^60 blocks is refused before any allocation.
        let mut huge = bytes.clone();
        huge[112..120].copy_from_slice(&(1u64 << 60).to_le_bytes());
        let m = load_err(&write("huge.tsdf", &huge));
        assert!(m.contains("announces 1152921504606846976 blocks"), "{m}");
        let mut huge = bytes.clone();
        huge[112..120].copy_from_slice(&u64::MAX.to_le_bytes());
        let m = load_err(&write("max.tsdf", &huge));
        assert!(m.contains("more than 2^64"), "{m}");
        // Bad parameters: a negative voxel size.
        let mut neg = bytes.clone();
        neg[12..20].copy_from_slice(&(-0.02f64).to_le_bytes());
        let m = load_err(&write("neg.tsdf", &neg));
        assert!(m.contains("voxel_size"), "{m}");
        // A block beyond the key range, and a block twice.
        let mut far = bytes.clone();
        far[120..124].copy_from_slice(&i32::MAX.to_le_bytes());
        let m = load_err(&write("far.tsdf", &far));
        assert!(m.contains("beyond"), "{m}");
        let mut twice = bytes.clone();
        twice.copy_within(120..132, 132);
        let crc = crc32fast::hash(&twice[..twice.len() - 4]);
        let n = twice.len();
        twice[n - 4..].copy_from_slice(&crc.to_le_bytes());
        let m = load_err(&write("twice.tsdf", &twice));
        assert!(m.contains("twice"), "{m}");
        // A NaN distance, and a flipped colour bit (valid voxel, wrong checksum).
        let voxels = HEADER_BYTES as usize + 12 * vol.block_count();
        let mut nan = bytes.clone();
        nan[voxels..voxels + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        let m = load_err(&write("nan.tsdf", &nan));
        assert!(m.contains("voxel 0 of block 0 is invalid"), "{m}");
        let mut flip = bytes.clone();
        flip[voxels + 8] ^= 1;
        let m = load_err(&write("flip.tsdf", &flip));
        assert!(m.contains("checksum"), "{m}");
    }
}
