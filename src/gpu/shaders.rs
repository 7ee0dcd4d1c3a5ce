//! The WGSL sources, embedded at compile time, and their assembly from shared includes.
//!
//! A kernel file may start with lines `//! include: NAME.wgsl`; those files are prepended
//! (once each, in order), so helpers such as bilinear sampling exist once.

/// Every shader file shipped with rgbid: (file name, source).
pub const ALL: &[(&str, &str)] = &[
    ("common.wgsl", include_str!("../../shaders/common.wgsl")),
    ("pyramid.wgsl", include_str!("../../shaders/pyramid.wgsl")),
    ("odometry.wgsl", include_str!("../../shaders/odometry.wgsl")),
    (
        "odometry_subgroup.wgsl",
        include_str!("../../shaders/odometry_subgroup.wgsl"),
    ),
    ("raycast.wgsl", include_str!("../../shaders/raycast.wgsl")),
    ("normals.wgsl", include_str!("../../shaders/normals.wgsl")),
    ("fuse.wgsl", include_str!("../../shaders/fuse.wgsl")),
    ("tsdf.wgsl", include_str!("../../shaders/tsdf.wgsl")),
    (
        "tsdf_blocks.wgsl",
        include_str!("../../shaders/tsdf_blocks.wgsl"),
    ),
    (
        "tsdf_cast.wgsl",
        include_str!("../../shaders/tsdf_cast.wgsl"),
    ),
    (
        "tsdf_mesh.wgsl",
        include_str!("../../shaders/tsdf_mesh.wgsl"),
    ),
];

/// Returns the raw source of `name`.
pub fn raw(name: &str) -> Option<&'static str> {
    ALL.iter().find(|(n, _)| *n == name).map(|(_, s)| *s)
}

/// Returns the source of `name` with its includes prepended; `None` for an unknown name.
pub fn assembled(name: &str) -> Option<String> {
    let src = raw(name)?;
    let mut out = String::new();
    for line in src.lines() {
        if let Some(inc) = line.strip_prefix("//! include:") {
            out.push_str(raw(inc.trim())?);
            out.push('\n');
        }
    }
    out.push_str(src);
    Some(out)
}

/// Every WGSL kernel parses and validates with naga, on any machine (no GPU needed), so a
/// broken shader fails `cargo test` with the file and line.
#[cfg(test)]
mod tests {
    #[test]
    fn all_shaders_parse_and_validate() {
        let mut failures = Vec::new();
        for (name, raw) in super::ALL {
            // A file without an entry point is an include: it is validated inside every
            // kernel that includes it (and must be included by one).
            if !raw.contains("@compute") {
                let line = format!("//! include: {name}");
                if !super::ALL
                    .iter()
                    .any(|(_, s)| s.lines().any(|l| l.trim() == line))
                {
                    failures.push(format!("{name}: no entry point and included by no kernel"));
                }
                continue;
            }
            let src = super::assembled(name).expect("listed shader exists");
            match naga::front::wgsl::parse_str(&src) {
                Err(e) => failures.push(format!("{name}: {}", e.emit_to_string(&src))),
                Ok(module) => {
                    let caps =
                        naga::valid::Capabilities::default() | naga::valid::Capabilities::SUBGROUP;
                    if let Err(e) =
                        naga::valid::Validator::new(naga::valid::ValidationFlags::all(), caps)
                            .validate(&module)
                    {
                        failures.push(format!("{name}: {}", e.emit_to_string(&src)));
                    }
                }
            }
        }
        assert!(
            failures.is_empty(),
            "shader errors:\n{}",
            failures.join("\n")
        );
    }
}
