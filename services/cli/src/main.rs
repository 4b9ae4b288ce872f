//! The `depthmill` binary: [`depthmill_cli::cli`].

fn main() -> std::process::ExitCode {
    limit_malloc_arenas();
    std::process::ExitCode::from(depthmill_cli::cli::main_from(std::env::args_os()))
}

/// glibc's malloc gives a thread that meets contention an arena of its own, up to eight per core,
/// and memory freed into one arena serves only the threads that use it: `depthmill serve` runs
/// every stage on whichever tokio and rayon threads are free, so each arena kept the high-water
/// mark of the stages that passed through it (a 10^7-point cloud job: 311 MiB resident while
/// executing with under 200 MiB live). One arena per core keeps the resident set near the live
/// heap (196 MiB at most in the same job), the stage times within run-to-run noise. Set before
/// any other thread exists.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)] // one call into the C library, nothing else
fn limit_malloc_arenas() {
    let cores = std::thread::available_parallelism().map_or(2, |n| n.get()).clamp(2, 64);
    // SAFETY: mallopt only sets a tuning parameter of the allocator; no other thread runs yet.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, cores as libc::c_int);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn limit_malloc_arenas() {}
