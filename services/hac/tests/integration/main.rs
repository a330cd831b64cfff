//! The integration tests of the `hac` binary (hac-cli), built as one test binary: one link, and one
//! copy of the dependencies' generic code, where a binary per file repeated both. Each module was a
//! test file of its own; `cargo test -p <package> --test integration <module>::` runs one.
//!
//! `paper_tasks.rs` (cartpole and pick-and-place through the daemons) and `containers.rs` (the
//! Compose stacks, opt-in) stay test binaries of their own: each loads the machine for minutes,
//! and alone in its binary it never runs beside the learning tests of `shm` and `distributed`,
//! whose free-running actors learn more slowly under load.

// Shared with the two test binaries beside this one.
mod cli;
mod cluster;
#[path = "../common/mod.rs"]
mod common;
mod config;
mod deploy;
mod distributed;
mod docs;
mod durable;
mod experiment_resume;
mod export;
mod hostile;
mod ops;
mod resume;
mod shm;
