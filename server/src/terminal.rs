//! Whether what the binaries print may carry colours.

use std::io::IsTerminal;

/// Whether log lines written to `stream` may be coloured: only when it is a
/// terminal, and not when `NO_COLOR` is set (<https://no-color.org>). Logs
/// sent to a file, a pipe or journald would otherwise carry escape codes
/// on every line.
pub fn colours_on(stream: &impl IsTerminal) -> bool {
    stream.is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty())
}
