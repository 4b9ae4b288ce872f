//! Simulated spindle sensors with their resolution, range and noise (DESIGN §5):
//! torque (TS19 through a 10-bit ADC, about 0.139 N·m per count), spindle current (6.25 mA per
//! count, ±5 A), spindle speed (incremental encoder, 100 pulses per revolution, counted over the
//! sampling window).
//!
//! Noise is Gaussian in counts (Box–Muller on a seeded generator, so a run is reproducible), added
//! before quantisation; readings saturate at the sensor's range. At this machine's scale a cut is
//! a few torque counts: [`RevAverager`] averages the raw samples of one revolution, which is what
//! the adaptive loop reads.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::profile::Sensors;

/// One reading of every spindle sensor, in counts and in engineering units.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct Reading {
    pub torque_counts: i32,
    pub torque_nm: f64,
    pub current_counts: i32,
    pub current_a: f64,
    pub encoder_pulses: u64,
    pub rpm: f64,
}

/// The sensor front end: quantisation, range, noise.
#[derive(Debug, Clone)]
pub struct SensorBank {
    cfg: Sensors,
    rng: StdRng,
    /// Fraction of a pulse left over from the previous window (the encoder is a counter).
    pulse_phase: f64,
}

impl SensorBank {
    /// Sensors of a profile with a fixed seed.
    pub fn new(cfg: Sensors, seed: u64) -> Self {
        SensorBank { cfg, rng: StdRng::seed_from_u64(seed), pulse_phase: 0.0 }
    }

    fn gauss(&mut self) -> f64 {
        // Box–Muller; 1 − u keeps the logarithm finite.
        let u1: f64 = 1.0 - self.rng.random::<f64>();
        let u2: f64 = self.rng.random::<f64>();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// The torque ADC: 10 bits, 0 .. 1023 counts.
    pub fn torque(&mut self, true_nm: f64) -> (i32, f64) {
        let c = true_nm / self.cfg.torque_nm_per_count + self.cfg.torque_noise_counts * self.gauss();
        let max = (self.cfg.torque_max_nm / self.cfg.torque_nm_per_count).min(1023.0);
        let counts = c.round().clamp(0.0, max) as i32;
        (counts, f64::from(counts) * self.cfg.torque_nm_per_count)
    }

    /// The current sensor: ±current_max_a.
    pub fn current(&mut self, true_a: f64) -> (i32, f64) {
        let c = true_a / self.cfg.current_a_per_count + self.cfg.current_noise_counts * self.gauss();
        let max = self.cfg.current_max_a / self.cfg.current_a_per_count;
        let counts = c.round().clamp(-max, max) as i32;
        (counts, f64::from(counts) * self.cfg.current_a_per_count)
    }

    /// Encoder pulses counted over `dt_s` at `true_rpm`, and the speed they give.
    pub fn speed(&mut self, true_rpm: f64, dt_s: f64) -> (u64, f64) {
        let ppr = f64::from(self.cfg.encoder_pulses_per_rev);
        let exact = true_rpm.max(0.0) / 60.0 * ppr * dt_s + self.pulse_phase;
        let pulses = exact.floor();
        self.pulse_phase = exact - pulses;
        let rpm = if dt_s > 0.0 { pulses / ppr / dt_s * 60.0 } else { 0.0 };
        (pulses as u64, rpm)
    }

    /// Reads every sensor once.
    pub fn read(&mut self, torque_nm: f64, current_a: f64, rpm: f64, dt_s: f64) -> Reading {
        let (torque_counts, torque_nm) = self.torque(torque_nm);
        let (current_counts, current_a) = self.current(current_a);
        let (encoder_pulses, rpm) = self.speed(rpm, dt_s);
        Reading { torque_counts, torque_nm, current_counts, current_a, encoder_pulses, rpm }
    }
}

/// Averages raw samples over one spindle revolution (and keeps the maximum torque, which the
/// seed's loop uses).
#[derive(Debug, Clone, Copy, Default)]
pub struct RevAverager {
    n: u32,
    torque: f64,
    current: f64,
    torque_max: f64,
}

impl RevAverager {
    pub fn push(&mut self, r: &Reading) {
        self.n += 1;
        self.torque += r.torque_nm;
        self.current += r.current_a;
        self.torque_max = self.torque_max.max(r.torque_nm);
    }

    /// (mean torque N·m, mean current A, max torque N·m) and a reset; `None` with no samples.
    pub fn take(&mut self) -> Option<(f64, f64, f64)> {
        if self.n == 0 {
            return None;
        }
        let n = f64::from(self.n);
        let out = (self.torque / n, self.current / n, self.torque_max);
        *self = RevAverager::default();
        Some(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::profile::MachineProfile;

    fn bank(seed: u64) -> SensorBank {
        SensorBank::new(MachineProfile::builtin("emco-f1").expect("profile").sensors, seed)
    }

    #[test]
    fn resolution_and_range() {
        let mut quiet = MachineProfile::builtin("emco-f1").expect("profile").sensors;
        quiet.torque_noise_counts = 0.0;
        quiet.current_noise_counts = 0.0;
        let mut s = SensorBank::new(quiet, 1);
        assert_eq!(s.torque(0.16).0, 1, "a typical cut is one count");
        assert_eq!(s.torque(0.06).0, 0);
        assert_eq!(s.torque(1e6).0, 719, "saturates at 100 N·m");
        assert_eq!(s.torque(-1.0).0, 0);
        assert_eq!(s.current(1.0).0, 160, "6.25 mA per count");
        assert_eq!(s.current(-9.0).0, -800, "±5 A");
        // 1000 rpm over 60 ms: exactly one revolution, 100 pulses.
        let (p, rpm) = s.speed(1000.0, 0.06);
        assert_eq!(p, 100);
        assert!((rpm - 1000.0).abs() < 1e-9);
    }

    #[test]
    fn averaging_a_revolution_resolves_what_one_sample_cannot() {
        // 0.09 N·m is below one count; with 0.5 count noise the average of many samples finds it.
        let mut s = bank(7);
        let mut avg = RevAverager::default();
        for _ in 0..4000 {
            let r = s.read(0.09, 0.46, 1500.0, 0.0001);
            avg.push(&r);
        }
        let (t, i, tmax) = avg.take().expect("samples");
        assert!((t - 0.09).abs() < 0.01, "mean torque {t}");
        assert!((i - 0.46).abs() < 0.001, "mean current {i}");
        assert!(tmax >= 0.139);
        assert!(avg.take().is_none(), "reset after take");
    }

    #[test]
    fn the_encoder_keeps_fractional_pulses() {
        let mut s = bank(1);
        let total: u64 = (0..1000).map(|_| s.speed(1234.0, 0.001).0).sum();
        // 1234 rpm for 1 s = 20.567 rev = 2056.7 pulses.
        assert!((2055..=2057).contains(&total), "{total}");
    }
}
