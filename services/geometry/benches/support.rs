//! What the geometry benches share: their result type, command-line options and Gaussian noise.

use rand::Rng;
use rand::rngs::StdRng;

pub type BoxResult<T> = Result<T, Box<dyn std::error::Error>>;

/// The value after `name` on the command line, parsed, else `default`.
pub fn arg<T: std::str::FromStr>(args: &[String], name: &str, default: T) -> T {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// A standard normal deviate (Box–Muller).
pub fn gauss(rng: &mut StdRng) -> f64 {
    let u: f64 = rng.random_range(1e-12..1.0);
    let v: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}
