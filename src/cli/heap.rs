//! Live heap bytes of the `rgbid` process: the system allocator wrapped in a counter, so
//! that `rgbid bench load` can tell memory the program holds (allocated and not freed) from
//! what the process's resident size adds to it (pages the C allocator keeps after frees).

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Bytes allocated and not yet freed, by every thread.
static LIVE: AtomicUsize = AtomicUsize::new(0);

/// Live bytes by the size of their allocation: class `k` holds allocations of `2^k` to
/// `2^(k+1) - 1` bytes.
static BY_SIZE: [AtomicUsize; 64] = [const { AtomicUsize::new(0) }; 64];

/// Allocations of at least this many bytes print where they come from (stderr), when
/// [`TRACE_ENV`] sets it; 0 = off.
static TRACE_ABOVE: AtomicUsize = AtomicUsize::new(0);

/// Environment variable: a size in bytes; every allocation of at least that size prints its
/// backtrace on stderr (a diagnostic for memory that grows).
pub const TRACE_ENV: &str = "RGBID_HEAP_TRACE_ABOVE";

thread_local! {
    /// Set while this thread prints a trace (which allocates itself).
    static TRACING: Cell<bool> = const { Cell::new(false) };
}

fn class(size: usize) -> usize {
    (usize::BITS - 1 - size.max(1).leading_zeros()) as usize
}

fn added(size: usize) {
    LIVE.fetch_add(size, Ordering::Relaxed);
    BY_SIZE[class(size)].fetch_add(size, Ordering::Relaxed);
    let above = TRACE_ABOVE.load(Ordering::Relaxed);
    if above > 0 && size >= above {
        // `try_with`: the allocator also runs while thread-locals are torn down.
        let _ = TRACING.try_with(|t| {
            if !t.replace(true) {
                let bt = std::backtrace::Backtrace::force_capture();
                eprintln!("heap: {size} bytes allocated at\n{bt}");
                t.set(false);
            }
        });
    }
}

fn removed(size: usize) {
    LIVE.fetch_sub(size, Ordering::Relaxed);
    BY_SIZE[class(size)].fetch_sub(size, Ordering::Relaxed);
}

/// Reads [`TRACE_ENV`] (call once at start-up).
pub fn init_trace_from_env() {
    if let Some(n) = std::env::var(TRACE_ENV)
        .ok()
        .and_then(|v| v.trim().parse().ok())
    {
        TRACE_ABOVE.store(n, Ordering::Relaxed);
    }
}

/// Makes glibc's `malloc` keep freed blocks of up to 64 MiB in the process for reuse.
///
/// By default glibc serves large blocks with `mmap` and returns them to the kernel when they
/// are freed, and it trims the heap's free top. A frame loop allocates and frees image-sized
/// buffers (pyramids, residual rows, decoded images) every frame, so each frame would fault
/// freshly zeroed pages back in. A fixed mmap threshold serves those buffers from the heap,
/// where the next frame reuses them; the trim threshold bounds how much free memory the heap
/// keeps above its peak use. Other C libraries are unaffected.
pub fn keep_freed_buffers() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        const MMAP_THRESHOLD: libc::c_int = 64 << 20;
        const TRIM_THRESHOLD: libc::c_int = 128 << 20;
        // SAFETY: `mallopt` only changes allocator parameters; it is called before any other
        // thread exists. A rejected value leaves glibc's default, which is still correct.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
            libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD);
        }
    }
}

/// Live bytes in allocations of at least 1 MiB, by size class: `(smallest size of the class,
/// bytes)` for the classes that hold any.
pub fn large_classes() -> Vec<(usize, usize)> {
    (20..64)
        .filter_map(|k| {
            let b = BY_SIZE[k].load(Ordering::Relaxed);
            (b > 0).then_some((1usize << k, b))
        })
        .collect()
}

/// The system allocator, counting the bytes it hands out and takes back (one relaxed atomic
/// add per call).
pub struct Counting;

// SAFETY: every call is forwarded unchanged to `System`; the counter only observes sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract for `layout` is passed on.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            added(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as for `alloc`.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            added(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from this allocator (that is, from `System`) with `layout`.
        unsafe { System.dealloc(ptr, layout) };
        removed(layout.size());
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: as for `dealloc`, and `new_size` is the caller's valid size.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            added(new_size);
            removed(layout.size());
        }
        p
    }
}

/// Bytes the process holds on the heap now (allocated by Rust code and not freed; memory
/// that C libraries allocate with `malloc` directly is not seen).
pub fn live_bytes() -> usize {
    LIVE.load(Ordering::Relaxed)
}
