//! Encoder latching (DESIGN §6): at every scanner sync pulse the robot and the rotary table store
//! their positions, so each profile can be placed with the pose it was taken at.
//!
//! The device has seven channels: the scanner's pose from the robot controller as X, Y, Z (mm)
//! and yaw, pitch, roll (degrees, ZYX), and the table angle (degrees, unwrapped). Operations
//! mirror the device interface: `initialize`, `uninitialize`, `is_initialized`,
//! `begin_latching`, `end_latching`, `write_encoder` (set a channel's origin),
//! `read_encoders` (now), `is_latching`, `dev_caps`, `external_clock_frequency`; events
//! [`LatchEvent::FirstExternalClock`] (the first pulse after `begin_latching`) and
//! [`LatchEvent::Latch`] (positions stored at a pulse), drained with [`EncoderLatch::take_events`].
//!
//! Timing: a pulse at `t` latches the positions at `t + latency + jitter`, `jitter` Gaussian
//! (σ [`LatchConfig::jitter_s`], clipped at ±4σ, seeded), the way a real controller's interrupt
//! answers a little late. The event reports the pulse time and the latched values; a moving axis
//! is therefore off by its speed times the delay, which [`LatchConfig`] makes visible and tests
//! measure. Pulses closer together than the external clock resolves (one clock period) or
//! arriving when the event queue is full are errors, not silent drops.

use std::collections::VecDeque;

use depthmill_geometry::XyzYpr;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Channel order of every reading.
pub const CHANNELS: [&str; 7] = ["x_mm", "y_mm", "z_mm", "yaw_deg", "pitch_deg", "roll_deg", "table_deg"];

/// Where latched positions come from: the robot controller and the table, at a simulated time.
pub trait PositionSource {
    /// The scanner's pose (robot tool frame) at `t_s`.
    fn robot_pose(&mut self, t_s: f64) -> Result<XyzYpr, LatchError>;
    /// The table angle at `t_s`, degrees (unwrapped).
    fn table_deg(&mut self, t_s: f64) -> Result<f64, LatchError>;
}

/// Device settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LatchConfig {
    /// Delay from the pulse to the latch, s.
    pub latency_s: f64,
    /// Standard deviation of the delay, s.
    pub jitter_s: f64,
    /// Frequency of the external clock that timestamps pulses, Hz.
    pub external_clock_hz: f64,
    /// Events kept until drained.
    pub queue_capacity: usize,
    pub seed: u64,
}

impl Default for LatchConfig {
    /// 50 µs latency, 5 µs jitter, a 1 MHz clock, 100 000 queued events (assumptions for a
    /// controller latching on an interrupt).
    fn default() -> Self {
        LatchConfig {
            latency_s: 50e-6,
            jitter_s: 5e-6,
            external_clock_hz: 1e6,
            queue_capacity: 100_000,
            seed: 7,
        }
    }
}

/// What the device can do.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct DevCaps {
    pub channels: usize,
    pub external_clock_hz: f64,
    pub latency_s: f64,
    pub jitter_s: f64,
    pub queue_capacity: usize,
}

/// A device event.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LatchEvent {
    /// The first external clock pulse after `begin_latching`.
    FirstExternalClock { t_s: f64 },
    /// Positions stored at a sync pulse.
    Latch {
        /// Pulses since `begin_latching`, from 0.
        index: u64,
        /// When the pulse came (the scanner frame's time), on the external clock's grid.
        pulse_s: f64,
        /// When the positions were read.
        latched_s: f64,
        /// The seven channels, origins applied.
        values: [f64; 7],
    },
}

/// Errors, each saying what was asked and why it cannot be done.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LatchError {
    #[error("the latch device is not initialized")]
    NotInitialized,
    #[error("latching is not running: call begin_latching first")]
    NotLatching,
    #[error("latching is already running")]
    AlreadyLatching,
    #[error("invalid {field} = {value}: {reason}")]
    Invalid { field: &'static str, value: String, reason: &'static str },
    #[error(
        "pulse at {t_s} s comes {gap_s:.9} s after the previous one, less than one clock period ({period_s:.9} s)"
    )]
    PulseTooSoon { t_s: f64, gap_s: f64, period_s: f64 },
    #[error("the event queue is full ({capacity} events): drain it with take_events")]
    QueueFull { capacity: usize },
    #[error("position source: {0}")]
    Source(String),
}

/// The simulated latching device.
#[derive(Debug)]
pub struct EncoderLatch {
    cfg: LatchConfig,
    initialized: bool,
    latching: bool,
    origins: [f64; 7],
    next_index: u64,
    last_pulse_s: Option<f64>,
    events: VecDeque<LatchEvent>,
    rng: StdRng,
}

impl EncoderLatch {
    /// A powered-off device; errors name a bad setting.
    pub fn new(cfg: LatchConfig) -> Result<Self, LatchError> {
        let bad =
            |field, value: f64, reason| Err(LatchError::Invalid { field, value: value.to_string(), reason });
        if !(cfg.latency_s.is_finite() && (0.0..=1.0).contains(&cfg.latency_s)) {
            return bad("latency_s", cfg.latency_s, "must be in [0, 1] s");
        }
        if !(cfg.jitter_s.is_finite() && (0.0..=0.1).contains(&cfg.jitter_s)) {
            return bad("jitter_s", cfg.jitter_s, "must be in [0, 0.1] s");
        }
        if !(cfg.external_clock_hz.is_finite() && cfg.external_clock_hz >= 1000.0) {
            return bad("external_clock_hz", cfg.external_clock_hz, "must be at least 1 kHz");
        }
        if cfg.queue_capacity == 0 {
            return bad("queue_capacity", 0.0, "must be at least 1");
        }
        Ok(EncoderLatch {
            cfg,
            initialized: false,
            latching: false,
            origins: [0.0; 7],
            next_index: 0,
            last_pulse_s: None,
            events: VecDeque::new(),
            rng: StdRng::seed_from_u64(cfg.seed),
        })
    }

    pub fn initialize(&mut self) {
        self.initialized = true;
    }

    /// Powers off: stops latching and drops queued events; origins are kept.
    pub fn uninitialize(&mut self) {
        self.initialized = false;
        self.latching = false;
        self.events.clear();
    }

    pub fn is_initialized(&self) -> bool {
        self.initialized
    }

    pub fn is_latching(&self) -> bool {
        self.latching
    }

    pub fn dev_caps(&self) -> DevCaps {
        DevCaps {
            channels: CHANNELS.len(),
            external_clock_hz: self.cfg.external_clock_hz,
            latency_s: self.cfg.latency_s,
            jitter_s: self.cfg.jitter_s,
            queue_capacity: self.cfg.queue_capacity,
        }
    }

    pub fn external_clock_frequency(&self) -> f64 {
        self.cfg.external_clock_hz
    }

    /// Starts latching: pulse indices restart at 0 and the next pulse raises `FirstExternalClock`.
    pub fn begin_latching(&mut self) -> Result<(), LatchError> {
        if !self.initialized {
            return Err(LatchError::NotInitialized);
        }
        if self.latching {
            return Err(LatchError::AlreadyLatching);
        }
        self.latching = true;
        self.next_index = 0;
        self.last_pulse_s = None;
        Ok(())
    }

    pub fn end_latching(&mut self) -> Result<(), LatchError> {
        if !self.latching {
            return Err(LatchError::NotLatching);
        }
        self.latching = false;
        Ok(())
    }

    fn raw(&mut self, source: &mut dyn PositionSource, t_s: f64) -> Result<[f64; 7], LatchError> {
        let p = source.robot_pose(t_s)?;
        let a = source.table_deg(t_s)?;
        Ok([p.x_mm, p.y_mm, p.z_mm, p.yaw_deg, p.pitch_deg, p.roll_deg, a])
    }

    /// Sets channel `channel`'s origin so that it reads `value` now (WriteEncoder).
    pub fn write_encoder(
        &mut self,
        channel: usize,
        value: f64,
        source: &mut dyn PositionSource,
        t_s: f64,
    ) -> Result<(), LatchError> {
        if !self.initialized {
            return Err(LatchError::NotInitialized);
        }
        if channel >= CHANNELS.len() || !value.is_finite() {
            return Err(LatchError::Invalid {
                field: "channel",
                value: format!("{channel} = {value}"),
                reason: "needs a channel 0..=6 and a finite value",
            });
        }
        let raw = self.raw(source, t_s)?;
        self.origins[channel] = raw[channel] - value;
        Ok(())
    }

    /// Every channel now, origins applied (ReadEncoders).
    pub fn read_encoders(
        &mut self,
        source: &mut dyn PositionSource,
        t_s: f64,
    ) -> Result<[f64; 7], LatchError> {
        if !self.initialized {
            return Err(LatchError::NotInitialized);
        }
        let raw = self.raw(source, t_s)?;
        Ok(std::array::from_fn(|i| raw[i] - self.origins[i]))
    }

    fn jitter(&mut self) -> f64 {
        if self.cfg.jitter_s == 0.0 {
            return 0.0;
        }
        let u1: f64 = 1.0 - self.rng.random::<f64>();
        let u2: f64 = self.rng.random::<f64>();
        let g = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
        g.clamp(-4.0, 4.0) * self.cfg.jitter_s
    }

    /// A sync pulse at `t_s` (the scanner's frame): latch every channel and queue the event.
    pub fn sync_pulse(
        &mut self,
        source: &mut dyn PositionSource,
        t_s: f64,
    ) -> Result<LatchEvent, LatchError> {
        if !self.initialized {
            return Err(LatchError::NotInitialized);
        }
        if !self.latching {
            return Err(LatchError::NotLatching);
        }
        if !t_s.is_finite() {
            return Err(LatchError::Invalid {
                field: "t_s",
                value: t_s.to_string(),
                reason: "must be finite",
            });
        }
        let period = 1.0 / self.cfg.external_clock_hz;
        let pulse_s = (t_s / period).round() * period;
        if let Some(prev) = self.last_pulse_s
            && pulse_s - prev < period * 0.5
        {
            return Err(LatchError::PulseTooSoon { t_s, gap_s: t_s - prev, period_s: period });
        }
        if self.events.len() + 2 > self.cfg.queue_capacity {
            return Err(LatchError::QueueFull { capacity: self.cfg.queue_capacity });
        }
        if self.last_pulse_s.is_none() {
            self.events.push_back(LatchEvent::FirstExternalClock { t_s: pulse_s });
        }
        let latched_s = pulse_s + (self.cfg.latency_s + self.jitter()).max(0.0);
        let raw = self.raw(source, latched_s)?;
        let values = std::array::from_fn(|i| raw[i] - self.origins[i]);
        let event = LatchEvent::Latch { index: self.next_index, pulse_s, latched_s, values };
        self.next_index += 1;
        self.last_pulse_s = Some(pulse_s);
        self.events.push_back(event);
        Ok(event)
    }

    /// Drains the queued events, oldest first.
    pub fn take_events(&mut self) -> Vec<LatchEvent> {
        self.events.drain(..).collect()
    }
}

/// The simulated cell's devices as a position source: the robot controller and the table model.
pub struct CellSource<'a> {
    pub robot: &'a super::robot::MotionController,
    pub table: &'a mut super::table::model::Table,
}

impl PositionSource for CellSource<'_> {
    fn robot_pose(&mut self, t_s: f64) -> Result<XyzYpr, LatchError> {
        self.robot.latch(t_s).map_err(|e| LatchError::Source(e.to_string()))
    }

    fn table_deg(&mut self, t_s: f64) -> Result<f64, LatchError> {
        // The table model only runs forward: a latch in its past reads its present.
        if t_s > self.table.now_s() {
            self.table.advance_to(t_s);
        }
        Ok(self.table.position_unwrapped_deg())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Robot moving along X at 100 mm/s, table turning at 30 °/s.
    struct Moving;

    impl PositionSource for Moving {
        fn robot_pose(&mut self, t: f64) -> Result<XyzYpr, LatchError> {
            Ok(XyzYpr {
                x_mm: 100.0 * t,
                y_mm: 5.0,
                z_mm: 300.0,
                yaw_deg: 10.0,
                pitch_deg: 0.0,
                roll_deg: 180.0,
            })
        }
        fn table_deg(&mut self, t: f64) -> Result<f64, LatchError> {
            Ok(30.0 * t)
        }
    }

    #[test]
    fn the_device_interface_guards_its_states() {
        let mut d = EncoderLatch::new(LatchConfig::default()).expect("config");
        assert!(!d.is_initialized());
        assert_eq!(d.begin_latching(), Err(LatchError::NotInitialized));
        assert_eq!(d.sync_pulse(&mut Moving, 0.0).map(|_| ()), Err(LatchError::NotInitialized));
        d.initialize();
        assert_eq!(d.sync_pulse(&mut Moving, 0.0).map(|_| ()), Err(LatchError::NotLatching));
        d.begin_latching().expect("begin");
        assert!(d.is_latching());
        assert_eq!(d.begin_latching(), Err(LatchError::AlreadyLatching));
        d.end_latching().expect("end");
        assert_eq!(d.end_latching(), Err(LatchError::NotLatching));
        assert_eq!(d.dev_caps().channels, 7);
        assert_eq!(d.external_clock_frequency(), 1e6);
        let e = EncoderLatch::new(LatchConfig { external_clock_hz: 10.0, ..Default::default() })
            .expect_err("clock");
        assert!(e.to_string().contains("external_clock_hz = 10"), "{e}");
    }

    #[test]
    fn pulses_latch_with_latency_and_jitter_and_the_error_is_speed_times_delay() {
        let cfg = LatchConfig { latency_s: 200e-6, jitter_s: 20e-6, ..Default::default() };
        let mut d = EncoderLatch::new(cfg).expect("config");
        d.initialize();
        d.begin_latching().expect("begin");
        let rate = 100.0;
        let mut delays = Vec::new();
        for k in 0..2000 {
            let t = f64::from(k) / rate;
            let LatchEvent::Latch { index, pulse_s, latched_s, values } =
                d.sync_pulse(&mut Moving, t).expect("pulse")
            else {
                panic!("a latch event")
            };
            assert_eq!(index, k as u64);
            assert!((pulse_s - t).abs() < 1e-6, "on the clock grid");
            let delay = latched_s - pulse_s;
            delays.push(delay);
            // X moves at 100 mm/s: the latched X is late by 100 · delay.
            assert!((values[0] - 100.0 * latched_s).abs() < 1e-9);
            assert!((values[0] - 100.0 * pulse_s - 100.0 * delay).abs() < 1e-9);
            assert!((values[6] - 30.0 * latched_s).abs() < 1e-9);
        }
        let n = delays.len() as f64;
        let mean = delays.iter().sum::<f64>() / n;
        let sd = (delays.iter().map(|d| (d - mean) * (d - mean)).sum::<f64>() / (n - 1.0)).sqrt();
        assert!((mean - 200e-6).abs() < 3e-6, "mean delay {mean}");
        assert!((sd - 20e-6).abs() < 3e-6, "jitter {sd}");
        let events = d.take_events();
        assert_eq!(events.len(), 2001);
        assert_eq!(events[0], LatchEvent::FirstExternalClock { t_s: 0.0 });
        assert!(d.take_events().is_empty());
    }

    #[test]
    fn origins_pulses_too_close_and_a_full_queue_are_handled() {
        let mut d = EncoderLatch::new(LatchConfig { queue_capacity: 4, jitter_s: 0.0, ..Default::default() })
            .expect("config");
        d.initialize();
        d.write_encoder(0, 0.0, &mut Moving, 1.0).expect("origin");
        let now = d.read_encoders(&mut Moving, 1.0).expect("read");
        assert!(now[0].abs() < 1e-12 && (now[2] - 300.0).abs() < 1e-12);
        assert!(d.write_encoder(7, 0.0, &mut Moving, 1.0).is_err());
        d.begin_latching().expect("begin");
        d.sync_pulse(&mut Moving, 1.0).expect("first");
        let e = d.sync_pulse(&mut Moving, 1.0 + 1e-7).expect_err("too soon");
        assert!(matches!(e, LatchError::PulseTooSoon { .. }), "{e}");
        d.sync_pulse(&mut Moving, 1.01).expect("second");
        let e = d.sync_pulse(&mut Moving, 1.02).expect_err("full");
        assert_eq!(e, LatchError::QueueFull { capacity: 4 });
        assert_eq!(d.take_events().len(), 3);
        d.sync_pulse(&mut Moving, 1.03).expect("after draining");
    }

    #[test]
    fn the_cell_source_reads_the_robot_and_the_table() {
        use super::super::table::model::{Table, TableConfig};
        use super::super::table::protocol::Command;
        let robot = super::super::robot::MotionController::viper_s650();
        let mut table = Table::new(TableConfig::default()).expect("table");
        table.command(Command::MoveAbsolute { deg: 90.0 }, 0.0);
        let mut d = EncoderLatch::new(LatchConfig::default()).expect("config");
        d.initialize();
        d.begin_latching().expect("begin");
        let mut src = CellSource { robot: &robot, table: &mut table };
        let mut last = -1.0;
        // 90° at the default 20 °/s and 40 °/s²: 5 s.
        for k in 0..70 {
            let t = 0.1 * f64::from(k);
            let LatchEvent::Latch { values, .. } = d.sync_pulse(&mut src, t).expect("pulse") else {
                panic!("a latch event")
            };
            assert!(values.iter().all(|v| v.is_finite()));
            assert!(values[6] >= last - 1e-6, "the table turns one way");
            last = values[6];
        }
        assert!((last - 90.0).abs() < 0.05, "the table arrived: {last}");
    }
}
