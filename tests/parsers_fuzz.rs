//! Property tests of every file parser: random bytes and mutations of a valid file (flipped
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
