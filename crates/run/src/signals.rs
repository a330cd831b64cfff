//! Ctrl-C and SIGTERM for long-running commands.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::{Context, Result};

/// A flag that SIGINT/SIGTERM set, so that long runs stop between episodes and save their
/// results; a second signal while the flag is set exits at once (status 130).
pub fn interrupt_flag() -> Result<Arc<AtomicBool>> {
    let flag = Arc::new(AtomicBool::new(false));
    for &signal in signal_hook::consts::TERM_SIGNALS {
        signal_hook::flag::register_conditional_shutdown(signal, 130, Arc::clone(&flag))
            .context("installing signal handlers")?;
        signal_hook::flag::register(signal, Arc::clone(&flag))
            .context("installing signal handlers")?;
    }
    Ok(flag)
}
