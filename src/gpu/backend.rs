use std::sync::Arc;

use super::context::{GpuContext, GpuError};

/// What the user asked for on the command line (`--backend`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum BackendChoice {
    /// A hardware GPU if there is one, else the CPU backend (software GPU adapters such as
    /// lavapipe are slower than the rayon CPU backend, so `auto` does not pick them).
    #[default]
    Auto,
    /// Any GPU adapter, software ones (lavapipe) included; an error if there is none.
    Gpu,
    /// The rayon CPU backend (the CPU mirror of every kernel).
    Cpu,
}

/// Where the pixel work runs.
#[derive(Clone)]
pub enum ComputeBackend {
    /// rayon on the CPU.
    Cpu,
    /// WGSL kernels on a wgpu device.
    Gpu(Arc<GpuContext>),
}

impl ComputeBackend {
    /// A short human-readable name (`cpu` or the adapter's name).
    pub fn name(&self) -> String {
        match self {
            ComputeBackend::Cpu => format!("cpu (rayon, {} threads)", rayon::current_num_threads()),
            ComputeBackend::Gpu(g) => format!("gpu ({}, {:?})", g.info.name, g.info.backend),
        }
    }
}

fn instance() -> wgpu::Instance {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
    if std::env::var_os("WGPU_BACKEND").is_none() {
        // Vulkan, Metal, DX12 (and WebGPU): the compute backends. OpenGL is left out: it has
        // no compute path worth using here and its probing prints EGL errors on headless hosts.
        desc.backends = wgpu::Backends::PRIMARY;
    }
    wgpu::Instance::new(desc)
}

fn adapters() -> Vec<wgpu::Adapter> {
    pollster::block_on(instance().enumerate_adapters(wgpu::Backends::all()))
}

/// One line per adapter wgpu can see: name, backend, device type.
pub fn describe_adapters() -> Vec<String> {
    adapters()
        .into_iter()
        .map(|a| {
            let i = a.get_info();
            format!("{} ({:?}, {:?})", i.name, i.backend, i.device_type)
        })
        .collect()
}

/// Resolves the user's choice to a backend.
///
/// `adapter_filter` is a case-insensitive substring of the adapter name. With `Auto`, a
/// hardware adapter is preferred; if only software adapters exist (or none), the CPU backend
/// is used and one log line says so. With `Gpu`, any adapter is accepted and none is an error
/// ([`GpuError::NoGpuAdapter`]) that explains how to install one.
pub fn select_backend(
    choice: BackendChoice,
    adapter_filter: Option<&str>,
) -> Result<ComputeBackend, GpuError> {
    if choice == BackendChoice::Cpu {
        return Ok(ComputeBackend::Cpu);
    }
    let filter = adapter_filter.map(|s| s.to_lowercase());
    let mut found: Vec<wgpu::Adapter> = adapters()
        .into_iter()
        .filter(|a| {
            let i = a.get_info();
            i.device_type != wgpu::DeviceType::Other || i.backend != wgpu::Backend::Noop
        })
        .filter(|a| {
            filter
                .as_ref()
                .is_none_or(|f| a.get_info().name.to_lowercase().contains(f))
        })
        .collect();
    // Hardware first: discrete, integrated, virtual, then software.
    found.sort_by_key(|a| match a.get_info().device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    });
    let pick = match choice {
        BackendChoice::Auto if filter.is_none() => found
            .into_iter()
            .find(|a| a.get_info().device_type != wgpu::DeviceType::Cpu),
        _ => found.into_iter().next(),
    };
    match (pick, choice) {
        (Some(adapter), _) => Ok(ComputeBackend::Gpu(Arc::new(GpuContext::from_adapter(
            adapter,
        )?))),
        (None, BackendChoice::Auto) => {
            log::info!(
                "no hardware GPU adapter found; using the CPU backend (rayon). \
                 Use `--backend gpu` to run the WGSL kernels on a software adapter such as lavapipe."
            );
            Ok(ComputeBackend::Cpu)
        }
        (None, _) => Err(GpuError::NoGpuAdapter {
            filter: adapter_filter
                .map(|f| format!(" matching '{f}'"))
                .unwrap_or_default(),
        }),
    }
}
