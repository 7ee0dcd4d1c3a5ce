//! The one GPU-test helper of the crate and the viewer.
//!
//! Tests that need a GPU adapter are named `gpu_*` and marked
//! `#[ignore = "needs a GPU adapter"]`, so a machine without an adapter reports them ignored,
//! never passed. CI runs them on lavapipe with `cargo test --workspace --tests -- --ignored gpu_`
//! and `RGBID_REQUIRE_GPU=1`, where a missing adapter is a failure (`tests/ci_stages.rs` keeps
//! the names, the ignore reasons and the CI stages consistent).

use std::sync::Arc;

use super::backend::{select_backend, BackendChoice, ComputeBackend};
use super::context::{GpuContext, GpuError};

/// The environment variable that turns a missing adapter in a GPU test into a failure.
#[doc(hidden)]
pub const REQUIRE_GPU_ENV: &str = "RGBID_REQUIRE_GPU";

/// A context on any adapter (lavapipe included) for the GPU test `test`. Without one: panics
/// when `RGBID_REQUIRE_GPU=1`, otherwise prints `SKIPPED test: no GPU adapter` and returns
/// `None` (the test then returns early).
#[doc(hidden)]
pub fn test_gpu(test: &str) -> Option<Arc<GpuContext>> {
    match select_backend(BackendChoice::Gpu, None) {
        Ok(ComputeBackend::Gpu(g)) => Some(g),
        Ok(ComputeBackend::Cpu) => {
            no_test_gpu(test, "the GPU backend resolved to the CPU");
            None
        }
        Err(GpuError::NoGpuAdapter { .. }) => {
            no_test_gpu(
                test,
                "wgpu found none; `apt-get install mesa-vulkan-drivers` gives lavapipe",
            );
            None
        }
        Err(e) => {
            no_test_gpu(test, &e.to_string());
            None
        }
    }
}

/// What a GPU test does when it finds no adapter (also for helpers that create their own
/// device, such as the viewer's egui render state): panics when `RGBID_REQUIRE_GPU=1`,
/// otherwise prints a loud `SKIPPED` line.
#[doc(hidden)]
pub fn no_test_gpu(test: &str, why: &str) {
    if std::env::var(REQUIRE_GPU_ENV).as_deref() == Ok("1") {
        panic!("{test}: {REQUIRE_GPU_ENV}=1 but no GPU adapter ({why})");
    }
    eprintln!("SKIPPED {test}: no GPU adapter ({why}); {REQUIRE_GPU_ENV}=1 makes this a failure");
}

/// The layout of a WGSL struct as naga lays it out: `(member name, byte offset)` in order,
/// and the struct's size. `None` when `shader` (an embedded file, includes assembled) does not
/// parse or has no struct `name`.
#[cfg(test)]
pub(crate) fn wgsl_struct_layout(source: &str, name: &str) -> Option<(Vec<(String, u32)>, u32)> {
    let module = naga::front::wgsl::parse_str(source).ok()?;
    let found = module.types.iter().find_map(|(_, ty)| {
        if ty.name.as_deref() != Some(name) {
            return None;
        }
        match &ty.inner {
            naga::TypeInner::Struct { members, span } => Some((
                members
                    .iter()
                    .map(|m| (m.name.clone().unwrap_or_default(), m.offset))
                    .collect(),
                *span,
            )),
            _ => None,
        }
    });
    found
}

/// Compares the WGSL struct `name` of `source` with a host struct given as `(member name,
/// offset_of!)` pairs in order and its `size_of`; the mismatches, one line each (empty when
/// the layouts agree).
#[cfg(test)]
pub(crate) fn layout_mismatches(
    source: &str,
    name: &str,
    host: &[(&str, usize)],
    host_size: usize,
) -> Vec<String> {
    let Some((members, span)) = wgsl_struct_layout(source, name) else {
        return vec![format!(
            "no struct {name} in the WGSL (or it does not parse)"
        )];
    };
    let mut out = Vec::new();
    if members.len() != host.len() {
        out.push(format!(
            "{name}: {} WGSL members, {} host members",
            members.len(),
            host.len()
        ));
    }
    for ((wn, wo), (hn, ho)) in members.iter().zip(host) {
        if wn != hn || *wo as usize != *ho {
            out.push(format!(
                "{name}: WGSL member {wn} at byte {wo}, host member {hn} at byte {ho}"
            ));
        }
    }
    if span as usize != host_size {
        out.push(format!(
            "{name}: WGSL size {span} bytes, host size {host_size}"
        ));
    }
    out
}

/// `(field name, offset)` pairs of a `#[repr(C)]` struct, for [`layout_mismatches`]: plain
/// fields by name; `name = field[k] stride s` for array fields that the WGSL splits into
/// numbered members.
#[cfg(test)]
macro_rules! host_layout {
    ($t:ty { $($f:ident $(= $arr:ident [$k:literal] stride $s:literal)?),* $(,)? }) => {
        vec![$(host_layout!(@one $t, $f $(, $arr, $k, $s)?)),*]
    };
    (@one $t:ty, $f:ident) => {
        (stringify!($f), std::mem::offset_of!($t, $f))
    };
    (@one $t:ty, $f:ident, $arr:ident, $k:literal, $s:literal) => {
        (stringify!($f), std::mem::offset_of!($t, $arr) + $k * $s)
    };
}
#[cfg(test)]
pub(crate) use host_layout;
