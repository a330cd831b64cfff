//! The binaries' output on stdout, for a reader that may stop reading early.
//!
//! `hac eval --per-episode | head -n 3` closes the pipe while `hac` still writes. `println!`
//! would then panic with a backtrace; [`outln!`](crate::outln) and [`out!`](crate::out) end the
//! process quietly with status 0 instead, as the usual Unix tools do, and an error whose cause is
//! a broken pipe (a command that writes through its own `Write`) is ended the same way by
//! [`exit_if_broken_pipe`]. Any other write error still panics or fails the command.

use std::fmt;
use std::io::{self, Write as _};

/// `println!` for a binary's output; see [`output`](crate::output).
#[macro_export]
macro_rules! outln {
    () => { $crate::output::write(format_args!("\n")) };
    ($($arg:tt)*) => { $crate::output::write(format_args!("{}\n", format_args!($($arg)*))) };
}

/// `print!` for a binary's output; see [`output`](crate::output).
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => { $crate::output::write(format_args!($($arg)*)) };
}

/// Writes `args` to stdout; a reader that went away ends the process with status 0.
pub fn write(args: fmt::Arguments<'_>) {
    let mut stdout = io::stdout().lock();
    if let Err(e) = stdout.write_fmt(args) {
        if e.kind() == io::ErrorKind::BrokenPipe {
            std::process::exit(0);
        }
        panic!("failed printing to stdout: {e}");
    }
}

/// Ends the process with status 0 when `error` was caused by writing to a closed pipe: the reader
/// of the command's output stopped reading, which is not the command's failure.
pub fn exit_if_broken_pipe(error: &anyhow::Error) {
    let broken = error.chain().any(|cause| {
        cause
            .downcast_ref::<io::Error>()
            .is_some_and(|e| e.kind() == io::ErrorKind::BrokenPipe)
    });
    if broken {
        std::process::exit(0);
    }
}
