//! The G-code interpreter and the simulated EMCO F1 running the program (removal on a small
//! coarse stock, the adaptive loop on): whatever the program, it runs or is refused, without a
//! panic; the motion-only timing is finite (the travel itself is checked by the machine's
//! property test).
#![no_main]

use depthmill_geometry::ToolProfile;
use depthmill_machine::domain::cutting::material;
use depthmill_machine::domain::profile::MachineProfile;
use depthmill_machine::domain::sim::{MachineTool, PolicyKind, SimError, SimSetup, StockSpec, simulate};
use libfuzzer_sys::fuzz_target;

fn setup() -> Option<SimSetup> {
    Some(SimSetup {
        profile: MachineProfile::builtin("emco-f1").ok()?,
        material: material("aluminium")?,
        stock: StockSpec {
            min_x_mm: 0.0,
            min_y_mm: 0.0,
            min_z_mm: 0.0,
            x_mm: 30.0,
            y_mm: 20.0,
            z_mm: 10.0,
            cell_mm: 0.5,
        },
        faces: Vec::new(),
        dexel: None,
        tools: vec![
            MachineTool {
                number: 1,
                name: "flat-6".into(),
                profile: ToolProfile::flat(6.0).ok()?,
                teeth: 2,
                length_mm: 45.0,
            },
            MachineTool {
                number: 2,
                name: "ball-3".into(),
                profile: ToolProfile::ball(3.0).ok()?,
                teeth: 2,
                length_mm: 40.0,
            },
        ],
        policy: PolicyKind::Aco,
        clamp: false,
        inclusions: Vec::new(),
        seed: 1,
        telemetry_interval_s: 0.5,
        motion_only: false,
    })
}

fuzz_target!(|data: &[u8]| {
    let Some(setup) = setup() else { return };
    // As the service does: motion only first (travel, feeds, speeds, tools checked; the cycle
    // time, cheaply), then the run that cuts. The service refuses programs over 24 h of
    // machining (`MAX_CYCLE_TIME_S`); here cutting is skipped past 5 simulated seconds (cutting
    // is simulated per spindle revolution, up to 67 of them a second at 4000 rpm) so that inputs
    // stay fast.
    let never = || false;
    let plain = SimSetup { policy: PolicyKind::Off, motion_only: true, ..setup.clone() };
    let timed = match simulate(std::io::Cursor::new(data), &plain, &never, &mut |_: &_| {}) {
        Ok((report, _)) => report.cycle_time_s,
        Err(SimError::Setup(e)) => panic!("the fixed setup is valid: {e}"),
        Err(e) => {
            assert!(!e.to_string().is_empty());
            return;
        }
    };
    assert!(timed.is_finite() && timed >= 0.0, "cycle time {timed}");
    if timed > 5.0 {
        return;
    }
    match simulate(std::io::Cursor::new(data), &setup, &never, &mut |_: &_| {}) {
        Ok(_) => {}
        Err(SimError::Setup(e)) => panic!("the fixed setup is valid: {e}"),
        Err(e) => assert!(!e.to_string().is_empty()),
    }
});
