//! `rgbid-viewer`: a native viewer (eframe + egui with the wgpu renderer) that is a thin client
//! of the `rgbid` library. SLAM runs in a background thread ([`worker`]) that sends owned
//! per-frame snapshots to the UI; [`state`] turns them into what the panels show; [`app`] has
//! the widgets; [`scene3d`] draws the 3D view with wgpu inside egui.

pub mod app;
pub mod images;
pub mod output;
pub mod scene3d;
/// Where frames come from (the library's [`rgbid::source`], shared with `rgbid slam`).
pub use rgbid::source;
pub mod state;
pub mod worker;

pub use app::ViewerApp;
