//! The cell's devices over gRPC, the interfaces of DESIGN §6: `MotionControllerService` for the
//! arm (`device = "robot"`, the default) and the rotary table (`device = "table"`, driven over its
//! protocol), and `EncoderLatchService` latching both at the scanner's sync pulses.
//!
//! These run in real time: the simulated controllers' clock is the time since the service
//! started, so a client sees moves take as long as they would on the cell. Refusals come back as
//! FAILED_PRECONDITION (state: not initialized, busy, e-stop latched) or INVALID_ARGUMENT (a bad
//! target) with the controller's reason.

use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use depthmill_proto::scanning::v1 as pb;
use tokio::net::TcpStream;
use tonic::{Request, Response, Status};

use crate::devices::table::TableClient;
use crate::domain::latch::{EncoderLatch, LatchConfig, LatchError, LatchEvent, PositionSource};
use crate::domain::robot::controller::{ControllerState, MotionController, RobotError};
use crate::domain::table::model::shortest_delta_deg;

pub(crate) const MOTION_SERVICE_NAME: &str = "depthmill.scanning.v1.MotionControllerService";
pub(crate) const LATCH_SERVICE_NAME: &str = "depthmill.scanning.v1.EncoderLatchService";

/// Rate of the scanner's sync pulses while latching over gRPC, Hz.
const SYNC_RATE_HZ: f64 = 100.0;

pub(crate) struct Devices {
    start: tokio::time::Instant,
    robot: Mutex<MotionController>,
    latch: Mutex<EncoderLatch>,
    table: tokio::sync::Mutex<Option<TableClient<TcpStream>>>,
    table_addr: String,
}

impl Devices {
    pub(crate) fn new(table_addr: String) -> Result<Self, LatchError> {
        Ok(Self {
            start: tokio::time::Instant::now(),
            robot: Mutex::new(MotionController::viper_s650()),
            latch: Mutex::new(EncoderLatch::new(LatchConfig::default())?),
            table: tokio::sync::Mutex::new(None),
            table_addr,
        })
    }

    fn now(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    fn robot(&self) -> MutexGuard<'_, MotionController> {
        self.robot.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The controller and the time now, read under its lock (commands must come in time order).
    fn robot_now(&self) -> (MutexGuard<'_, MotionController>, f64) {
        let guard = self.robot();
        let t = self.now();
        (guard, t)
    }

    fn latch(&self) -> MutexGuard<'_, EncoderLatch> {
        self.latch.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The table's angle now, if the table is connected.
    async fn table_deg(&self) -> Result<Option<f64>, Status> {
        let mut t = self.table.lock().await;
        match t.as_mut() {
            Some(c) => c.position_deg().await.map(Some).map_err(table_status),
            None => Ok(None),
        }
    }
}

fn robot_status(e: RobotError) -> Status {
    match e {
        RobotError::NotInitialized { .. }
        | RobotError::NotHomed { .. }
        | RobotError::EstopLatched { .. }
        | RobotError::Busy { .. } => Status::failed_precondition(e.to_string()),
        _ => Status::invalid_argument(e.to_string()),
    }
}

fn table_status(e: crate::devices::table::TableError) -> Status {
    Status::unavailable(format!("rotary table: {e}"))
}

fn latch_status(e: LatchError) -> Status {
    match e {
        LatchError::Invalid { .. } => Status::invalid_argument(e.to_string()),
        _ => Status::failed_precondition(e.to_string()),
    }
}

enum Device {
    Robot,
    Table,
}

fn device(name: &str) -> Result<Device, Status> {
    match name {
        "" | "robot" => Ok(Device::Robot),
        "table" => Ok(Device::Table),
        other => Err(Status::invalid_argument(format!("device {other:?}: expected \"robot\" or \"table\""))),
    }
}

/// Adds the two device services to `routes`.
pub(crate) fn add_routes(routes: tonic::service::Routes, devices: Arc<Devices>) -> tonic::service::Routes {
    routes
        .add_service(pb::motion_controller_service_server::MotionControllerServiceServer::new(Motion(
            devices.clone(),
        )))
        .add_service(pb::encoder_latch_service_server::EncoderLatchServiceServer::new(Latch(devices)))
}

struct Motion(Arc<Devices>);

impl Motion {
    fn robot_status(&self) -> pb::MotionStatus {
        let d = &self.0;
        let t = d.now();
        let r = d.robot();
        let (moving, fault) = match r.read_status(t) {
            Ok(s) => (s.moving, s.last_error.map(|e| e.to_string()).unwrap_or_default()),
            Err(e) => (false, e.to_string()),
        };
        pb::MotionStatus {
            initialized: r.is_initialized(),
            moving,
            homed: r.state() == ControllerState::Homed,
            fault,
            joints_deg: r.read_position(t).map(|q| q.to_vec()).unwrap_or_default(),
        }
    }

    async fn table_status(&self) -> Result<pb::MotionStatus, Status> {
        let mut t = self.0.table.lock().await;
        let Some(c) = t.as_mut() else {
            return Ok(pb::MotionStatus::default());
        };
        let a = c.position_deg().await.map_err(table_status)?;
        let b = c.position_deg().await.map_err(table_status)?;
        let at_target = c.target_deg().is_none_or(|g| shortest_delta_deg(g, b).abs() <= 0.0625);
        Ok(pb::MotionStatus {
            initialized: true,
            moving: a != b || !at_target,
            homed: true,
            fault: String::new(),
            joints_deg: vec![b],
        })
    }

    async fn with_table<T>(
        &self,
        f: impl AsyncFnOnce(&mut TableClient<TcpStream>) -> Result<T, crate::devices::table::TableError>,
    ) -> Result<T, Status> {
        let mut t = self.0.table.lock().await;
        let c = t.as_mut().ok_or_else(|| {
            Status::failed_precondition(
                "the table is not initialized (call Initialize with device \"table\")",
            )
        })?;
        f(c).await.map_err(table_status)
    }

    /// Stops the table where it is: a move to its own position (the protocol has no stop).
    async fn hold_table(&self) -> Result<(), Status> {
        self.with_table(async |c| {
            let here = c.position_deg().await?;
            c.move_to(here).await
        })
        .await
    }

    async fn status(&self, dev: Device) -> Result<Response<pb::MotionStatus>, Status> {
        Ok(Response::new(match dev {
            Device::Robot => self.robot_status(),
            Device::Table => self.table_status().await?,
        }))
    }
}

#[tonic::async_trait]
impl pb::motion_controller_service_server::MotionControllerService for Motion {
    async fn initialize(&self, r: Request<pb::MotionRequest>) -> Result<Response<pb::MotionStatus>, Status> {
        let dev = device(&r.get_ref().device)?;
        match dev {
            Device::Robot => {
                let (mut robot, t) = self.0.robot_now();
                robot.initialize(t).map_err(robot_status)?;
            }
            Device::Table => {
                let mut t = self.0.table.lock().await;
                if t.is_none() {
                    *t = Some(TableClient::connect(self.0.table_addr.as_str()).await.map_err(table_status)?);
                }
            }
        }
        self.status(dev).await
    }

    async fn uninitialize(
        &self,
        r: Request<pb::MotionRequest>,
    ) -> Result<Response<pb::MotionStatus>, Status> {
        let dev = device(&r.get_ref().device)?;
        match dev {
            Device::Robot => {
                let (mut robot, t) = self.0.robot_now();
                robot.uninitialize(t).map_err(robot_status)?;
            }
            Device::Table => *self.0.table.lock().await = None,
        }
        self.status(dev).await
    }

    async fn is_initialized(
        &self,
        r: Request<pb::MotionRequest>,
    ) -> Result<Response<pb::MotionStatus>, Status> {
        self.status(device(&r.get_ref().device)?).await
    }

    async fn home(&self, r: Request<pb::MotionRequest>) -> Result<Response<pb::MotionStatus>, Status> {
        let dev = device(&r.get_ref().device)?;
        match dev {
            Device::Robot => {
                let (mut robot, t) = self.0.robot_now();
                robot.home(t, 0.5).map_err(robot_status)?;
            }
            Device::Table => self.with_table(async |c| c.move_to(0.0).await).await?,
        }
        self.status(dev).await
    }

    async fn r#move(&self, r: Request<pb::MoveRequest>) -> Result<Response<pb::MotionStatus>, Status> {
        let m = r.into_inner();
        let dev = device(&m.device)?;
        match dev {
            Device::Robot => {
                let (mut robot, t) = self.0.robot_now();
                let axis = m.axis as usize;
                let frac = match m.speed_deg_s {
                    Some(v) => {
                        let lim = robot.model().limits.get(axis.wrapping_sub(1)).map(|l| l.max_speed_deg_s);
                        let top = lim.ok_or_else(|| {
                            Status::invalid_argument(format!("axis {axis}: expected 1..=6"))
                        })?;
                        v / top
                    }
                    None => 0.5,
                };
                robot.move_joint(t, axis, m.target_deg, frac).map_err(robot_status)?;
            }
            Device::Table => {
                if m.axis > 1 {
                    return Err(Status::invalid_argument(format!(
                        "axis {}: the table has one axis (1)",
                        m.axis
                    )));
                }
                self.with_table(async |c| {
                    if let Some(v) = m.speed_deg_s {
                        c.set_speed(v).await?;
                    }
                    if let Some(a) = m.accel_deg_s2 {
                        c.set_accel(a).await?;
                    }
                    c.move_to(m.target_deg).await
                })
                .await?;
            }
        }
        self.status(dev).await
    }

    async fn coordinated_move(
        &self,
        r: Request<pb::CoordinatedMoveRequest>,
    ) -> Result<Response<pb::MotionStatus>, Status> {
        let m = r.into_inner();
        let dev = device(&m.device)?;
        match dev {
            Device::Robot => {
                let targets: Vec<(usize, f64)> =
                    m.targets_deg.iter().enumerate().map(|(i, q)| (i + 1, *q)).collect();
                let (mut robot, t) = self.0.robot_now();
                robot.coordinated_move(t, &targets, m.speed_fraction.unwrap_or(0.5)).map_err(robot_status)?;
            }
            Device::Table => {
                let [target] = m.targets_deg[..] else {
                    return Err(Status::invalid_argument(format!(
                        "targets_deg: the table has one axis, got {} targets",
                        m.targets_deg.len()
                    )));
                };
                self.with_table(async |c| c.move_to(target).await).await?;
            }
        }
        self.status(dev).await
    }

    async fn read_position(&self, r: Request<pb::MotionRequest>) -> Result<Response<pb::Position>, Status> {
        match device(&r.get_ref().device)? {
            Device::Robot => {
                let (robot, t) = self.0.robot_now();
                let q = robot.read_position(t).map_err(robot_status)?;
                let p = robot.latch(t).map_err(robot_status)?;
                Ok(Response::new(pb::Position {
                    joints_deg: q.to_vec(),
                    tool: Some(pb::Pose {
                        x_mm: p.x_mm,
                        y_mm: p.y_mm,
                        z_mm: p.z_mm,
                        yaw_deg: p.yaw_deg,
                        pitch_deg: p.pitch_deg,
                        roll_deg: p.roll_deg,
                    }),
                }))
            }
            Device::Table => {
                let a = self.with_table(async |c| c.position_deg().await).await?;
                Ok(Response::new(pb::Position { joints_deg: vec![a], tool: None }))
            }
        }
    }

    async fn read_status(&self, r: Request<pb::MotionRequest>) -> Result<Response<pb::MotionStatus>, Status> {
        self.status(device(&r.get_ref().device)?).await
    }

    async fn reset(&self, r: Request<pb::MotionRequest>) -> Result<Response<pb::MotionStatus>, Status> {
        let dev = device(&r.get_ref().device)?;
        match dev {
            Device::Robot => {
                let (mut robot, t) = self.0.robot_now();
                robot.reset(t).map_err(robot_status)?;
            }
            // The table's protocol has no emergency stop: hold where it is.
            Device::Table => self.hold_table().await?,
        }
        self.status(dev).await
    }

    async fn stop(&self, r: Request<pb::AxisRequest>) -> Result<Response<pb::MotionStatus>, Status> {
        let a = r.into_inner();
        let dev = device(&a.device)?;
        match dev {
            Device::Robot => {
                let (mut robot, t) = self.0.robot_now();
                robot.stop(t, a.axis as usize).map_err(robot_status)?;
            }
            Device::Table => self.hold_table().await?,
        }
        self.status(dev).await
    }
}

struct Latch(Arc<Devices>);

/// The robot controller and a table angle read just before.
struct LiveSource<'a> {
    robot: &'a MotionController,
    table_deg: f64,
}

impl PositionSource for LiveSource<'_> {
    fn robot_pose(&mut self, t_s: f64) -> Result<depthmill_geometry::XyzYpr, LatchError> {
        self.robot.latch(t_s).map_err(|e| LatchError::Source(e.to_string()))
    }

    fn table_deg(&mut self, _t_s: f64) -> Result<f64, LatchError> {
        Ok(self.table_deg)
    }
}

fn positions(pulse: u64, time_s: f64, v: &[f64; 7], first: bool) -> pb::LatchedPositions {
    pb::LatchedPositions {
        pulse,
        time_s,
        robot: Some(pb::Pose {
            x_mm: v[0],
            y_mm: v[1],
            z_mm: v[2],
            yaw_deg: v[3],
            pitch_deg: v[4],
            roll_deg: v[5],
        }),
        table_deg: v[6],
        first_external_clock: first,
    }
}

impl Latch {
    fn status(&self) -> Response<pb::LatchStatus> {
        let l = self.0.latch();
        Response::new(pb::LatchStatus { initialized: l.is_initialized(), latching: l.is_latching() })
    }
}

type LatchStream = Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::LatchedPositions, Status>> + Send>>;

#[tonic::async_trait]
impl pb::encoder_latch_service_server::EncoderLatchService for Latch {
    type LatchEncodersStream = LatchStream;

    async fn initialize(&self, _: Request<pb::LatchRequest>) -> Result<Response<pb::LatchStatus>, Status> {
        self.0.latch().initialize();
        Ok(self.status())
    }

    async fn uninitialize(&self, _: Request<pb::LatchRequest>) -> Result<Response<pb::LatchStatus>, Status> {
        self.0.latch().uninitialize();
        Ok(self.status())
    }

    async fn is_initialized(
        &self,
        _: Request<pb::LatchRequest>,
    ) -> Result<Response<pb::LatchStatus>, Status> {
        Ok(self.status())
    }

    async fn begin_latching(
        &self,
        _: Request<pb::LatchRequest>,
    ) -> Result<Response<pb::LatchStatus>, Status> {
        self.0.latch().begin_latching().map_err(latch_status)?;
        Ok(self.status())
    }

    async fn end_latching(&self, _: Request<pb::LatchRequest>) -> Result<Response<pb::LatchStatus>, Status> {
        self.0.latch().end_latching().map_err(latch_status)?;
        Ok(self.status())
    }

    async fn write_encoder(
        &self,
        r: Request<pb::WriteEncoderRequest>,
    ) -> Result<Response<pb::LatchStatus>, Status> {
        let w = r.into_inner();
        let table_deg = self.0.table_deg().await?.unwrap_or(0.0);
        {
            let (robot, t) = self.0.robot_now();
            let mut src = LiveSource { robot: &robot, table_deg };
            self.0.latch().write_encoder(w.encoder as usize, w.value, &mut src, t).map_err(latch_status)?;
        }
        Ok(self.status())
    }

    async fn read_encoders(
        &self,
        _: Request<pb::LatchRequest>,
    ) -> Result<Response<pb::LatchedPositions>, Status> {
        let table_deg = self.0.table_deg().await?.unwrap_or(0.0);
        let (robot, t) = self.0.robot_now();
        let mut src = LiveSource { robot: &robot, table_deg };
        let v = self.0.latch().read_encoders(&mut src, t).map_err(latch_status)?;
        Ok(Response::new(positions(0, t, &v, false)))
    }

    async fn is_latching(&self, _: Request<pb::LatchRequest>) -> Result<Response<pb::LatchStatus>, Status> {
        Ok(self.status())
    }

    async fn dev_caps(
        &self,
        _: Request<pb::LatchRequest>,
    ) -> Result<Response<pb::DeviceCapabilities>, Status> {
        let c = self.0.latch().dev_caps();
        Ok(Response::new(pb::DeviceCapabilities {
            encoders: c.channels as u32,
            max_clock_hz: c.external_clock_hz,
            latency_s: c.latency_s,
        }))
    }

    async fn external_clock_frequency(
        &self,
        _: Request<pb::LatchRequest>,
    ) -> Result<Response<pb::ClockFrequency>, Status> {
        Ok(Response::new(pb::ClockFrequency { hz: self.0.latch().external_clock_frequency() }))
    }

    /// Events at the scanner's sync pulses (100 Hz) while latching; the stream ends at EndLatching.
    async fn latch_encoders(
        &self,
        _: Request<pb::LatchRequest>,
    ) -> Result<Response<Self::LatchEncodersStream>, Status> {
        if !self.0.latch().is_latching() {
            return Err(Status::failed_precondition("latching is not running: call BeginLatching first"));
        }
        let (tx, rx) = tokio::sync::mpsc::channel(256);
        let devices = self.0.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / SYNC_RATE_HZ));
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
            loop {
                tick.tick().await;
                let table_deg = match devices.table_deg().await {
                    Ok(a) => a.unwrap_or(0.0),
                    Err(s) => {
                        let _ = tx.send(Err(s)).await;
                        return;
                    }
                };
                let events = {
                    let (robot, t) = devices.robot_now();
                    let mut latch = devices.latch();
                    if !latch.is_latching() {
                        return;
                    }
                    let mut src = LiveSource { robot: &robot, table_deg };
                    match latch.sync_pulse(&mut src, t) {
                        Ok(_) => latch.take_events(),
                        Err(e) => {
                            drop(latch);
                            let _ = tx.try_send(Err(latch_status(e)));
                            return;
                        }
                    }
                };
                let mut first = false;
                for ev in events {
                    match ev {
                        LatchEvent::FirstExternalClock { .. } => first = true,
                        LatchEvent::Latch { index, pulse_s, values, .. } => {
                            if tx.send(Ok(positions(index, pulse_s, &values, first))).await.is_err() {
                                return;
                            }
                            first = false;
                        }
                    }
                }
            }
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }
}
