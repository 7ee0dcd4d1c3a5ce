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
