//! Every kind of bad input to the sequence reader gives its own `IoError`, whose message names
//! the file (and line, for text files) and the cause. Nothing panics.

use std::path::Path;

use rgbid::camera::PinholeCamera;
use rgbid::io::{load_pair_frame, CameraConfig, IoError, OpenOptions, TumSequence};

const W: u32 = 16;
const H: u32 = 12;

fn rgb_png(path: &Path, w: u32, h: u32) {
    image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([(x * 10) as u8, (y * 10) as u8, 50])
    })
    .save(path)
    .unwrap();
}

fn depth_png(path: &Path, w: u32, h: u32, raw: u16) {
    image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |_, _| image::Luma([raw]))
        .save(path)
        .unwrap();
}

/// A valid 2-frame sequence (2 m depth at factor 5000) in rgb.txt/depth.txt layout.
fn good_sequence(dir: &Path) {
    std::fs::create_dir_all(dir.join("rgb")).unwrap();
    std::fs::create_dir_all(dir.join("depth")).unwrap();
    for i in 0..2 {
        rgb_png(&dir.join(format!("rgb/{i}.png")), W, H);
        depth_png(&dir.join(format!("depth/{i}.png")), W, H, 10000);
    }
    std::fs::write(dir.join("rgb.txt"), "# rgb\n0.0 rgb/0.png\n0.1 rgb/1.png\n").unwrap();
    std::fs::write(
        dir.join("depth.txt"),
        "# depth\n0.001 depth/0.png\n0.101 depth/1.png\n",
    )
    .unwrap();
}

fn opts() -> OpenOptions {
    let camera = PinholeCamera::new(20.0, 20.0, 7.5, 5.5, W, H);
    OpenOptions {
        camera: Some(CameraConfig {
            camera,
            depth_factor: 5000.0,
            source: "test camera".into(),
        }),
        ..Default::default()
    }
}

fn open_err(dir: &Path) -> (IoError, String) {
    let e = TumSequence::open(dir, &opts()).unwrap_err();
    let s = e.to_string();
    (e, s)
}

#[test]
fn good_sequence_opens() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    let seq = TumSequence::open(tmp.path(), &opts()).unwrap();
    assert_eq!(seq.len(), 2);
    assert!(seq.load(1).is_ok());
}

#[test]
fn missing_folder() {
    let (e, s) = open_err(Path::new("/nonexistent/rgbid-seq"));
    assert!(matches!(e, IoError::MissingFolder { .. }));
    assert!(
        s.contains("/nonexistent/rgbid-seq") && s.contains("not found"),
        "{s}"
    );
}

#[test]
fn missing_lists() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    std::fs::remove_file(tmp.path().join("depth.txt")).unwrap();
    let (e, s) = open_err(tmp.path());
    assert!(matches!(e, IoError::MissingFile { .. }));
    assert!(s.contains("depth.txt") && s.contains("missing"), "{s}");
}

#[test]
fn missing_image_names_list_line() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    std::fs::remove_file(tmp.path().join("rgb/1.png")).unwrap();
    let (e, s) = open_err(tmp.path());
    assert!(matches!(e, IoError::MissingFile { .. }));
    assert!(s.contains("rgb/1.png") && s.contains("rgb.txt:3"), "{s}");
}

#[test]
fn corrupt_and_truncated_images() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    let seq = TumSequence::open(tmp.path(), &opts()).unwrap();
    std::fs::write(tmp.path().join("rgb/1.png"), b"this is not an image at all").unwrap();
    let e = seq.load(1).unwrap_err();
    let s = e.to_string();
    assert!(matches!(e, IoError::Image { .. }), "{s}");
    assert!(
        s.contains("rgb/1.png") && s.contains("cannot decode"),
        "{s}"
    );

    // A PNG cut in half.
    let bytes = std::fs::read(tmp.path().join("depth/0.png")).unwrap();
    std::fs::write(tmp.path().join("depth/1.png"), &bytes[..bytes.len() / 2]).unwrap();
    rgb_png(&tmp.path().join("rgb/1.png"), W, H);
    let e = seq.load(1).unwrap_err();
    let s = e.to_string();
    assert!(matches!(e, IoError::Image { .. }), "{s}");
    assert!(s.contains("depth/1.png"), "{s}");

    // A corrupt first frame is reported by open itself.
    std::fs::write(
        tmp.path().join("rgb/0.png"),
        [0x89, b'P', b'N', b'G', 0, 0, 0],
    )
    .unwrap();
    let (e, s) = open_err(tmp.path());
    assert!(matches!(e, IoError::Image { .. }), "{s}");
}

#[test]
fn colour_depth_size_mismatch() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    depth_png(&tmp.path().join("depth/0.png"), W / 2, H / 2, 10000);
    let (e, s) = open_err(tmp.path());
    assert!(matches!(e, IoError::ImageSizeMismatch { .. }), "{s}");
    assert!(
        s.contains("rgb/0.png")
            && s.contains("depth/0.png")
            && s.contains("16x12")
            && s.contains("8x6"),
        "{s}"
    );
}

#[test]
fn image_size_differs_from_camera() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    let mut o = opts();
    if let Some(c) = o.camera.as_mut() {
        c.camera.width = 640;
        c.camera.height = 480;
    }
    let e = TumSequence::open(tmp.path(), &o).unwrap_err();
    let s = e.to_string();
    assert!(matches!(e, IoError::CameraSizeMismatch { .. }), "{s}");
    assert!(
        s.contains("rgb/0.png") && s.contains("640x480") && s.contains("test camera"),
        "{s}"
    );
}

/// A distorted camera far larger than the images is refused from the image header, before
/// its undistortion table (tens of bytes per camera pixel: 65535 x 65535 would be ~50 GB)
/// is built.
#[test]
fn huge_distorted_camera_is_refused_before_its_undistortion_table() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    let mut o = opts();
    if let Some(c) = o.camera.as_mut() {
        c.camera.width = 65535;
        c.camera.height = 65535;
        c.camera.distortion.k1 = 0.01;
    }
    let e = TumSequence::open(tmp.path(), &o).unwrap_err();
    let s = e.to_string();
    assert!(matches!(e, IoError::CameraSizeMismatch { .. }), "{s}");
    assert!(s.contains("65535x65535") && s.contains("16x12"), "{s}");
}

#[test]
fn depth_not_16_bit() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    image::GrayImage::from_fn(W, H, |_, _| image::Luma([200]))
        .save(tmp.path().join("depth/0.png"))
        .unwrap();
    let (e, s) = open_err(tmp.path());
    assert!(matches!(e, IoError::DepthNot16Bit { .. }), "{s}");
    assert!(
        s.contains("depth/0.png") && s.contains("16-bit") && s.contains("L8"),
        "{s}"
    );
}

#[test]
fn wrong_depth_scale_is_detected_with_a_suggestion() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    let mut o = opts();
    if let Some(c) = o.camera.as_mut() {
        c.depth_factor = 1.0; // raw 10000 at factor 1 = 10 km
    }
    let e = TumSequence::open(tmp.path(), &o).unwrap_err();
    let s = e.to_string();
    match &e {
        IoError::DepthScaleMismatch {
            factor,
            suggested,
            median_m,
            ..
        } => {
            assert_eq!(*factor, 1.0);
            assert_eq!(*median_m, 10000.0);
            assert_eq!(*suggested, Some(5000.0));
        }
        other => panic!("wrong error {other:?}"),
    }
    assert!(
        s.contains("depth/0.png") && s.contains("factor 5000 would fit"),
        "{s}"
    );

    // Also through the loose-pair loader (millimetre data read with a 10x too small factor).
    let e = load_pair_frame(
        &tmp.path().join("rgb/0.png"),
        &tmp.path().join("depth/0.png"),
        &o.camera.unwrap().camera,
        100.0,
    )
    .unwrap_err();
    assert!(matches!(e, IoError::DepthScaleMismatch { .. }), "{e}");
}

#[test]
fn nan_and_malformed_lines_name_file_and_line() {
    let cases: [(&str, &str, &str, &str); 5] = [
        (
            "rgb.txt",
            "# rgb\n0.0 rgb/0.png\nnan rgb/1.png\n",
            "rgb.txt:3",
            "not finite",
        ),
        (
            "rgb.txt",
            "0.0 rgb/0.png\ninf rgb/1.png\n",
            "rgb.txt:2",
            "not finite",
        ),
        (
            "depth.txt",
            "0.001 depth/0.png\n0.101\n",
            "depth.txt:2",
            "expected `timestamp path`",
        ),
        (
            "depth.txt",
            "zero depth/0.png\n",
            "depth.txt:1",
            "not a number",
        ),
        (
            "associations.txt",
            "0.0 rgb/0.png 0.0\n",
            "associations.txt:1",
            "expected `t_rgb rgb_path t_depth depth_path`",
        ),
    ];
    for (file, text, at, cause) in cases {
        let tmp = tempfile::tempdir().unwrap();
        good_sequence(tmp.path());
        std::fs::write(tmp.path().join(file), text).unwrap();
        let (e, s) = open_err(tmp.path());
        assert!(matches!(e, IoError::Parse { .. }), "{s}");
        assert!(s.contains(at) && s.contains(cause), "{file}: {s}");
    }
}

#[test]
fn empty_sequence() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    std::fs::write(tmp.path().join("rgb.txt"), "# nothing here\n\n").unwrap();
    let (e, s) = open_err(tmp.path());
    assert!(matches!(e, IoError::Empty { .. }), "{s}");
    assert!(s.contains("rgb.txt") && s.contains("no entries"), "{s}");

    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    let e = TumSequence::open(
        tmp.path(),
        &OpenOptions {
            max_frames: Some(0),
            ..opts()
        },
    )
    .unwrap_err();
    assert!(
        matches!(e, IoError::Empty { .. }) && e.to_string().contains("no frames"),
        "{e}"
    );
}

#[test]
fn no_associations_within_tolerance() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    std::fs::write(
        tmp.path().join("depth.txt"),
        "5.0 depth/0.png\n5.1 depth/1.png\n",
    )
    .unwrap();
    let (e, s) = open_err(tmp.path());
    assert!(matches!(e, IoError::NoAssociations { .. }), "{s}");
    assert!(
        s.contains("no colour/depth pairs within 0.02 s") && s.contains("4.9"),
        "{s}"
    );
}

#[test]
fn frame_index_out_of_range() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    let seq = TumSequence::open(tmp.path(), &opts()).unwrap();
    let s = seq.load(7).unwrap_err().to_string();
    assert!(s.contains("frame 7") && s.contains("2 frames"), "{s}");
}

#[test]
fn bad_camera_files() {
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    let calib = tmp.path().join("calib.txt");
    for (text, cause) in [
        ("525 525 319.5\n", "found 3 numbers"),
        ("# c\n525 525 nan 239.5 5000\n", "not finite"),
        (
            "525 525 319.5 239.5 5000 16.5 12\n",
            "not a positive integer size",
        ),
    ] {
        std::fs::write(&calib, text).unwrap();
        let e = TumSequence::open(tmp.path(), &OpenOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("calib.txt:") && e.contains(cause), "{e}");
    }
    std::fs::write(&calib, "-525 525 7.5 5.5 5000 16 12\n").unwrap();
    let e = TumSequence::open(tmp.path(), &OpenOptions::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("calib.txt") && e.contains("fx"), "{e}");
    std::fs::write(&calib, "20 20 7.5 5.5 0 16 12\n").unwrap();
    let e = TumSequence::open(tmp.path(), &OpenOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("calib.txt") && e.contains("depth factor 0"),
        "{e}"
    );

    let cfg = tmp.path().join("cam.cfg");
    std::fs::write(&cfg, "fx = 500\nfy = 500\ncx 3\n").unwrap();
    let e = cfg
        .to_str()
        .unwrap()
        .parse::<CameraConfig>()
        .unwrap_err()
        .to_string();
    assert!(e.contains("cam.cfg:3") && e.contains("key = value"), "{e}");
}

#[test]
fn garbage_text_never_panics() {
    // Deterministic fuzz of the list parsers: random bytes and mutated lines.
    let tmp = tempfile::tempdir().unwrap();
    good_sequence(tmp.path());
    let mut state = 0x1234_5678u64;
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 33) as u32
    };
    let base = "0.0 rgb/0.png\n0.1 rgb/1.png\n".as_bytes().to_vec();
    for _ in 0..200 {
        let mut b = base.clone();
        for _ in 0..(next() % 6) {
            let k = next() as usize % b.len();
            b[k] = (next() % 256) as u8;
        }
        std::fs::write(tmp.path().join("rgb.txt"), &b).unwrap();
        let _ = TumSequence::open(tmp.path(), &opts());
        std::fs::write(tmp.path().join("calib.txt"), &b).unwrap();
        let _ = TumSequence::open(tmp.path(), &OpenOptions::default());
        std::fs::remove_file(tmp.path().join("calib.txt")).unwrap();
    }
}
