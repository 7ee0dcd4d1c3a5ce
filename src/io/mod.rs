//! Placeholder: filled by the io work.
