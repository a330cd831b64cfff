//! The integration tests of hac-core, built as one test binary: one link, and one copy of the
//! dependencies' generic code, where a binary per file repeated both. Each module was a test file
//! of its own; `cargo test -p <package> --test integration <module>::` runs one.

mod common;
mod hiro_rollout;
mod moved_end_goal;
mod rollout_properties;
mod worked_example;
