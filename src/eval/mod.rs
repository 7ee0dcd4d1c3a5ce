//! Placeholder: filled by the eval work.
