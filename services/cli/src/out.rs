//! Standard output for the CLI's verbs: `outln!` and `out!` instead of `println!` and `print!`,
//! so that output into a pipe closed early (`depthmill status ID | head -1`) ends the program
//! quietly with success instead of a panic, and any other write failure ends it with one line on
//! standard error and exit code 1.

use std::io::Write as _;

/// Writes `args` (and a line break when `newline`) to standard output; see the module.
pub fn write(args: std::fmt::Arguments<'_>, newline: bool) {
    let mut out = std::io::stdout().lock();
    let written = out.write_fmt(args).and_then(|()| if newline { out.write_all(b"\n") } else { Ok(()) });
    if let Err(e) = written.and_then(|()| if newline { out.flush() } else { Ok(()) }) {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            std::process::exit(0);
        }
        let _ = writeln!(std::io::stderr(), "depthmill: writing to standard output failed: {e}");
        std::process::exit(1);
    }
}

/// `println!` that ends quietly on a closed pipe.
#[macro_export]
macro_rules! outln {
    () => { $crate::out::write(format_args!(""), true) };
    ($($arg:tt)*) => { $crate::out::write(format_args!($($arg)*), true) };
}

/// `print!` that ends quietly on a closed pipe.
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => { $crate::out::write(format_args!($($arg)*), false) };
}
