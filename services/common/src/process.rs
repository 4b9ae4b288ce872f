//! Process set-up shared by the binaries: the allocator's tuning, and a service's `main`.

/// Limits glibc's malloc to one arena per core.
///
/// glibc gives a thread that meets contention an arena of its own, up to eight per core, and
/// memory freed into one arena serves only the threads that use it: a service runs its work on
/// whichever tokio and rayon threads are free, so each arena kept the high-water mark of the work
/// that passed through it (`depthmill serve` with a 10^7-point cloud job: 311 MiB resident while
/// executing with under 200 MiB live). One arena per core keeps the resident set near the live
/// heap (196 MiB at most in the same job), the stage times within run-to-run noise. Call it
/// before any other thread exists (before the tokio runtime is built); a no-op on other
/// platforms.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)] // one call into the C library, nothing else
pub fn limit_malloc_arenas() {
    let cores = std::thread::available_parallelism().map_or(2, |n| n.get()).clamp(2, 64);
    // SAFETY: mallopt only sets a tuning parameter of the allocator; the caller runs it before
    // any other thread exists.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, cores as libc::c_int);
    }
}

/// Limits glibc's malloc to one arena per core (a no-op without glibc).
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn limit_malloc_arenas() {}

/// A service binary's `main`: [`limit_malloc_arenas`], then `service` to completion on a
/// multi-thread tokio runtime built after it (so no runtime thread exists yet). Errors: the
/// runtime could not be built.
pub fn run<T>(service: impl std::future::Future<Output = T>) -> std::io::Result<T> {
    limit_malloc_arenas();
    Ok(tokio::runtime::Builder::new_multi_thread().enable_all().build()?.block_on(service))
}
