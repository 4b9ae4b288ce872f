//! The `depthmill` binary: [`depthmill_cli::cli`].

fn main() -> std::process::ExitCode {
    depthmill_common::process::limit_malloc_arenas();
    std::process::ExitCode::from(depthmill_cli::cli::main_from(std::env::args_os()))
}
