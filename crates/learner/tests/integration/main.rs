//! The integration tests of hac-learner, built as one test binary: one link, and one copy of the
//! dependencies' generic code, where a binary per file repeated both. Each module was a test file
//! of its own; `cargo test -p <package> --test integration <module>::` runs one.

mod best;
mod checkpoint;
mod common;
mod durable;
mod hiro;
mod hostile;
mod ingest;
mod turns;
