//! Every WGSL kernel parses and validates with naga, on any machine (no GPU needed), so a
//! broken shader fails `cargo test` with the file and line.

#[test]
fn all_shaders_parse_and_validate() {
    let mut failures = Vec::new();
    for (name, _) in rgbid::gpu::shaders::ALL {
        let src = rgbid::gpu::shaders::assembled(name).expect("listed shader exists");
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
