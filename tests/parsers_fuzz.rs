//! Property tests of every file parser (trajectories in TUM, KITTI and EuRoC form, camera files
//! in every form, configurations, g2o, iSAM, TUM lists and the other layouts' folders, PLY,
//! run folders, vocabularies, maps): random bytes and mutations of a valid file (flipped
//! bytes, cuts, repeated spans) never panic, never allocate more than 64 times the input plus
//! 64 MB (a counting global allocator, per thread), and their errors name the file, with the
//! line for text formats and the byte offset for binary ones.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::Path;

use proptest::prelude::*;
use rgbid::graph::g2o::parse_g2o;
use rgbid::graph::isam::parse_isam;
use rgbid::io::CameraConfig;

/// Counts the bytes this thread holds and the peak since the last [`start`].
struct Counting;

thread_local! {
    static HELD: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
}

fn note(delta: isize) {
    // `try_with`: the allocator also runs while thread-locals are torn down.
    let _ = HELD.try_with(|h| {
        let now = h.get() + delta;
        h.set(now);
        let _ = PEAK.try_with(|p| p.set(p.get().max(now)));
    });
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note(layout.size() as isize);
        System.alloc(layout)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        note(-(layout.size() as isize));
        System.dealloc(ptr, layout)
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note(new_size as isize - layout.size() as isize);
        System.realloc(ptr, layout, new_size)
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Runs `f` and returns its result and the most bytes it held at once on this thread.
fn measured<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let base = HELD.with(|h| h.get());
    PEAK.with(|p| p.set(base));
    let out = f();
    let peak = PEAK.with(|p| p.get());
    (out, (peak - base).max(0) as usize)
}

fn bound(input: usize) -> usize {
    64 * input + (64 << 20)
}

/// `valid` with byte edits, an optional cut and an optional repeated span.
fn mutated(valid: &[u8]) -> impl Strategy<Value = Vec<u8>> {
    let n = valid.len().max(1);
    let valid = valid.to_vec();
    (
        proptest::collection::vec((0..n, any::<u8>()), 0..8),
        proptest::option::of(0..n),
        proptest::option::of((0..n, 0..n)),
    )
        .prop_map(move |(edits, cut, repeat)| {
            let mut b = valid.clone();
            for (i, v) in edits {
                if i < b.len() {
                    b[i] = v;
                }
            }
            if let Some((a, z)) = repeat {
                let (a, z) = (a.min(z), a.max(z).min(b.len()));
                let span = b[a..z].to_vec();
                b.splice(a..a, span);
            }
            if let Some(c) = cut {
                b.truncate(c);
            }
            b
        })
}

/// Random bytes, random printable text, or a mutation of `valid`.
fn inputs(valid: &'static [u8]) -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![
        proptest::collection::vec(any::<u8>(), 0..512),
        "[ -~\n\t]{0,400}".prop_map(String::into_bytes),
        mutated(valid),
    ]
}

fn config() -> ProptestConfig {
    ProptestConfig {
        cases: 64,
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

/// Checks a text parser's error: names the file and, for a parse error, the line.
fn names_file(e: &str, file: &str) -> Result<(), TestCaseError> {
    prop_assert!(e.contains(file), "error without the file name: {e}");
    Ok(())
}

const TRAJECTORY: &[u8] =
    b"# t x y z qx qy qz qw\n1.0 0 0 0 0 0 0 1\n2.0 1 2 3 0 0 0.7071 0.7071\n";
const CAMERA: &[u8] =
    b"# camera\nfx = 525\nfy = 525\ncx = 319.5\ncy = 239.5\nwidth = 640\nheight = 480\ndepth_factor = 5000\nk1 = 0.01\n";
const G2O: &[u8] =
    b"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.1\nEDGE_SE2 0 1 1 0 0.1 10 0 0 10 0 100\nFIX 0\n";
const G2O3: &[u8] = b"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n";
const ISAM: &[u8] = b"POSE2D 0 0 0 0\nPOSE2D 1 1 0 0\nEDGE2 0 1 1 0 0 10 0 0 10 0 100\n";
const SLAM_TOML: &[u8] =
    b"masks = false\nkeyframe_covisibility = 0.6\n[odometry]\nlevels = 3\nestimator = \"huber\"\n";
const DROID_CALIB: &[u8] =
    b"# fx fy cx cy k1 k2 p1 p2 k3\n517.3 516.5 318.6 255.3 0.2624 -0.9531 -0.0054 0.0026 1.1633\n";
const RGB_LIST: &[u8] = b"# rgb\n0.0 rgb/0.png\n0.1 rgb/1.png\n";

proptest! {
    #![proptest_config(config())]

    #[test]
    fn trajectories(bytes in inputs(TRAJECTORY)) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("traj.txt");
        std::fs::write(&p, &bytes).unwrap();
        let (r, peak) = measured(|| rgbid::io::trajectory::read_tum(&p));
        prop_assert!(peak <= bound(bytes.len()), "{peak} bytes");
        if let Err(e) = r {
            names_file(&e.to_string(), "traj.txt")?;
        }
    }

    #[test]
    fn camera_files(bytes in inputs(CAMERA)) {
        let text = String::from_utf8_lossy(&bytes);
        let (r, peak) = measured(|| CameraConfig::parse_config(&text, Path::new("cam.cfg")));
        prop_assert!(peak <= bound(bytes.len()), "{peak} bytes");
        if let Err(e) = r {
            names_file(&e.to_string(), "cam.cfg")?;
        }
    }

    #[test]
    fn droid_calibration_files(bytes in inputs(DROID_CALIB)) {
        let text = String::from_utf8_lossy(&bytes);
        let (r, peak) = measured(|| {
            CameraConfig::parse_droid(&text, Path::new("calib.txt"), 640, 480, 5000.0)
        });
        prop_assert!(peak <= bound(bytes.len()), "{peak} bytes");
        if let Err(e) = r {
            names_file(&e.to_string(), "calib.txt")?;
        }
    }

    #[test]
    fn g2o_files(bytes in prop_oneof![inputs(G2O), inputs(G2O3)]) {
        let text = String::from_utf8_lossy(&bytes);
        let (r, peak) = measured(|| parse_g2o(&text, Path::new("g.g2o")));
        prop_assert!(peak <= bound(bytes.len()), "{peak} bytes");
        if let Err(e) = r {
            let e = e.to_string();
            names_file(&e, "g.g2o")?;
        }
    }

    #[test]
    fn isam_files(bytes in inputs(ISAM)) {
        let text = String::from_utf8_lossy(&bytes);
        let (r, peak) = measured(|| parse_isam(&text, Path::new("g.isam")));
        prop_assert!(peak <= bound(bytes.len()), "{peak} bytes");
        if let Err(e) = r {
            names_file(&e.to_string(), "g.isam")?;
        }
    }

    #[test]
    fn configuration_files(bytes in inputs(SLAM_TOML), json in any::<bool>()) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join(if json { "c.json" } else { "c.toml" });
        std::fs::write(&p, &bytes).unwrap();
        let base = rgbid::slam::SlamConfig::default();
        let (r, peak) = measured(|| rgbid::io::settings::load_file(&base, &p));
        prop_assert!(peak <= bound(bytes.len()), "{peak} bytes");
        if let Err(e) = r {
            names_file(&e.to_string(), if json { "c.json" } else { "c.toml" })?;
        }
    }

    #[test]
    fn tum_lists(bytes in inputs(RGB_LIST)) {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("rgb.txt"), &bytes).unwrap();
        std::fs::write(dir.path().join("depth.txt"), &bytes).unwrap();
        let (r, peak) = measured(|| {
            rgbid::io::TumSequence::open(dir.path(), &rgbid::io::OpenOptions::default())
        });
        prop_assert!(peak <= bound(bytes.len()), "{peak} bytes");
        // No images exist: every outcome is an error naming a file (of the folder, or an
        // absolute path a mutated list names).
        let e = r.err().map(|e| e.to_string()).unwrap_or_default();
        prop_assert!(e.contains('/'), "{e}");
    }

    #[test]
    fn vocabularies(bytes in prop_oneof![
        proptest::collection::vec(any::<u8>(), 0..512),
        mutated(include_bytes!("../assets/vocab_default.rgbvoc")),
    ]) {
        let (r, peak) = measured(|| rgbid::place::Vocabulary::read_binary(&bytes));
        prop_assert!(peak <= bound(bytes.len()), "{peak} bytes");
        if let Err(e) = r {
            let e = e.to_string();
            prop_assert!(e.contains("byte") || e.contains("magic") || e.contains("node count"), "{e}");
        }
        let text = String::from_utf8_lossy(&bytes);
        let (_, peak) = measured(|| rgbid::place::Vocabulary::read_dbow2_text(text.as_bytes()));
        prop_assert!(peak <= bound(bytes.len()), "{peak} bytes");
    }
}

const PLY_ASCII: &[u8] = b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n1 2 3 10 20 30\n-1 0.5 2 0 0 0\n3 0 1 1\n";
const KITTI: &[u8] = b"1 0 0 0 0 1 0 0 0 0 1 0\n0 -1 0 1 1 0 0 2 0 0 1 3\n";
const KITTI_TIMES: &[u8] = b"0.0\n0.1\n";
const EUROC: &[u8] = b"#timestamp [ns],p_x,p_y,p_z,q_w,q_x,q_y,q_z\n1403636579763555584,0,0,0,1,0,0,0\n1403636579813555456,1,2,3,0.7071,0,0,0.7071\n";
const OPENCV_YAML: &[u8] = b"%YAML:1.0\n---\nCamera.type: \"PinHole\"\nCamera.fx: 517.3\nCamera.fy: 516.5\nCamera.cx: 318.6\nCamera.cy: 255.3\nCamera.k1: 0.26\nCamera.k2: -0.95\nCamera.p1: -0.005\nCamera.p2: 0.002\nCamera.width: 640\nCamera.height: 480\nDepthMapFactor: 5000.0\n";
const CALIB_TXT: &[u8] = b"525 525 319.5 239.5 5000 640 480\n";
const SUMMARY: &[u8] = br#"{"format_version": 1, "complete": true, "status": "complete", "frames": 2, "tracked": 2, "wall_s": 0.5}"#;
const TIMING: &[u8] = b"index,timestamp,status,frontend_ms,pyramid_ms,scale_ms,reduce_ms,solve_ms,covisibility_ms,fusion_ms,covisibility,keyframe_covisibility,sigma_photo\n0,0.0,NewKeyframe,1,0.1,0.2,0.3,0.4,0.5,0.6,1,1,\n1,0.1,Tracking,1,0.1,0.2,0.3,0.4,0.5,0.6,0.9,0.8,4.5\n";
const LOOPS: &[u8] = b"query,candidate,inliers,refine_translation_m,refine_rotation_rad,covisibility,accepted,relocalisation,reason\n9,2,40,0.01,0.01,0.8,true,false,\"ok, fine\"\n";
const KEYFRAME_TIMING: &[u8] =
    b"id,segment_ms,describe_ms,query_ms,align_ms,optimise_ms,total_ms\n1,10,5,1,0,0,16\n";
/// A 4x4 camera-to-world matrix, row by row (7-Scenes and ScanNet pose files).
const POSE_4X4: &[u8] = b"1 0 0 0.5\n0 1 0 -0.25\n0 0 1 1\n0 0 0 1\n";
/// ScanNet's intrinsic matrix for 32 x 24 images.
const INTRINSIC: &[u8] = b"30 0 15.5 0\n0 30 11.5 0\n0 0 1 0\n0 0 0 1\n";
/// Replica's `traj.txt`: one row-major 4x4 per line.
const REPLICA_TRAJ: &[u8] = b"1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n1 0 0 0.1 0 1 0 0 0 0 1 0 0 0 0 1\n";
/// ETH3D's `calibration.txt` for 32 x 24 images.
const ETH3D_CALIBRATION: &[u8] = b"30 30 15.5 11.5\n";

/// The bytes of a binary PLY file as `write_ply` writes it.
fn binary_ply() -> &'static [u8] {
    static BYTES: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    BYTES.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("b.ply");
        let pts = [
            (glam::DVec3::new(1.0, 2.0, 3.0), [1u8, 2, 3]),
            (glam::DVec3::new(-1.0, 0.5, 4.0), [200, 100, 50]),
        ];
        rgbid::io::ply::write_ply(&p, &pts).unwrap();
        std::fs::read(&p).unwrap()
    })
}

/// Writes a 32 x 24 grey image (JPEG or PNG, as its name says) and a 16-bit PNG depth image
/// (every pixel `depth`).
fn frame_images(colour: &Path, depth_path: &Path, depth: u16) {
    for p in [colour, depth_path] {
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
    }
    image::GrayImage::from_pixel(32, 24, image::Luma([128]))
        .save(colour)
        .unwrap();
    image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_pixel(32, 24, image::Luma([depth]))
        .save_with_format(depth_path, image::ImageFormat::Png)
        .unwrap();
}

/// Opens a sequence folder of `layout` and reads its ground truth; the error, if any, must
/// name a file or folder inside `dir`.
fn open_layout(
    dir: &Path,
    layout: rgbid::io::Layout,
    camera: Option<CameraConfig>,
    input: usize,
) -> Result<(), TestCaseError> {
    let opts = rgbid::io::OpenOptions {
        layout: Some(layout),
        camera,
        ..Default::default()
    };
    let (r, peak) = measured(|| {
        rgbid::io::TumSequence::open(dir, &opts).and_then(|seq| seq.ground_truth().map(|_| ()))
    });
    // Decoding the frame images holds a few of their copies beside the text.
    prop_assert!(peak <= bound(input), "{peak} bytes");
    if let Err(e) = r {
        let e = e.to_string();
        prop_assert!(
            e.contains(&*dir.to_string_lossy()),
            "error without a path: {e}"
        );
    }
    Ok(())
}

/// A small camera for layouts whose preset has a large image size.
fn small_camera(depth_factor: f64) -> CameraConfig {
    CameraConfig {
        camera: rgbid::camera::PinholeCamera::new(30.0, 30.0, 15.5, 11.5, 32, 24),
        depth_factor,
        source: "the test's camera".into(),
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 32, ..config() })]

    #[test]
    fn ply_files(bytes in prop_oneof![inputs(PLY_ASCII), inputs(binary_ply())], reader in 0..3usize) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        std::fs::write(&p, &bytes).unwrap();
        let (r, peak) = measured(|| match reader {
            0 => rgbid::io::ply::read_ply_grey(&p).map(|v| v.len()),
            1 => rgbid::io::ply::read_ply(&p).map(|v| v.len()),
            _ => rgbid::io::ply::read_mesh_ply(&p).map(|m| m.vertices.len() + m.triangles.len()),
        });
        prop_assert!(peak <= bound(bytes.len()), "{peak} bytes");
        if let Err(e) = r {
            let e = e.to_string();
            names_file(&e, "m.ply")?;
            // A complaint about one vertex, one face or the body says where.
            if e.contains("vertex ") && !e.contains("vertex element") || e.contains("face ") && !e.contains("face element") || e.contains("ends early") {
                prop_assert!(e.contains("line ") || e.contains("at byte "), "{e}");
            }
        }
    }

    #[test]
    fn trajectory_formats(
        bytes in prop_oneof![inputs(KITTI), inputs(EUROC), inputs(TRAJECTORY)],
        times in inputs(KITTI_TIMES),
        format in 0..4usize,
    ) {
        use rgbid::io::trajectory::{read_trajectory, read_trajectory_as, TrajectoryFormat};
        let dir = tempfile::tempdir().unwrap();
        let (name, format) = match format {
            0 => ("traj.kitti", Some(TrajectoryFormat::Kitti)),
            1 => ("traj.csv", Some(TrajectoryFormat::Euroc)),
            2 => ("traj.txt", Some(TrajectoryFormat::Tum)),
            _ => ("traj.txt", None),
        };
        let p = dir.path().join(name);
        std::fs::write(&p, &bytes).unwrap();
        std::fs::write(dir.path().join("traj.times.txt"), &times).unwrap();
        let (r, peak) = measured(|| match format {
            Some(f) => read_trajectory_as(&p, f),
            None => read_trajectory(&p),
        });
        prop_assert!(peak <= bound(bytes.len() + times.len()), "{peak} bytes");
        if let Err(e) = r {
            let e = e.to_string();
            prop_assert!(e.contains(name) || e.contains("traj.times.txt"), "{e}");
        }
    }

    #[test]
    fn opencv_yaml_and_calib_txt_camera_files(
        yaml in inputs(OPENCV_YAML),
        calib in inputs(CALIB_TXT),
    ) {
        let text = String::from_utf8_lossy(&yaml);
        let (r, peak) =
            measured(|| CameraConfig::parse_opencv_yaml(&text, Path::new("cam.yaml")));
        prop_assert!(peak <= bound(yaml.len()), "{peak} bytes");
        if let Err(e) = r {
            names_file(&e.to_string(), "cam.yaml")?;
        }
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.txt");
        std::fs::write(&p, &calib).unwrap();
        let (r, peak) = measured(|| CameraConfig::from_calib_txt(&p));
        prop_assert!(peak <= bound(calib.len()), "{peak} bytes");
        if let Err(e) = r {
            names_file(&e.to_string(), "calib.txt")?;
        }
    }

    #[test]
    fn run_folders(
        bytes in prop_oneof![
            inputs(SUMMARY), inputs(TIMING), inputs(LOOPS), inputs(KEYFRAME_TIMING),
            inputs(TRAJECTORY), inputs(PLY_ASCII),
        ],
        which in 0..7usize,
    ) {
        use rgbid::io::run_folder::{files, RunFolder};
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let valid: [(&str, &[u8]); 7] = [
            (files::SUMMARY, SUMMARY),
            (files::TIMING, TIMING),
            (files::LOOPS, LOOPS),
            (files::KEYFRAME_TIMING, KEYFRAME_TIMING),
            (files::TRAJECTORY, TRAJECTORY),
            (files::MODEL, PLY_ASCII),
            (files::KEYFRAMES, TRAJECTORY),
        ];
        for (i, (name, content)) in valid.iter().enumerate() {
            std::fs::write(d.join(name), if i == which { &bytes[..] } else { content }).unwrap();
        }
        let total: usize = valid.iter().map(|(_, c)| c.len()).sum::<usize>() + bytes.len();
        let (r, peak) = measured(|| RunFolder::read(d));
        prop_assert!(peak <= bound(total), "{peak} bytes");
        if let Err(e) = r {
            let e = e.to_string();
            names_file(&e, valid[which].0)?;
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 16, ..config() })]

    #[test]
    fn eth3d_folders(text in inputs(ETH3D_CALIBRATION), truth in inputs(TRAJECTORY), which in any::<bool>()) {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        frame_images(&d.join("rgb/0.png"), &d.join("depth/0.png"), 5000);
        frame_images(&d.join("rgb/1.png"), &d.join("depth/1.png"), 5000);
        std::fs::write(d.join("rgb.txt"), "0.0 rgb/0.png\n0.1 rgb/1.png\n").unwrap();
        std::fs::write(d.join("depth.txt"), "0.0 depth/0.png\n0.1 depth/1.png\n").unwrap();
        let (calibration, gt): (&[u8], &[u8]) =
            if which { (&text, TRAJECTORY) } else { (ETH3D_CALIBRATION, &truth) };
        std::fs::write(d.join("calibration.txt"), calibration).unwrap();
        std::fs::write(d.join("groundtruth.txt"), gt).unwrap();
        open_layout(d, rgbid::io::Layout::Eth3d, None, text.len() + truth.len())?;
    }

    #[test]
    fn seven_scenes_folders(pose in inputs(POSE_4X4)) {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        for i in 0..2 {
            frame_images(
                &d.join(format!("frame-{i:06}.color.png")),
                &d.join(format!("frame-{i:06}.depth.png")),
                1000,
            );
        }
        std::fs::write(d.join("frame-000000.pose.txt"), POSE_4X4).unwrap();
        std::fs::write(d.join("frame-000001.pose.txt"), &pose).unwrap();
        open_layout(d, rgbid::io::Layout::SevenScenes, Some(small_camera(1000.0)), pose.len())?;
    }

    #[test]
    fn scannet_folders(text in prop_oneof![inputs(INTRINSIC), inputs(POSE_4X4)], which in 0..3usize) {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        for i in 0..2 {
            frame_images(
                &d.join(format!("color/{i}.jpg")),
                &d.join(format!("depth/{i}.png")),
                1000,
            );
        }
        let files: [(&str, &[u8]); 3] = [
            ("intrinsic/intrinsic_depth.txt", INTRINSIC),
            ("intrinsic/intrinsic_color.txt", INTRINSIC),
            ("pose/1.txt", POSE_4X4),
        ];
        std::fs::create_dir_all(d.join("intrinsic")).unwrap();
        std::fs::create_dir_all(d.join("pose")).unwrap();
        std::fs::write(d.join("pose/0.txt"), POSE_4X4).unwrap();
        for (i, (name, content)) in files.iter().enumerate() {
            std::fs::write(d.join(name), if i == which { &text[..] } else { content }).unwrap();
        }
        open_layout(d, rgbid::io::Layout::ScanNet, None, text.len())?;
    }

    #[test]
    fn replica_folders(traj in inputs(REPLICA_TRAJ)) {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        for i in 0..2 {
            frame_images(
                &d.join(format!("results/frame{i:06}.jpg")),
                &d.join(format!("results/depth{i:06}.png")),
                6553,
            );
        }
        std::fs::write(d.join("traj.txt"), &traj).unwrap();
        open_layout(d, rgbid::io::Layout::Replica, Some(small_camera(6553.5)), traj.len())?;
    }
}

/// A PLY header that declares four billion vertices over an empty body reserves nothing for
/// them.
#[test]
fn a_huge_declared_vertex_count_allocates_little() {
    let dir = tempfile::tempdir().unwrap();
    for format in ["ascii", "binary_little_endian"] {
        let p = dir.path().join("big.ply");
        let header = format!(
            "ply\nformat {format} 1.0\nelement vertex 4000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        );
        std::fs::write(&p, &header).unwrap();
        let (r, peak) = measured(|| rgbid::io::ply::read_ply(&p));
        let e = r.unwrap_err().to_string();
        assert!(e.contains("big.ply") && e.contains("ends early"), "{e}");
        assert!(peak < 1 << 20, "{format}: {peak} bytes");
    }
}

/// A saved map of a short generated run, mutated: loads or fails with the byte offset, never
/// panics, never allocates beyond the bound.
#[test]
fn maps() {
    use rgbid::slam::Map;
    let dir = tempfile::tempdir().unwrap();
    let valid = dir.path().join("valid.rgbmap");
    small_map_file(&valid);
    let valid_bytes = std::fs::read(&valid).unwrap();
    let mut runner = proptest::test_runner::TestRunner::new(ProptestConfig {
        cases: 48,
        failure_persistence: None,
        ..ProptestConfig::default()
    });
    let strategy = prop_oneof![
        proptest::collection::vec(any::<u8>(), 0..512),
        mutated(&valid_bytes),
    ];
    let p = dir.path().join("m.rgbmap");
    runner
        .run(&strategy, |bytes| {
            std::fs::write(&p, &bytes).unwrap();
            let (r, peak) = measured(|| Map::load(&p));
            prop_assert!(peak <= bound(bytes.len()), "{peak} bytes");
            if let Err(e) = r {
                let e = e.to_string();
                prop_assert!(e.contains("m.rgbmap"), "{e}");
                prop_assert!(
                    e.contains("at byte")
                        || e.contains("not an rgbid map")
                        || e.contains("version"),
                    "{e}"
                );
            }
            Ok(())
        })
        .unwrap();
}

/// Writes the map of a few generated frames.
fn small_map_file(path: &Path) {
    use rgbid::gpu::{select_backend, BackendChoice};
    use rgbid::place::Vocabulary;
    use rgbid::slam::{Slam, SlamConfig};
    use rgbid::source::{FrameSource, SynthOptions};
    let backend = select_backend(BackendChoice::Cpu, None).unwrap();
    let opts = SynthOptions {
        frames: 12,
        width: 160,
        ..SynthOptions::default()
    };
    let spec = opts
        .spec_of(rgbid::source::SynthOptions::DEFAULT_SPEC, 0, None)
        .unwrap();
    let mut source = FrameSource::open(&spec, &backend).unwrap();
    let mut slam = Slam::new(
        SlamConfig::default(),
        source.camera(),
        &backend,
        Vocabulary::embedded_default().unwrap(),
        None,
    )
    .unwrap();
    for i in 0..source.len() {
        slam.process(&source.load(i).unwrap()).unwrap();
    }
    slam.finish().unwrap().map.save(path).unwrap();
}

/// The counter sees what a closure holds at its peak, freed or not.
#[test]
fn the_counter_sees_allocations() {
    let ((), peak) = measured(|| {
        let v = vec![1u8; 1 << 20];
        std::hint::black_box(&v);
    });
    assert!(peak >= 1 << 20, "{peak}");
    let (v, peak) = measured(|| vec![0u64; 1000]);
    assert!(peak >= 8000 && v.len() == 1000, "{peak}");
}
