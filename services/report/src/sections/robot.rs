//! A robot milling job (`"process": "robot"`): its summary, the plan (layers, rings, the tool
//! body's clearance check and tilts, the arm's program) with the tip path seen from above, and
//! the simulated run measured against the part's mesh. Data: `plan_report` (the CAM's robot
//! report), `gcode` (the Cartesian program, drawn from its X and Y), `machine_report` (the robot
//! run) and the job's metrics.

use std::fmt::Write as _;

use serde_json::Value;

use crate::html::{esc, kv_table, missing, section, table};
use crate::raster::fmt_num;
use crate::{Ctx, ReportError, fmt_count, fmt_duration};

/// Blocked positions and unreachable stretches listed on the page.
const LISTED: usize = 10;

fn num(v: &Value) -> String {
    v.as_f64().filter(|x| x.is_finite()).map_or("—".to_string(), fmt_num)
}

fn count(v: &Value) -> String {
    v.as_u64().map_or("—".to_string(), |n| fmt_count(n as usize))
}

fn mm(v: &Value) -> String {
    v.as_f64().filter(|x| x.is_finite()).map_or("—".to_string(), |x| format!("{x:.3} mm"))
}

fn secs(v: &Value) -> String {
    v.as_f64().map_or("—".to_string(), fmt_duration)
}

fn point(v: &Value) -> String {
    match v.as_array() {
        Some(a) if a.len() >= 2 => {
            let parts: Vec<String> =
                a.iter().map(|c| c.as_f64().map_or("?".into(), |x| format!("{x:.2}"))).collect();
            format!("({})", parts.join(", "))
        }
        _ => "—".into(),
    }
}

impl Ctx<'_> {
    /// Whether the job is a robot milling job.
    pub(crate) fn is_robot(&self) -> bool {
        self.job["spec"]["process"].as_str() == Some("robot")
    }

    /// The summary of a robot job: the part against its mesh and the arm's time.
    pub(crate) fn robot_summary(&self) -> String {
        let m = |k: &str| self.metric(k).map_or(Value::Null, Value::from);
        let rows = vec![
            (
                "Process".to_string(),
                "robot milling: the 6-axis arm with a spindle, from the mesh".to_string(),
            ),
            ("Max gouge (cut into the part)".into(), mm(&m("max_gouge_mm"))),
            ("Max leftover (material left)".into(), mm(&m("max_leftover_mm"))),
            ("Mean material left".into(), mm(&m("original_mean_leftover_mm"))),
            ("RMS deviation".into(), mm(&m("rms_deviation_mm"))),
            ("Cycle time of the arm".into(), secs(&m("cycle_time_s"))),
            ("Removed by rapid moves (a crash on a real cell)".into(), {
                self.metric("robot_rapid_removed_mm3").map_or("—".into(), |v| format!("{} mm³", fmt_num(v)))
            }),
            ("Positions no tilt clears (left uncut)".into(), count(&m("robot_blocked"))),
            ("Stretches the arm cannot follow".into(), count(&m("robot_unreachable_stretches"))),
        ];
        let rows: Vec<(String, String)> = rows.into_iter().map(|(k, v)| (k, esc(&v))).collect();
        section("summary", "Summary", &kv_table(&rows))
    }

    /// The robot plan and its simulated run.
    pub(crate) fn robot(&mut self) -> Result<String, ReportError> {
        let mut body = String::new();
        body.push_str("<h3>Plan</h3>");
        match self.plan_report.clone() {
            None => body.push_str(&missing(&self.why_missing("plan_report"))),
            Some(p) => body.push_str(&plan_html(&p)),
        }
        body.push_str("<h3>Tip path from above</h3>");
        let picture = match self.digests.programs.get("gcode") {
            Some(program) => match crate::toolpath_image(None, program, 0) {
                Some(img) => Some(self.picture(
                    "robot_toolpath.png",
                    &img,
                    "The robot's tool tip path seen from above",
                    "The tool tip's path in the part frame seen from above (X right, Y up): feed moves in colour, rapids grey.",
                )?),
                None => None,
            },
            None => None,
        };
        match picture {
            Some(fig) => body.push_str(&fig),
            None => body.push_str(&missing(&self.why_missing("gcode"))),
        }
        body.push_str("<h3>Simulated run against the part's mesh</h3>");
        match self.machine_report.clone() {
            None => body.push_str(&missing(&self.why_missing("machine_report"))),
            Some(r) => body.push_str(&run_html(&r)),
        }
        Ok(section("robot", "Robot milling", &body))
    }
}

fn plan_html(p: &Value) -> String {
    let c = &p["clearance"];
    let r = &p["robot"];
    let mesh = &p["mesh"];
    let closed = match mesh["closed_manifold"].as_bool() {
        Some(true) => "closed and manifold".to_string(),
        Some(false) => format!(
            "not closed: {} open, {} non-manifold, {} misoriented edges",
            count(&mesh["boundary_edges"]),
            count(&mesh["non_manifold_edges"]),
            count(&mesh["misoriented_edges"])
        ),
        None => "—".into(),
    };
    let rows = vec![
        ("Mesh".to_string(), closed),
        ("Tool".into(), p["tool"].as_str().unwrap_or("—").to_string()),
        ("Layers".into(), count(&p["layers"])),
        ("Rings".into(), count(&p["rings"])),
        (
            "Links in cleared material / retracts".into(),
            format!("{} / {}", count(&p["feed_links"]), count(&p["retracts"])),
        ),
        ("Positions checked".into(), count(&c["positions"])),
        ("Upright tool body collides at".into(), count(&c["colliding_upright"])),
        ("Cleared by tilting".into(), count(&c["tilted"])),
        ("Largest tilt".into(), format!("{}°", num(&c["max_tilt_deg"]))),
        ("Fastest axis turn".into(), format!("{}°/mm", num(&c["max_axis_rate_deg_mm"]))),
        ("Blocked (no tilt clears; lifted over)".into(), count(&c["blocked"])),
        (
            "Arm".into(),
            format!(
                "{} ({}, spin {}°)",
                r["arm"].as_str().unwrap_or("—"),
                r["configuration"].as_str().unwrap_or("—"),
                num(&r["spin_deg"])
            ),
        ),
        (
            "Arm time (feed / rapid)".into(),
            format!("{} ({} / {})", secs(&r["duration_s"]), secs(&r["feed_s"]), secs(&r["rapid_s"])),
        ),
        ("Steps slowed by joint speeds".into(), count(&r["joint_limited_steps"])),
        (
            "Smallest dexterity √det(JJᵀ)".into(),
            r["min_dexterity"].as_f64().map_or("—".into(), |d| format!("{d:.3e}")),
        ),
        ("Unreachable stretches".into(), count(&r["unreachable_stretches"])),
        ("Planning time".into(), secs(&p["planning_s"])),
    ];
    let rows: Vec<(String, String)> = rows.into_iter().map(|(k, v)| (k, esc(&v))).collect();
    let mut s = kv_table(&rows);
    if let Some(w) = p["warnings"].as_array().filter(|w| !w.is_empty()) {
        s.push_str("<ul class=\"warnings\">");
        for x in w {
            let _ = write!(
                s,
                "<li><code>{}</code> {}</li>",
                esc(x["code"].as_str().unwrap_or("")),
                esc(x["message"].as_str().unwrap_or(""))
            );
        }
        s.push_str("</ul>");
    }
    let blocked: Vec<Vec<String>> = c["blocked_positions"]
        .as_array()
        .into_iter()
        .flatten()
        .take(LISTED)
        .map(|b| {
            vec![esc(&point(&b["at_mm"])), esc(b["part"].as_str().unwrap_or("—")), esc(&mm(&b["depth_mm"]))]
        })
        .collect();
    if !blocked.is_empty() {
        s.push_str("<p>Positions no tilt clears (the first listed; lifted over, left uncut):</p>");
        s.push_str(&table(&["at (mm)", "what hits the part", "how deep"], &blocked));
    }
    let unreachable: Vec<Vec<String>> = r["unreachable"]
        .as_array()
        .into_iter()
        .flatten()
        .take(LISTED)
        .map(|u| {
            vec![
                esc(&format!("{}–{}", count(&u["from_point"]), count(&u["to_point"]))),
                esc(&point(&u["at_mm"])),
                esc(u["reason"].as_str().unwrap_or("—")),
            ]
        })
        .collect();
    if !unreachable.is_empty() {
        s.push_str("<p>Stretches the arm cannot follow:</p>");
        s.push_str(&table(&["points", "from (mm)", "why"], &unreachable));
    }
    s
}

fn run_html(r: &Value) -> String {
    let d = &r["deviation"];
    let pct = |v: &Value| v.as_f64().map_or("—".into(), |x| format!("{:.1} %", 100.0 * x));
    let mut rows = vec![
        (
            "Trajectory points / steps cut".to_string(),
            format!("{} / {}", count(&r["points"]), count(&r["steps_cut"])),
        ),
        ("Dexel cell".into(), mm(&r["options"]["cell_mm"])),
        ("Cycle time".into(), secs(&r["cycle_time_s"])),
        (
            "Stock / removed / left".into(),
            format!(
                "{} / {} / {} mm³",
                num(&r["stock_volume_mm3"]),
                num(&r["removed_mm3"]),
                num(&r["final_volume_mm3"])
            ),
        ),
        ("Removed by rapids".into(), format!("{} mm³", num(&r["rapid_removed_mm3"]))),
    ];
    if d.is_object() {
        rows.extend([
            ("Points of the part measured".to_string(), count(&d["points"])),
            (
                "Max gouge, and where".into(),
                format!("{} at {}", mm(&d["max_gouge_mm"]), point(&d["max_gouge_at_mm"])),
            ),
            ("Max leftover".into(), mm(&d["max_leftover_mm"])),
            (
                "Mean (signed) / mean left / RMS".into(),
                format!("{} / {} / {}", mm(&d["mean_mm"]), mm(&d["mean_leftover_mm"]), mm(&d["rms_mm"])),
            ),
            (
                "Within ±0.1 mm / ±1 mm".into(),
                format!("{} / {}", pct(&d["within_0_1_mm"]), pct(&d["within_1_mm"])),
            ),
        ]);
    } else {
        rows.push(("Against the part".into(), "not measured (no mesh given)".into()));
    }
    let rows: Vec<(String, String)> = rows.into_iter().map(|(k, v)| (k, esc(&v))).collect();
    let mut s = kv_table(&rows);
    let cuts: Vec<Vec<String>> = r["rapid_cuts"]
        .as_array()
        .into_iter()
        .flatten()
        .take(LISTED)
        .map(|c| vec![esc(&count(&c["point"])), esc(&point(&c["at_mm"])), esc(&num(&c["removed_mm3"]))])
        .collect();
    if !cuts.is_empty() {
        s.push_str("<p>Rapid moves that removed material:</p>");
        s.push_str(&table(&["to point", "at (mm)", "removed (mm³)"], &cuts));
    }
    s
}
