//! `rgbid-viewer`: the native viewer. The egui/eframe application is tracked by its own issue;
//! until it lands this binary only reports the library version and the GPU adapters it can see,
//! which is already useful to check a machine's set-up.

fn main() {
    println!(
        "rgbid-viewer {} (the egui viewer is not built yet)",
        env!("CARGO_PKG_VERSION")
    );
    for line in rgbid::gpu::describe_adapters() {
        println!("  adapter: {line}");
    }
}
