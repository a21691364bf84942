//! The command-line tools' lines on standard output and error, whose
//! readers may leave before the tools are done: `coordctl tasks 1 | head`
//! closes the pipe after ten lines, and `println!` and `eprintln!` panic
//! then.

use std::fmt;
use std::io::{self, Write};

/// An error and its causes on one line, each cause once (the executive's
/// own report, so that every binary of the workspace says it alike).
pub use coordinator::error::report;

/// Standard output did not take a line.
#[derive(Debug, thiserror::Error)]
pub enum StdoutError {
    /// Its reader has gone (a closed pipe): nothing more is wanted, and the
    /// tool ends quietly with success, as `head`'s writers do.
    #[error("standard output was closed by its reader")]
    ReaderGone,
    /// Anything else (a full disk behind a redirection).
    #[error("cannot write to standard output")]
    Failed(#[source] io::Error),
}

impl StdoutError {
    /// Whether a tool failed only because its output's reader has gone.
    pub fn is_reader_gone(error: &anyhow::Error) -> bool {
        matches!(error.downcast_ref::<Self>(), Some(Self::ReaderGone))
    }
}

/// Writes `args` and a newline to standard output (see [`outln!`](crate::outln)).
pub fn write_line(args: fmt::Arguments<'_>) -> Result<(), StdoutError> {
    let mut out = io::stdout().lock();
    out.write_fmt(args).and_then(|()| out.write_all(b"\n")).map_err(|e| match e.kind() {
        io::ErrorKind::BrokenPipe => StdoutError::ReaderGone,
        _ => StdoutError::Failed(e),
    })
}

/// `println!` that returns a [`StdoutError`] instead of panicking when
/// standard output fails.
#[macro_export]
macro_rules! outln {
    () => {
        $crate::console::write_line(format_args!(""))
    };
    ($($arg:tt)*) => {
        $crate::console::write_line(format_args!($($arg)*))
    };
}

/// `eprintln!` that ignores a failure: what goes to standard error is for a
/// person watching, and a run neither stops nor panics because nobody is.
#[macro_export]
macro_rules! errln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($arg)*);
    }};
}
