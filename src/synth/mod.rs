//! Placeholder: filled by the synth work.
