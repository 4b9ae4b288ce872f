//! The adaptive feed/speed loop of seed 002 (DESIGN §5), and the feed-only baseline that
//! commercial controllers use, behind one [`Policy`] trait so both run the same program.
//!
//! # The permitted region
//! In the control plane (w = feed mm/min, n = spindle rpm) six constraints bound the region:
//! torque `T <= T_max`; deflection (tool force `F = T/r <= F_max`, the force that bends the tool
//! by the allowed deflection); feed per tooth `fz_min <= w/(z·n) <= fz_max`; feed motor
//! `w_min <= w <= w_max`; spindle `n_min <= n <= n_max`; power `P <= P_max`. With Kienzle,
//! `T ∝ (w/n)^(1−mc)` and `P ∝ w^yp · n^(1−yp)` with `yp = 1 − mc`, so torque and deflection bound
//! `w/n` and power bounds `w^yp·n^(1−yp)`: the region moves as hardness and depth change, which is
//! why it is measured, not precomputed.
//!
//! # One update per spindle revolution
//! Measure (revolution averages): w, n, torque (from the motor current, which resolves ~3 mN·m,
//! rather than the 0.139 N·m torque ADC; the ADC's maximum is kept for overloads), power. Every
//! violated constraint votes: torque, deflection and high feed per tooth → WDEC + NINC; low feed
//! per tooth → WINC + NDEC; feed above/below its range → WDEC/WINC; speed above/below → NDEC/NINC;
//! power → WDEC + NDEC. Then, as in the seed,
//! `w ← w + (WINC − WDEC)·Δw` when WINC ≠ WDEC, else `w ← w + Δw` (inside the region the feed is
//! raised for productivity); `n ← n + (NINC − NDEC)·Δn`. Hysteresis on the measured constraints
//! (torque, deflection, power): one becomes active above its limit and clears only below
//! `limit·(1 − band)`; while a measured value sits in that band the feed is held instead of
//! raised, so the loop does not chatter on one count. Feed, speed and feed-per-tooth limits are
//! exact (computed from the commanded values) and have no band.
//! Results are clamped to the machine's ranges.
//!
//! # Feed-only baseline
//! Hold the cutting power at a reference by a feed override within `[min, max]` (proportional
//! step per revolution); on overload (torque or power above its limit) the override drops to its
//! minimum at once. The spindle stays at the programmed speed.

use serde::Serialize;

/// Bounds of the permitted region for one tool, material and machine.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Limits {
    pub torque_max_nm: f64,
    pub force_max_n: f64,
    pub tool_radius_mm: f64,
    pub teeth: u32,
    pub fz_min_mm: f64,
    pub fz_max_mm: f64,
    pub feed_min_mm_min: f64,
    pub feed_max_mm_min: f64,
    pub rpm_min: f64,
    pub rpm_max: f64,
    pub power_max_w: f64,
}

/// Loop tuning.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Tuning {
    /// Feed step per revolution, mm/min.
    pub dw_mm_min: f64,
    /// Speed step per revolution, rpm.
    pub dn_rpm: f64,
    /// Hysteresis band as a fraction of each limit.
    pub band: f64,
}

impl Default for Tuning {
    fn default() -> Self {
        Tuning { dw_mm_min: 4.0, dn_rpm: 20.0, band: 0.08 }
    }
}

/// What the loop measured over one revolution.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct Measured {
    pub feed_mm_min: f64,
    pub rpm: f64,
    /// Cutting torque from the motor current, N·m.
    pub torque_nm: f64,
    /// Maximum of the torque ADC over the revolution, N·m.
    pub torque_adc_max_nm: f64,
    /// Cutting power, W.
    pub power_w: f64,
}

/// The constraints, as reported in telemetry.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Constraint {
    Torque,
    Deflection,
    FeedPerToothHigh,
    FeedPerToothLow,
    FeedMax,
    FeedMin,
    SpeedMax,
    SpeedMin,
    Power,
}

impl Constraint {
    pub const ALL: [Constraint; 9] = [
        Constraint::Torque,
        Constraint::Deflection,
        Constraint::FeedPerToothHigh,
        Constraint::FeedPerToothLow,
        Constraint::FeedMax,
        Constraint::FeedMin,
        Constraint::SpeedMax,
        Constraint::SpeedMin,
        Constraint::Power,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            Constraint::Torque => "torque",
            Constraint::Deflection => "deflection",
            Constraint::FeedPerToothHigh => "fz_high",
            Constraint::FeedPerToothLow => "fz_low",
            Constraint::FeedMax => "feed_max",
            Constraint::FeedMin => "feed_min",
            Constraint::SpeedMax => "speed_max",
            Constraint::SpeedMin => "speed_min",
            Constraint::Power => "power",
        }
    }
}

/// The loop's decision for the next revolution.
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct Decision {
    pub feed_mm_min: f64,
    pub rpm: f64,
    /// Constraints active (violated, or not yet back below their hysteresis band).
    pub active: Vec<Constraint>,
}

/// A feed/speed policy run once per spindle revolution.
pub trait Policy: Send {
    /// Name for reports: `aco`, `feed_only` or `off`.
    fn name(&self) -> &'static str;
    /// Called when a new program block sets `F` and `S` (the programmed values).
    fn programmed(&mut self, feed_mm_min: f64, rpm: f64);
    /// One revolution's measurement in, next revolution's feed and speed out.
    fn step(&mut self, m: &Measured) -> Decision;
}

/// No adaptation: the programmed feed and speed.
#[derive(Debug, Clone, Default)]
pub struct Fixed {
    feed: f64,
    rpm: f64,
}

impl Policy for Fixed {
    fn name(&self) -> &'static str {
        "off"
    }
    fn programmed(&mut self, feed_mm_min: f64, rpm: f64) {
        (self.feed, self.rpm) = (feed_mm_min, rpm);
    }
    fn step(&mut self, _m: &Measured) -> Decision {
        Decision { feed_mm_min: self.feed, rpm: self.rpm, active: Vec::new() }
    }
}

/// The seed's adaptive control of feed and speed (`aco`).
#[derive(Debug, Clone)]
pub struct Aco {
    limits: Limits,
    tuning: Tuning,
    w: f64,
    n: f64,
    active: [bool; 9],
}

impl Aco {
    pub fn new(limits: Limits, tuning: Tuning) -> Self {
        Aco { limits, tuning, w: limits.feed_min_mm_min, n: limits.rpm_min, active: [false; 9] }
    }

    /// (value, limit, is an upper bound) of each constraint at a measurement.
    fn values(&self, m: &Measured) -> [(f64, f64, bool); 9] {
        let l = &self.limits;
        let fz = m.feed_mm_min / (f64::from(l.teeth.max(1)) * m.rpm.max(1.0));
        let torque = m.torque_nm;
        let force = torque * 1000.0 / l.tool_radius_mm.max(1e-3);
        [
            (torque, l.torque_max_nm, true),
            (force, l.force_max_n, true),
            (fz, l.fz_max_mm, true),
            (fz, l.fz_min_mm, false),
            (m.feed_mm_min, l.feed_max_mm_min, true),
            (m.feed_mm_min, l.feed_min_mm_min, false),
            (m.rpm, l.rpm_max, true),
            (m.rpm, l.rpm_min, false),
            (m.power_w, l.power_max_w, true),
        ]
    }
}

impl Policy for Aco {
    fn name(&self) -> &'static str {
        "aco"
    }

    fn programmed(&mut self, feed_mm_min: f64, rpm: f64) {
        self.w = feed_mm_min.clamp(self.limits.feed_min_mm_min, self.limits.feed_max_mm_min);
        self.n = rpm.clamp(self.limits.rpm_min, self.limits.rpm_max);
    }

    fn step(&mut self, m: &Measured) -> Decision {
        let (mut winc, mut wdec, mut ninc, mut ndec) = (0i32, 0i32, 0i32, 0i32);
        let mut in_band = false;
        let values = self.values(m);
        for (i, &(v, limit, upper)) in values.iter().enumerate() {
            // Hysteresis on the measured constraints only; feed and speed limits are exact.
            let measured =
                matches!(Constraint::ALL[i], Constraint::Torque | Constraint::Deflection | Constraint::Power);
            let band = if measured { self.tuning.band } else { 0.0 };
            let (over, clear) = if upper {
                (v > limit, v < limit * (1.0 - band))
            } else {
                (v < limit, v > limit * (1.0 + band))
            };
            if over {
                self.active[i] = true;
            } else if clear {
                self.active[i] = false;
            } else if !self.active[i] && measured {
                in_band = true;
            }
            if !self.active[i] {
                continue;
            }
            match Constraint::ALL[i] {
                Constraint::Torque | Constraint::Deflection | Constraint::FeedPerToothHigh => {
                    wdec += 1;
                    ninc += 1;
                }
                Constraint::FeedPerToothLow => {
                    winc += 1;
                    ndec += 1;
                }
                Constraint::FeedMax => wdec += 1,
                Constraint::FeedMin => winc += 1,
                Constraint::SpeedMax => ndec += 1,
                Constraint::SpeedMin => ninc += 1,
                Constraint::Power => {
                    wdec += 1;
                    ndec += 1;
                }
            }
        }
        let l = &self.limits;
        let t = &self.tuning;
        if winc != wdec {
            self.w += f64::from(winc - wdec) * t.dw_mm_min;
        } else if !in_band {
            self.w += t.dw_mm_min;
        }
        self.n += f64::from(ninc - ndec) * t.dn_rpm;
        self.w = self.w.clamp(l.feed_min_mm_min, l.feed_max_mm_min);
        self.n = self.n.clamp(l.rpm_min, l.rpm_max);
        let active = Constraint::ALL.iter().zip(self.active).filter(|(_, a)| *a).map(|(c, _)| *c).collect();
        Decision { feed_mm_min: self.w, rpm: self.n, active }
    }
}

/// The feed-only baseline: hold cutting power at `power_ref_w` by a feed override.
#[derive(Debug, Clone)]
pub struct FeedOnly {
    limits: Limits,
    pub power_ref_w: f64,
    pub override_min: f64,
    pub override_max: f64,
    /// Override change per revolution per unit of relative power error.
    pub gain: f64,
    factor: f64,
    feed: f64,
    rpm: f64,
}

impl FeedOnly {
    pub fn new(limits: Limits, power_ref_w: f64) -> Self {
        FeedOnly {
            limits,
            power_ref_w,
            override_min: 0.1,
            override_max: 1.5,
            gain: 0.05,
            factor: 1.0,
            feed: limits.feed_min_mm_min,
            rpm: limits.rpm_min,
        }
    }
}

impl Policy for FeedOnly {
    fn name(&self) -> &'static str {
        "feed_only"
    }

    fn programmed(&mut self, feed_mm_min: f64, rpm: f64) {
        (self.feed, self.rpm) = (feed_mm_min, rpm);
    }

    fn step(&mut self, m: &Measured) -> Decision {
        let l = &self.limits;
        let mut active = Vec::new();
        let overload_t = m.torque_nm > l.torque_max_nm || m.torque_adc_max_nm > 1.5 * l.torque_max_nm;
        let overload_p = m.power_w > l.power_max_w;
        if overload_t || overload_p {
            self.factor = self.override_min;
            if overload_t {
                active.push(Constraint::Torque);
            }
            if overload_p {
                active.push(Constraint::Power);
            }
        } else {
            let err = (self.power_ref_w - m.power_w) / self.power_ref_w.max(1e-6);
            self.factor =
                (self.factor + self.gain * err.clamp(-2.0, 1.0)).clamp(self.override_min, self.override_max);
        }
        let feed = (self.feed * self.factor).clamp(l.feed_min_mm_min, l.feed_max_mm_min);
        Decision { feed_mm_min: feed, rpm: self.rpm.clamp(l.rpm_min, l.rpm_max), active }
    }
}

/// Inputs of the productivity index.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Economics {
    /// Scale constant K.
    pub k: f64,
    /// Tool life T, min.
    pub tool_life_min: f64,
    /// Tool cost Cs.
    pub tool_cost: f64,
    /// ks: constant of the tool-change cost term.
    pub ks: f64,
    /// Power while changing tools Ps, kW.
    pub tool_change_power_kw: f64,
    /// Tool change time ts, min.
    pub tool_change_min: f64,
    /// Labour cost per minute Ct.
    pub labour_per_min: f64,
    /// Regrind time tr, min.
    pub regrind_min: f64,
    /// Energy cost per kWh Ce.
    pub energy_per_kwh: f64,
}

impl Default for Economics {
    /// Illustrative figures for a small shop (assumptions, documented in the report).
    fn default() -> Self {
        Economics {
            k: 1.0,
            tool_life_min: 60.0,
            tool_cost: 20.0,
            ks: 0.1,
            tool_change_power_kw: 0.1,
            tool_change_min: 2.0,
            labour_per_min: 0.5,
            regrind_min: 10.0,
            energy_per_kwh: 0.25,
        }
    }
}

/// Productivity index of seed 002:
/// `I = K·w·B·Δ·ρ·T / (Cs + ks·Cs·Ps·ts + Ct·(tr+T) + Ce·Pc·T)` with `w` mm/min, `B` cut width mm,
/// `Δ` depth mm, `ρ` g/cm³, `Pc` cutting power kW (Ce per kWh, T in min: the energy term uses
/// hours). Higher is better.
pub fn productivity(e: &Economics, w: f64, width_mm: f64, depth_mm: f64, rho: f64, cut_power_kw: f64) -> f64 {
    let t = e.tool_life_min;
    let denom = e.tool_cost
        + e.ks * e.tool_cost * e.tool_change_power_kw * e.tool_change_min
        + e.labour_per_min * (e.regrind_min + t)
        + e.energy_per_kwh * cut_power_kw * t / 60.0;
    e.k * w * width_mm * depth_mm * rho * t / denom.max(1e-12)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> Limits {
        Limits {
            torque_max_nm: 0.5,
            force_max_n: 1000.0,
            tool_radius_mm: 3.0,
            teeth: 2,
            fz_min_mm: 0.005,
            fz_max_mm: 0.3,
            feed_min_mm_min: 5.0,
            feed_max_mm_min: 400.0,
            rpm_min: 300.0,
            rpm_max: 2000.0,
            power_max_w: 400.0,
        }
    }

    /// A plant: Kienzle torque `T = c·(w/n)^(1−mc)` with hardness `c`.
    fn plant(c: f64, w: f64, n: f64) -> Measured {
        let t = c * (w / n).powf(0.75);
        Measured {
            feed_mm_min: w,
            rpm: n,
            torque_nm: t,
            torque_adc_max_nm: t,
            power_w: t * n * std::f64::consts::TAU / 60.0,
        }
    }

    fn run(policy: &mut dyn Policy, c: impl Fn(usize) -> f64, revs: usize) -> Vec<(Measured, Decision)> {
        policy.programmed(200.0, 1000.0);
        let mut d = policy.step(&Measured { feed_mm_min: 200.0, rpm: 1000.0, ..Default::default() });
        let mut out = Vec::new();
        for k in 0..revs {
            let m = plant(c(k), d.feed_mm_min, d.rpm);
            d = policy.step(&m);
            out.push((m, d.clone()));
        }
        out
    }

    #[test]
    fn inside_the_region_feed_rises_to_its_limit() {
        let mut aco = Aco::new(limits(), Tuning::default());
        let trace = run(&mut aco, |_| 0.2, 300);
        let last = &trace[trace.len() - 1].1;
        assert!(last.feed_mm_min > 390.0, "{last:?}");
        assert!(trace.iter().all(|(m, _)| m.torque_nm <= 0.5 * 1.02));
    }

    #[test]
    fn a_hard_inclusion_pulls_the_point_back_inside_and_does_not_chatter() {
        let mut aco = Aco::new(limits(), Tuning::default());
        // Soft, then 3x harder for 400 revolutions, then soft again.
        let trace = run(&mut aco, |k| if (200..600).contains(&k) { 3.0 } else { 1.0 }, 900);
        // Torque over the limit only briefly after the step (the loop needs some revolutions).
        let over = trace[200..600].iter().filter(|(m, _)| m.torque_nm > 0.5).count();
        assert!(over < 80, "{over} revolutions over the torque limit");
        // Settled in the hard zone: below the limit, within the band, feed not oscillating.
        let settled = &trace[450..600];
        assert!(
            settled.iter().all(|(m, _)| m.torque_nm <= 0.5 && m.torque_nm > 0.5 * 0.8),
            "{:?}",
            settled[0]
        );
        let feeds: Vec<f64> = settled.iter().map(|(_, d)| d.feed_mm_min).collect();
        let changes = feeds.windows(2).filter(|w| (w[1] - w[0]).abs() > 1e-9).count();
        assert!(changes < 20, "{changes} feed changes in 150 settled revolutions");
        // A fixed feed in the same zone exceeds the limit.
        let mut fixed = Fixed::default();
        let trace_fixed = run(&mut fixed, |k| if (200..600).contains(&k) { 3.0 } else { 1.0 }, 900);
        assert!(trace_fixed[300].0.torque_nm > 0.5, "{:?}", trace_fixed[300].0);
    }

    #[test]
    fn feed_only_holds_power_and_reacts_to_overload() {
        let mut p = FeedOnly::new(limits(), 40.0);
        let trace = run(&mut p, |_| 1.0, 400);
        let last = &trace[trace.len() - 1].0;
        assert!((last.power_w - 40.0).abs() < 4.0, "{last:?}");
        assert!(trace.iter().all(|(_, d)| (d.rpm - 1000.0).abs() < 1e-9), "speed untouched");
        let mut p = FeedOnly::new(limits(), 60.0);
        p.programmed(400.0, 1000.0);
        let d = p.step(&plant(20.0, 400.0, 1000.0));
        assert_eq!(d.feed_mm_min, 40.0, "overload drops the override to its minimum");
        assert!(d.active.contains(&Constraint::Torque));
    }

    #[test]
    fn productivity_grows_with_feed() {
        let e = Economics::default();
        let a = productivity(&e, 100.0, 3.0, 1.0, 2.7, 0.05);
        let b = productivity(&e, 200.0, 3.0, 1.0, 2.7, 0.05);
        assert!(b > a && a > 0.0);
    }
}
