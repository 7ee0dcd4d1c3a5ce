use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use wgpu::util::DeviceExt;

/// Errors of the GPU layer.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter could be found; the message says how to get one.
    #[error(
        "no GPU adapter found{filter}. Install a Vulkan driver (on Debian/Ubuntu: \
         `apt-get install mesa-vulkan-drivers` gives Mesa's lavapipe software rasteriser), \
         or run with `--backend cpu`"
    )]
    NoGpuAdapter {
        /// Describes the adapter filter that was applied, if any.
        filter: String,
    },
    /// The device could not be created on the chosen adapter.
    #[error("could not create a device on adapter '{adapter}': {source}")]
    RequestDevice {
        /// Adapter name.
        adapter: String,
        /// Underlying error.
        source: wgpu::RequestDeviceError,
    },
    /// The device was lost (driver reset, GPU removed, out of memory).
    #[error("GPU device lost: {0}")]
    DeviceLost(String),
    /// Waiting for the GPU took longer than the timeout.
    #[error("GPU did not finish within {0:?} (hung or lost device)")]
    Timeout(Duration),
    /// A shader failed to compile or a pipeline failed validation.
    #[error("shader '{name}' failed: {message}")]
    Shader {
        /// Shader file name.
        name: String,
        /// The validation message.
        message: String,
    },
    /// A validation error from a GPU call (a bug in rgbid or an unsupported adapter).
    #[error("GPU validation error: {0}")]
    Validation(String),
    /// Mapping a buffer for read-back failed.
    #[error("GPU buffer read-back failed: {0}")]
    Readback(String),
}

/// A headless wgpu device and queue plus what rgbid needs to know about them.
///
/// Create it once per process (pipeline creation is expensive on lavapipe) and share it
/// behind an `Arc`; each user creates its pipelines once and keeps them.
pub struct GpuContext {
    /// The device.
    pub(crate) device: wgpu::Device,
    /// Its queue.
    pub(crate) queue: wgpu::Queue,
    /// Adapter information (name, backend, device type).
    pub(crate) info: wgpu::AdapterInfo,
    /// True for software adapters (lavapipe/llvmpipe, WARP): fewer, larger workgroups win there.
    pub(crate) is_software: bool,
    /// True when `Features::SUBGROUP` was enabled on the device.
    pub(crate) has_subgroups: bool,
    /// Device limits.
    pub(crate) limits: wgpu::Limits,
    lost: Arc<AtomicBool>,
    lost_message: Arc<Mutex<String>>,
    error: Arc<Mutex<Option<String>>>,
    /// Submissions so far, for [`LOSE_DEVICE_ENV`].
    submissions: AtomicU64,
    /// The submission before which the device is destroyed ([`LOSE_DEVICE_ENV`]).
    lose_at: Option<u64>,
    /// Whether [`LOSE_DEVICE_ENV`] destroyed the device (its error says so).
    simulated: AtomicBool,
}

/// Test hook, not a setting: when this environment variable holds a number N, the device is
/// destroyed (`wgpu::Device::destroy`) just before the N-th submission of command buffers
/// (counted from 1), which wgpu reports through the device-lost callback like a driver reset.
/// It lets tests check on any adapter, lavapipe included, that a device lost in the middle of
/// a run is an error that keeps what was written, which a real loss cannot be made to do on
/// demand.
#[doc(hidden)]
pub const LOSE_DEVICE_ENV: &str = "RGBID_TEST_LOSE_GPU_AT_SUBMISSION";

/// How long a single wait on the GPU may take before it is treated as a hang.
pub(crate) const GPU_WAIT_TIMEOUT: Duration = Duration::from_secs(60);

impl GpuContext {
    /// The adapter's name, backend and device type.
    pub fn adapter_info(&self) -> &wgpu::AdapterInfo {
        &self.info
    }

    /// True for software adapters (lavapipe/llvmpipe, WARP).
    pub fn is_software(&self) -> bool {
        self.is_software
    }

    /// Creates a device on `adapter`.
    pub(crate) fn from_adapter(adapter: wgpu::Adapter) -> Result<Self, GpuError> {
        let info = adapter.get_info();
        let wanted = wgpu::Features::SUBGROUP;
        let required_features = adapter.features() & wanted;
        let alimits = adapter.limits();
        let required_limits = wgpu::Limits {
            max_storage_buffer_binding_size: alimits.max_storage_buffer_binding_size,
            max_buffer_size: alimits.max_buffer_size,
            max_storage_buffers_per_shader_stage: alimits
                .max_storage_buffers_per_shader_stage
                .min(16),
            ..Default::default()
        };
        let desc = wgpu::DeviceDescriptor {
            label: Some("rgbid"),
            required_features,
            required_limits: required_limits.clone(),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        };
        let (device, queue) =
            pollster::block_on(adapter.request_device(&desc)).map_err(|source| {
                GpuError::RequestDevice {
                    adapter: info.name.clone(),
                    source,
                }
            })?;
        let lost = Arc::new(AtomicBool::new(false));
        let lost_message = Arc::new(Mutex::new(String::new()));
        {
            let lost = lost.clone();
            let msg = lost_message.clone();
            device.set_device_lost_callback(move |reason, m| {
                lost.store(true, Ordering::SeqCst);
                if let Ok(mut g) = msg.lock() {
                    *g = if m.is_empty() {
                        format!("{reason:?}")
                    } else {
                        format!("{reason:?}: {m}")
                    };
                }
            });
        }
        let error = Arc::new(Mutex::new(None));
        {
            let error = error.clone();
            device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
                if let Ok(mut g) = error.lock() {
                    if g.is_none() {
                        *g = Some(e.to_string());
                    }
                }
            }));
        }
        let is_software = info.device_type == wgpu::DeviceType::Cpu;
        log::info!(
            "GPU adapter: {} ({:?}, {:?}){}",
            info.name,
            info.backend,
            info.device_type,
            if required_features.contains(wgpu::Features::SUBGROUP) {
                ", subgroups"
            } else {
                ""
            }
        );
        Ok(Self {
            device,
            queue,
            info,
            is_software,
            has_subgroups: required_features.contains(wgpu::Features::SUBGROUP),
            limits: required_limits,
            lost,
            lost_message,
            error,
            submissions: AtomicU64::new(0),
            simulated: AtomicBool::new(false),
            lose_at: std::env::var(LOSE_DEVICE_ENV)
                .ok()
                .and_then(|v| v.trim().parse().ok()),
        })
    }

    /// Submits `commands` to the queue (every submission of rgbid goes through here, so that
    /// the [`LOSE_DEVICE_ENV`] hook sees them all).
    pub(crate) fn submit(&self, commands: wgpu::CommandBuffer) {
        let n = self.submissions.fetch_add(1, Ordering::SeqCst) + 1;
        if self.lose_at == Some(n) {
            self.simulated.store(true, Ordering::SeqCst);
            self.device.destroy();
        }
        self.queue.submit([commands]);
    }

    /// Returns an error if the device was lost or an uncaptured validation error occurred.
    pub(crate) fn check(&self) -> Result<(), GpuError> {
        if self.lost.load(Ordering::SeqCst) {
            let m = self
                .lost_message
                .lock()
                .map(|g| g.clone())
                .unwrap_or_default();
            return Err(GpuError::DeviceLost(
                if self.simulated.load(Ordering::SeqCst) {
                    format!("{m} (simulated: {LOSE_DEVICE_ENV} is set)")
                } else {
                    m
                },
            ));
        }
        if let Ok(mut g) = self.error.lock() {
            if let Some(e) = g.take() {
                return Err(GpuError::Validation(e));
            }
        }
        Ok(())
    }

    /// Waits for all submitted work, with a timeout, and reports loss or validation errors.
    pub(crate) fn wait(&self) -> Result<(), GpuError> {
        // A lost device is reported as such, without waiting on it.
        self.check()?;
        // wgpu panics inside `poll` on device errors other than a timeout (a device lost
        // while the work ran): that panic is turned into the error it stands for.
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            self.device.poll(wgpu::PollType::Wait {
                submission_index: None,
                timeout: Some(GPU_WAIT_TIMEOUT),
            })
        }))
        .map_err(|panic| {
            let m = panic
                .downcast_ref::<String>()
                .map(String::as_str)
                .or_else(|| panic.downcast_ref::<&str>().copied())
                .unwrap_or("wgpu panicked while waiting");
            GpuError::DeviceLost(m.to_string())
        })?;
        self.check()?;
        match r {
            Ok(_) => Ok(()),
            Err(wgpu::PollError::Timeout) => Err(GpuError::Timeout(GPU_WAIT_TIMEOUT)),
            Err(e) => Err(GpuError::DeviceLost(e.to_string())),
        }
    }

    /// Compiles a WGSL module and creates one compute pipeline per entry point, with an
    /// automatically derived layout. Errors name the shader.
    pub(crate) fn compute_pipelines(
        &self,
        name: &str,
        source: &str,
        entries: &[&str],
    ) -> Result<Vec<wgpu::ComputePipeline>, GpuError> {
        self.compute_pipelines_with_layout(name, source, entries, None)
    }

    /// Like [`Self::compute_pipelines`], with an explicit bind-group layout (group 0) shared by
    /// all entry points, so one bind group serves every kernel of the module.
    pub(crate) fn compute_pipelines_with_layout(
        &self,
        name: &str,
        source: &str,
        entries: &[&str],
        group0: Option<&wgpu::BindGroupLayout>,
    ) -> Result<Vec<wgpu::ComputePipeline>, GpuError> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let layout = group0.map(|bgl| {
            self.device
                .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                    label: Some(name),
                    bind_group_layouts: &[Some(bgl)],
                    immediate_size: 0,
                })
        });
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(name),
                source: wgpu::ShaderSource::Wgsl(source.into()),
            });
        let pipelines = entries
            .iter()
            .map(|entry| {
                self.device
                    .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                        label: Some(entry),
                        layout: layout.as_ref(),
                        module: &module,
                        entry_point: Some(entry),
                        compilation_options: wgpu::PipelineCompilationOptions::default(),
                        cache: None,
                    })
            })
            .collect();
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Shader {
                name: name.to_string(),
                message: e.to_string(),
            });
        }
        Ok(pipelines)
    }

    /// A bind-group layout of compute-stage buffers: binding 0 a uniform, then one storage
    /// buffer per entry of `storage_read_only` (true = read-only).
    pub(crate) fn buffer_layout(
        &self,
        label: &str,
        storage_read_only: &[bool],
    ) -> wgpu::BindGroupLayout {
        let mut entries = vec![wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        }];
        for (k, &read_only) in storage_read_only.iter().enumerate() {
            entries.push(wgpu::BindGroupLayoutEntry {
                binding: k as u32 + 1,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            });
        }
        self.device
            .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(label),
                entries: &entries,
            })
    }

    /// A bind group binding `buffers` whole, in order, to bindings 0, 1, ...
    pub(crate) fn bind_buffers(
        &self,
        label: &str,
        layout: &wgpu::BindGroupLayout,
        buffers: &[&wgpu::Buffer],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = buffers
            .iter()
            .enumerate()
            .map(|(k, b)| wgpu::BindGroupEntry {
                binding: k as u32,
                resource: b.as_entire_binding(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(label),
            layout,
            entries: &entries,
        })
    }

    /// A storage buffer initialised with `data`, usable as copy source and destination.
    pub(crate) fn storage_init<T: bytemuck::Pod>(&self, label: &str, data: &[T]) -> wgpu::Buffer {
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::cast_slice(data),
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
            })
    }

    /// An uninitialised (zeroed) storage buffer of `bytes` bytes.
    pub(crate) fn storage(&self, label: &str, bytes: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes.max(16),
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// A uniform buffer of `bytes` bytes, written with `queue.write_buffer`.
    pub(crate) fn uniform(&self, label: &str, bytes: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes.max(16),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// A buffer for reading results back to the CPU.
    pub(crate) fn staging(&self, label: &str, bytes: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes.max(16),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// Maps `staging` (already filled by a submitted copy), waits, and returns the first
    /// `count` values.
    pub(crate) fn read_staging<T: bytemuck::Pod>(
        &self,
        staging: &wgpu::Buffer,
        count: usize,
    ) -> Result<Vec<T>, GpuError> {
        let bytes = (count * std::mem::size_of::<T>()) as u64;
        let slice = staging.slice(0..bytes.max(4));
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        match rx.recv_timeout(Duration::from_secs(1)) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(GpuError::Readback(e.to_string())),
            Err(_) => return Err(GpuError::Readback("map callback never ran".into())),
        }
        let out = {
            let view = slice
                .get_mapped_range()
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            bytemuck::cast_slice::<u8, T>(&view[..bytes as usize]).to_vec()
        };
        staging.unmap();
        Ok(out)
    }

    /// Copies `count` values of `src` to a new staging buffer and reads them back (slow path
    /// for tests and one-off reads; hot loops keep their own staging buffers).
    pub(crate) fn read_buffer<T: bytemuck::Pod>(
        &self,
        src: &wgpu::Buffer,
        count: usize,
    ) -> Result<Vec<T>, GpuError> {
        let bytes = (count * std::mem::size_of::<T>()) as u64;
        let staging = self.staging("readback", bytes);
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("readback"),
            });
        enc.copy_buffer_to_buffer(src, 0, &staging, 0, bytes);
        self.submit(enc.finish());
        self.read_staging(&staging, count)
    }

    /// Workgroup count for a reduction over `items` items with `threads` threads per group:
    /// few large groups on software adapters, enough to fill a real GPU otherwise.
    pub(crate) fn reduction_groups(&self, items: usize, threads: usize) -> u32 {
        // Software: at least ~16 pixels per invocation, but several groups even on small
        // levels so that every driver thread gets work (80x60: 3 groups, not 1).
        let per_thread = if self.is_software { 16 } else { 8 };
        let groups = items.div_ceil(threads * per_thread).max(1);
        let cap = if self.is_software { 16 } else { 1024 };
        groups.min(cap) as u32
    }
}
