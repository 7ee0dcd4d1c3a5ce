//! `rgbid._rgbid`: the compiled part of the Python package `rgbid`.
//!
//! A thin layer over the library's public API: numpy arrays are checked (dtype, shape, C
//! order) and borrowed, each frame is built once by `RgbdFrame::from_buffers`, and the
//! interpreter lock is released while the library works. Results come back as numpy arrays
//! and dicts. Bad input raises `ValueError`; failures of the library raise `rgbid.RgbidError`
//! with the library's message (and its causes).

// `!(x < t)` is used on purpose: it also rejects NaN, which input can contain.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use pyo3::prelude::*;

mod convert;
mod frames;
mod sequence;
mod systems;
mod tools;
mod volume;

pyo3::create_exception!(
    _rgbid,
    RgbidError,
    pyo3::exceptions::PyRuntimeError,
    "A failure inside rgbid (I/O, GPU, tracking); the message is the library's, with its causes."
);

#[pymodule]
fn _rgbid(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("RgbidError", m.py().get_type::<RgbidError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<frames::Camera>()?;
    m.add_class::<systems::Odometry>()?;
    m.add_class::<systems::Slam>()?;
    m.add_class::<systems::SlamResult>()?;
    m.add_class::<systems::EventStream>()?;
    m.add_class::<sequence::Sequence>()?;
    m.add_class::<volume::TsdfVolume>()?;
    m.add_function(wrap_pyfunction!(sequence::read_sequence, m)?)?;
    m.add_function(wrap_pyfunction!(sequence::synth_render, m)?)?;
    m.add_function(wrap_pyfunction!(tools::read_trajectory, m)?)?;
    m.add_function(wrap_pyfunction!(tools::write_trajectory, m)?)?;
    m.add_function(wrap_pyfunction!(tools::evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(tools::graph_optimize, m)?)?;
    m.add_function(wrap_pyfunction!(tools::read_run, m)?)?;
    m.add_function(wrap_pyfunction!(tools::default_config, m)?)?;
    Ok(())
}
