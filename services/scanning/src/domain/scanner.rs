//! Simulated laser line scanner (SLP-400 class) casting its rays at a part's triangle mesh.
//!
//! # Sensor frame
//! Millimetres. Origin at the emitter window, +Z along the optical axis, the laser plane is the
//! XZ plane and the line spreads along X; +Y is the line normal. A pose is given per frame as
//! `world_from_sensor: Isometry3<f64>`. Points in a [`Profile`] are reported in the sensor frame,
//! as a real scanner does; [`Profile::to_world`] maps them with the frame's pose.
//!
//! # Sensor model (defaults of [`ScannerSpec::slp400`])
//! - Standoff (measuring) window: depth `z` of the point in the sensor frame in 65..245 mm. A
//!   surface closer than 65 mm or farther than 245 mm gives no point (`out_of_window`).
//! - Line length grows linearly with depth, 30 mm at 65 mm and 85 mm at 245 mm. The laser is a fan
//!   of rays from one apex, so `L(z) = 2 (z - z0) tan(α/2)`: the two figures fix the half angle
//!   `tan(α/2) = (85 - 30) / 2 / (245 - 65) = 0.15278`, i.e. a fan angle α = 17.37°, and put the
//!   (virtual) apex at `z0 = 65 - 15 / 0.15278 = -33.18 mm`, behind the window.
//! - 450 rays per line (configurable, at least 450), equally spaced in angle across the fan.
//! - Incidence limit 25°: the angle between the ray and the surface normal (either side of the
//!   triangle) beyond which the surface returns nothing (`incidence`).
//! - Gaussian noise along the ray, σ = 0.035 mm (the class's accuracy), Box–Muller from a seeded
//!   `StdRng`, so a scanner with the same seed replays the same noise.
//! - Intensity `I = I0 cos(incidence) / (z / z_ref)²` with `I0 = 1`, `z_ref = 65 mm`, plus
//!   Gaussian noise σ = 0.01, clamped to [0, 1]: it falls with incidence and with distance.
//! - Triangulation occlusion: the camera sits at a baseline of 60 mm along +Y from the emitter
//!   (`(0, 60, 0)` in the sensor frame) and looks back at the laser line. For each laser hit a
//!   second ray is cast from the hit to the camera; if the mesh blocks that line of sight the point
//!   is dropped (`occluded`); so is a spot whose surface faces away from the camera (the camera on
//!   the other side of the triangle's plane than the emitter). A step whose top is on the camera's
//!   side hides the floor next to it.
//! - Line rate 50..150 Hz (default 100 Hz); each frame carries a sync pulse time
//!   `start + frame / rate` ([`frame_times`], [`Profile::time_s`]).
//!
//! # Ray casting
//! [`Bvh`]: a bounding volume hierarchy of the mesh triangles, built by median split of the
//! triangle centroids along the longest axis of their bounds down to leaves of at most
//! [`BVH_LEAF_SIZE`] triangles, stored as a flattened node array (the left child follows its
//! parent, the right child's index is stored). Traversal keeps an explicit stack, visits the nearer
//! child first and prunes boxes beyond the current nearest hit. Ray/triangle tests are
//! Möller–Trumbore, two-sided.

use depthmill_geometry::Mesh;
use nalgebra::{Isometry3, Point3, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Lowest line rate of the class, Hz.
pub const MIN_LINE_RATE_HZ: f64 = 50.0;
/// Highest line rate of the class, Hz.
pub const MAX_LINE_RATE_HZ: f64 = 150.0;
/// Fewest points per line the class delivers.
pub const MIN_POINTS_PER_LINE: usize = 450;
/// Most triangles in a BVH leaf.
pub const BVH_LEAF_SIZE: usize = 4;

/// Errors of the scanner model, naming the parameter, its value and the limit.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScannerError {
    /// A spec parameter outside its allowed range.
    #[error("scanner parameter `{name}` = {value} is invalid: must be {limit}")]
    Parameter {
        /// Field name.
        name: &'static str,
        /// Offending value.
        value: f64,
        /// The rule it breaks.
        limit: String,
    },
    /// A line rate outside the class's 50..150 Hz.
    #[error("line rate {value} Hz is outside the allowed range {min}..={max} Hz")]
    LineRate {
        /// Offending rate, Hz.
        value: f64,
        /// Lowest rate, Hz.
        min: f64,
        /// Highest rate, Hz.
        max: f64,
    },
    /// A mesh triangle refers to a vertex that does not exist.
    #[error("mesh triangle {triangle} refers to vertex {index}, but the mesh has {vertices} vertices")]
    MeshIndex {
        /// Triangle index.
        triangle: usize,
        /// Bad vertex index.
        index: u32,
        /// Number of vertices.
        vertices: usize,
    },
    /// A mesh vertex with a NaN or infinite coordinate.
    #[error("mesh vertex {vertex} has a non-finite coordinate")]
    NonFiniteVertex {
        /// Vertex index.
        vertex: usize,
    },
}

/// Check a line rate against the class's 50..150 Hz and return the frame period in seconds.
pub fn check_line_rate(rate_hz: f64) -> Result<f64, ScannerError> {
    if rate_hz.is_finite() && (MIN_LINE_RATE_HZ..=MAX_LINE_RATE_HZ).contains(&rate_hz) {
        Ok(1.0 / rate_hz)
    } else {
        Err(ScannerError::LineRate { value: rate_hz, min: MIN_LINE_RATE_HZ, max: MAX_LINE_RATE_HZ })
    }
}

/// Sync pulse times (seconds) of `n` frames starting at `start_s` at `rate_hz`:
/// `start_s + k / rate_hz`. The rate must be within 50..150 Hz.
pub fn frame_times(start_s: f64, rate_hz: f64, n: usize) -> Result<Vec<f64>, ScannerError> {
    check_line_rate(rate_hz)?;
    if !start_s.is_finite() {
        return Err(ScannerError::Parameter { name: "start_s", value: start_s, limit: "finite".to_string() });
    }
    Ok((0..n).map(|k| start_s + k as f64 / rate_hz).collect())
}

/// Parameters of a laser line scanner; see the module doc for the model.
#[derive(Debug, Clone, PartialEq)]
pub struct ScannerSpec {
    /// Nearest depth of the measuring window, mm.
    pub standoff_min_mm: f64,
    /// Farthest depth of the measuring window, mm.
    pub standoff_max_mm: f64,
    /// Line length at `standoff_min_mm`, mm.
    pub line_length_near_mm: f64,
    /// Line length at `standoff_max_mm`, mm (greater than the near length: a diverging fan).
    pub line_length_far_mm: f64,
    /// Rays (points) per line, at least [`MIN_POINTS_PER_LINE`].
    pub points_per_line: usize,
    /// Largest angle between ray and surface normal that still returns, degrees.
    pub incidence_limit_deg: f64,
    /// Gaussian noise along the ray, σ in mm.
    pub noise_sigma_mm: f64,
    /// Line rate, Hz, within 50..150.
    pub line_rate_hz: f64,
    /// Camera offset from the emitter along +Y of the sensor frame, mm.
    pub camera_baseline_mm: f64,
    /// Intensity at normal incidence and depth `intensity_ref_mm`.
    pub intensity_gain: f64,
    /// Reference depth of the intensity model, mm.
    pub intensity_ref_mm: f64,
    /// Gaussian noise added to the intensity (σ, in intensity units).
    pub intensity_noise: f64,
}

impl Default for ScannerSpec {
    fn default() -> Self {
        Self::slp400()
    }
}

impl ScannerSpec {
    /// The SLP-400 class defaults (module doc).
    pub fn slp400() -> Self {
        Self {
            standoff_min_mm: 65.0,
            standoff_max_mm: 245.0,
            line_length_near_mm: 30.0,
            line_length_far_mm: 85.0,
            points_per_line: 450,
            incidence_limit_deg: 25.0,
            noise_sigma_mm: 0.035,
            line_rate_hz: 100.0,
            camera_baseline_mm: 60.0,
            intensity_gain: 1.0,
            intensity_ref_mm: 65.0,
            intensity_noise: 0.01,
        }
    }

    /// Check every parameter; the error names the first bad one.
    pub fn validate(&self) -> Result<(), ScannerError> {
        let p = |name: &'static str, value: f64, limit: &str| ScannerError::Parameter {
            name,
            value,
            limit: limit.to_string(),
        };
        if !(self.standoff_min_mm.is_finite() && self.standoff_min_mm > 0.0) {
            return Err(p("standoff_min_mm", self.standoff_min_mm, "finite and > 0"));
        }
        if !(self.standoff_max_mm.is_finite() && self.standoff_max_mm > self.standoff_min_mm) {
            return Err(p("standoff_max_mm", self.standoff_max_mm, "finite and > standoff_min_mm"));
        }
        if !(self.line_length_near_mm.is_finite() && self.line_length_near_mm > 0.0) {
            return Err(p("line_length_near_mm", self.line_length_near_mm, "finite and > 0"));
        }
        if !(self.line_length_far_mm.is_finite() && self.line_length_far_mm > self.line_length_near_mm) {
            return Err(p(
                "line_length_far_mm",
                self.line_length_far_mm,
                "finite and > line_length_near_mm (a diverging fan)",
            ));
        }
        if self.points_per_line < MIN_POINTS_PER_LINE || self.points_per_line > 1 << 20 {
            return Err(p("points_per_line", self.points_per_line as f64, "within 450..=1048576"));
        }
        if !(self.incidence_limit_deg > 0.0 && self.incidence_limit_deg < 90.0) {
            return Err(p("incidence_limit_deg", self.incidence_limit_deg, "within (0, 90)"));
        }
        if !(self.noise_sigma_mm.is_finite() && self.noise_sigma_mm >= 0.0) {
            return Err(p("noise_sigma_mm", self.noise_sigma_mm, "finite and >= 0"));
        }
        check_line_rate(self.line_rate_hz)?;
        if !(self.camera_baseline_mm.is_finite() && self.camera_baseline_mm > 0.0) {
            return Err(p("camera_baseline_mm", self.camera_baseline_mm, "finite and > 0"));
        }
        if !(self.intensity_gain.is_finite() && self.intensity_gain >= 0.0) {
            return Err(p("intensity_gain", self.intensity_gain, "finite and >= 0"));
        }
        if !(self.intensity_ref_mm.is_finite() && self.intensity_ref_mm > 0.0) {
            return Err(p("intensity_ref_mm", self.intensity_ref_mm, "finite and > 0"));
        }
        if !(self.intensity_noise.is_finite() && self.intensity_noise >= 0.0) {
            return Err(p("intensity_noise", self.intensity_noise, "finite and >= 0"));
        }
        Ok(())
    }

    /// Tangent of the fan's half angle, fixed by the near and far line lengths.
    pub fn fan_half_tan(&self) -> f64 {
        (self.line_length_far_mm - self.line_length_near_mm)
            / 2.0
            / (self.standoff_max_mm - self.standoff_min_mm)
    }

    /// Full fan angle, degrees (17.37° for the SLP-400 class).
    pub fn fan_angle_deg(&self) -> f64 {
        2.0 * self.fan_half_tan().atan().to_degrees()
    }

    /// Depth `z0` of the fan's virtual apex in the sensor frame, mm (−33.18 mm for the class).
    pub fn apex_z_mm(&self) -> f64 {
        self.standoff_min_mm - self.line_length_near_mm / 2.0 / self.fan_half_tan()
    }

    /// Line length at depth `z_mm`, mm: linear from the near to the far figure.
    pub fn line_length_at(&self, z_mm: f64) -> f64 {
        2.0 * (z_mm - self.apex_z_mm()) * self.fan_half_tan()
    }

    /// Frame period, seconds.
    pub fn frame_period_s(&self) -> f64 {
        1.0 / self.line_rate_hz
    }
}

/// A ray's nearest hit on the mesh.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray direction, mm.
    pub t: f64,
    /// Index of the triangle in the mesh.
    pub triangle: u32,
    /// Unit geometric normal of the triangle (right-hand rule on its winding).
    pub normal: Vector3<f64>,
}

#[derive(Debug, Clone, Copy)]
struct Node {
    lo: [f64; 3],
    hi: [f64; 3],
    /// Leaf: first triangle in `tris`; interior: index of the right child.
    index: u32,
    /// Leaf: number of triangles (> 0); interior: 0.
    count: u32,
}

/// Bounding volume hierarchy over a mesh's triangles (module doc).
#[derive(Debug, Clone, Default)]
pub struct Bvh {
    nodes: Vec<Node>,
    tris: Vec<[Point3<f64>; 3]>,
    ids: Vec<u32>,
}

const STACK: usize = 96;

impl Bvh {
    /// Build the hierarchy. Fails on a triangle index out of range or a non-finite vertex.
    pub fn build(mesh: &Mesh) -> Result<Bvh, ScannerError> {
        let nv = mesh.vertices.len();
        if let Some(vertex) = mesh.vertices.iter().position(|v| !v.coords.iter().all(|c| c.is_finite())) {
            return Err(ScannerError::NonFiniteVertex { vertex });
        }
        let mut tris = Vec::with_capacity(mesh.triangles.len());
        for (t, tri) in mesh.triangles.iter().enumerate() {
            if let Some(&index) = tri.iter().find(|&&i| i as usize >= nv) {
                return Err(ScannerError::MeshIndex { triangle: t, index, vertices: nv });
            }
            tris.push(tri.map(|i| mesh.vertices[i as usize]));
        }
        let cents: Vec<[f64; 3]> = tris
            .iter()
            .map(|[a, b, c]| {
                let m = (a.coords + b.coords + c.coords) / 3.0;
                [m.x, m.y, m.z]
            })
            .collect();
        let mut order: Vec<u32> = (0..tris.len() as u32).collect();
        let mut nodes = Vec::with_capacity(2 * tris.len() / BVH_LEAF_SIZE + 1);
        if !tris.is_empty() {
            build_node(&mut nodes, &tris, &cents, &mut order, 0);
        }
        let sorted = order.iter().map(|&i| tris[i as usize]).collect();
        Ok(Bvh { nodes, tris: sorted, ids: order })
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.tris.len()
    }

    /// Number of nodes in the flattened tree.
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Nearest hit of the ray `origin + t·dir`, `1e-9 < t < max_t` (`dir` is normalised here,
    /// `t` is in mm). `None` for a miss or a zero or non-finite direction.
    pub fn cast(&self, origin: &Point3<f64>, dir: &Vector3<f64>, max_t: f64) -> Option<Hit> {
        let d = dir.try_normalize(0.0)?;
        if !d.iter().all(|c| c.is_finite()) {
            return None;
        }
        let (t, k) = self.traverse(origin, &d, 1e-9, max_t, false)?;
        let [a, b, c] = self.tris[k];
        let normal = (b - a).cross(&(c - a)).try_normalize(0.0).unwrap_or_else(Vector3::z);
        Some(Hit { t, triangle: self.ids[k], normal })
    }

    /// Whether the mesh blocks the open segment between `from` and `to` (its ends excluded by a
    /// small tolerance, 1e-6 of its length plus 1e-7 mm, so a surface point is not its own occluder).
    pub fn occluded(&self, from: &Point3<f64>, to: &Point3<f64>) -> bool {
        let v = to - from;
        let len = v.norm();
        if !(len.is_finite() && len > 0.0) {
            return false;
        }
        let d = v / len;
        let eps = 1e-6 * len + 1e-7;
        if len <= 2.0 * eps {
            return false;
        }
        self.traverse(from, &d, eps, len - eps, true).is_some()
    }

    /// Nearest (or, with `any`, the first found) hit in `(t_min, t_max)`: `(t, index in tris)`.
    fn traverse(
        &self,
        o: &Point3<f64>,
        d: &Vector3<f64>,
        t_min: f64,
        t_max: f64,
        any: bool,
    ) -> Option<(f64, usize)> {
        if self.nodes.is_empty() {
            return None;
        }
        let inv = [1.0 / d.x, 1.0 / d.y, 1.0 / d.z];
        let oa = [o.x, o.y, o.z];
        let mut best: Option<(f64, usize)> = None;
        let mut far = t_max;
        let mut stack = [0u32; STACK];
        let mut sp = 0usize;
        let mut node = 0usize;
        loop {
            let n = &self.nodes[node];
            if n.count > 0 {
                let start = n.index as usize;
                for k in start..start + n.count as usize {
                    if let Some(t) = intersect(o, d, &self.tris[k], t_min, far) {
                        far = t;
                        best = Some((t, k));
                        if any {
                            return best;
                        }
                    }
                }
            } else {
                let (l, r) = (node + 1, n.index as usize);
                let tl = slab(&self.nodes[l], &oa, &inv, t_min, far);
                let tr = slab(&self.nodes[r], &oa, &inv, t_min, far);
                match (tl, tr) {
                    (Some(a), Some(b)) => {
                        let (near, other) = if a <= b { (l, r) } else { (r, l) };
                        // The median split halves the triangles at each level, so the depth (and
                        // the stack) stays below 33 for any u32 triangle count.
                        if sp < STACK {
                            stack[sp] = other as u32;
                            sp += 1;
                        }
                        node = near;
                        continue;
                    }
                    (Some(_), None) => {
                        node = l;
                        continue;
                    }
                    (None, Some(_)) => {
                        node = r;
                        continue;
                    }
                    (None, None) => {}
                }
            }
            // Pop the next node still nearer than the nearest hit found so far.
            loop {
                if sp == 0 {
                    return best;
                }
                sp -= 1;
                node = stack[sp] as usize;
                if slab(&self.nodes[node], &oa, &inv, t_min, far).is_some() {
                    break;
                }
            }
        }
    }
}

/// Recursively build the node for `order[..]` (triangle ids, whose first item sits at `offset`
/// in the final order); returns the node index.
fn build_node(
    nodes: &mut Vec<Node>,
    tris: &[[Point3<f64>; 3]],
    cents: &[[f64; 3]],
    order: &mut [u32],
    offset: usize,
) -> usize {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    let mut clo = [f64::INFINITY; 3];
    let mut chi = [f64::NEG_INFINITY; 3];
    for &i in order.iter() {
        for p in &tris[i as usize] {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let c = cents[i as usize];
        for a in 0..3 {
            clo[a] = clo[a].min(c[a]);
            chi[a] = chi[a].max(c[a]);
        }
    }
    let me = nodes.len();
    nodes.push(Node { lo, hi, index: offset as u32, count: order.len() as u32 });
    let ext = [chi[0] - clo[0], chi[1] - clo[1], chi[2] - clo[2]];
    let axis = if ext[0] >= ext[1] && ext[0] >= ext[2] {
        0
    } else if ext[1] >= ext[2] {
        1
    } else {
        2
    };
    if order.len() <= BVH_LEAF_SIZE || ext[axis] <= 0.0 {
        return me;
    }
    let mid = order.len() / 2;
    order.select_nth_unstable_by(mid, |&a, &b| cents[a as usize][axis].total_cmp(&cents[b as usize][axis]));
    let (left, right) = order.split_at_mut(mid);
    build_node(nodes, tris, cents, left, offset);
    let r = build_node(nodes, tris, cents, right, offset + mid);
    nodes[me].count = 0;
    nodes[me].index = r as u32;
    me
}

/// Entry distance of the ray into the node's box if it overlaps `(t_min, t_max)`.
#[inline]
fn slab(n: &Node, o: &[f64; 3], inv: &[f64; 3], t_min: f64, t_max: f64) -> Option<f64> {
    let mut t0 = t_min;
    let mut t1 = t_max;
    for a in 0..3 {
        let mut ta = (n.lo[a] - o[a]) * inv[a];
        let mut tb = (n.hi[a] - o[a]) * inv[a];
        if ta > tb {
            std::mem::swap(&mut ta, &mut tb);
        }
        // NaN (0 · ∞, origin on a slab plane of a parallel ray) leaves the bound unchanged.
        t0 = if ta > t0 { ta } else { t0 };
        t1 = if tb < t1 { tb } else { t1 };
        if t0 > t1 {
            return None;
        }
    }
    Some(t0)
}

/// Möller–Trumbore, two-sided: `t` of the hit in `(t_min, t_max)`.
#[inline]
fn intersect(
    o: &Point3<f64>,
    d: &Vector3<f64>,
    tri: &[Point3<f64>; 3],
    t_min: f64,
    t_max: f64,
) -> Option<f64> {
    let e1 = tri[1] - tri[0];
    let e2 = tri[2] - tri[0];
    let p = d.cross(&e2);
    let det = e1.dot(&p);
    if det.abs() <= 1e-14 * e1.norm() * e2.norm() {
        return None;
    }
    let inv = 1.0 / det;
    let s = o - tri[0];
    let u = s.dot(&p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(&e1);
    let v = d.dot(&q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = e2.dot(&q) * inv;
    (t > t_min && t < t_max).then_some(t)
}

/// Rays dropped from a profile, by reason.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DropCounts {
    /// The nearest surface is closer than the window's near end or beyond its far end.
    pub out_of_window: u32,
    /// The angle between ray and surface normal exceeds the incidence limit.
    pub incidence: u32,
    /// The camera's line of sight to the laser spot is blocked by the mesh.
    pub occluded: u32,
    /// The ray hits nothing.
    pub miss: u32,
}

impl DropCounts {
    /// Total dropped rays.
    pub fn total(&self) -> u32 {
        self.out_of_window + self.incidence + self.occluded + self.miss
    }
}

/// One laser line.
#[derive(Debug, Clone, PartialEq)]
pub struct Profile {
    /// Frame number.
    pub frame: u64,
    /// Sync pulse time of the frame, seconds: `frame / line_rate_hz`.
    pub time_s: f64,
    /// Measured points in the SENSOR frame, mm, in ray order (−X to +X).
    pub points: Vec<Point3<f64>>,
    /// Intensity of each point, [0, 1].
    pub intensity: Vec<f32>,
    /// Ray (column) index of each point, `0..points_per_line`.
    pub column: Vec<u32>,
    /// Rays that gave no point, by reason.
    pub dropped: DropCounts,
    /// Points on the floor (the table top under the part; [`Scanner::with_floor`]) where a ray
    /// missed the part, SENSOR frame, mm: where the scanner saw that there is no part.
    pub floor: Vec<Point3<f64>>,
    /// Ray (column) index of each floor point.
    pub floor_column: Vec<u32>,
}

/// The plane the part stands on, in the frame the scanner casts in (the part frame): the table
/// top, `z = z_mm` within `radius_mm` of `center_xy_mm`. A ray that misses the part returns a
/// point there, as a real scanner sees the table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Floor {
    pub z_mm: f64,
    pub center_xy_mm: [f64; 2],
    pub radius_mm: f64,
}

impl Profile {
    /// The points in the world frame, given the frame's `world_from_sensor` pose.
    pub fn to_world(&self, world_from_sensor: &Isometry3<f64>) -> Vec<Point3<f64>> {
        self.points.iter().map(|p| world_from_sensor * p).collect()
    }
}

/// A ray's return must lie this far past a vertical for the ray to show the vertical clear, mm
/// (three times the SLP-400 class's range noise).
pub const CLEAR_PAST_MM: f64 = 0.1;

/// A simulated laser line scanner looking at one mesh.
#[derive(Debug, Clone)]
pub struct Scanner {
    spec: ScannerSpec,
    floor: Option<Floor>,
    bvh: Bvh,
    apex: Point3<f64>,
    dirs: Vec<Vector3<f64>>,
    cos_limit: f64,
    rng: StdRng,
}

impl Scanner {
    /// A scanner with a validated spec, a BVH over `mesh` and a noise generator seeded by `seed`.
    pub fn new(spec: ScannerSpec, mesh: &Mesh, seed: u64) -> Result<Self, ScannerError> {
        spec.validate()?;
        let bvh = Bvh::build(mesh)?;
        let half = spec.fan_half_tan().atan();
        let n = spec.points_per_line;
        let dirs = (0..n)
            .map(|i| {
                let a = -half + 2.0 * half * i as f64 / (n - 1) as f64;
                Vector3::new(a.sin(), 0.0, a.cos())
            })
            .collect();
        let apex = Point3::new(0.0, 0.0, spec.apex_z_mm());
        let cos_limit = spec.incidence_limit_deg.to_radians().cos();
        Ok(Self { spec, floor: None, bvh, apex, dirs, cos_limit, rng: StdRng::seed_from_u64(seed) })
    }

    /// The same scanner seeing `floor` wherever a ray misses the part (the table top).
    pub fn with_floor(mut self, floor: Floor) -> Self {
        self.floor = Some(floor);
        self
    }

    /// Where the ray from `origin` along `dir` meets the floor, when it does within the disc:
    /// its parameter `t` (mm).
    fn floor_hit(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<f64> {
        let f = self.floor?;
        if dir.z >= -1e-12 {
            return None;
        }
        let t = (f.z_mm - origin.z) / dir.z;
        let p = origin + dir * t;
        let inside = (p.x - f.center_xy_mm[0]).hypot(p.y - f.center_xy_mm[1]) <= f.radius_mm;
        (t > 0.0 && inside).then_some(t)
    }

    /// The spec.
    pub fn spec(&self) -> &ScannerSpec {
        &self.spec
    }

    /// The ray-casting structure over the mesh.
    pub fn bvh(&self) -> &Bvh {
        &self.bvh
    }

    /// Camera position in the sensor frame.
    pub fn camera_in_sensor(&self) -> Point3<f64> {
        Point3::new(0.0, self.spec.camera_baseline_mm, 0.0)
    }

    /// Fan apex (ray origin) in the sensor frame.
    pub fn apex_in_sensor(&self) -> Point3<f64> {
        self.apex
    }

    /// How high over each of `profile`'s floor points the vertical is shown clear: every ray of
    /// the fan that crosses it below that height returned from beyond the crossing (the floor,
    /// or the part past the vertical, by more than [`CLEAR_PAST_MM`]; the vertical starts three
    /// times that over the point). `up` is the vertical in the SENSOR frame; heights are checked
    /// up to the plane `up · x = top` (a height at or over it: clear all the way). A floor point
    /// alone says only that its own ray is clear: a ray slanted past an overhang reaches the
    /// table under it, and the vertical over that spot crosses the rays the overhang stopped. A
    /// ray that gave no point (missed, too steep, hidden from the camera) shows nothing, and the
    /// vertical is shown clear no higher than where it leaves the fan. The vertical is taken in
    /// the laser plane: the caller keeps only lines from a sensor looking straight down.
    pub fn floor_clear_height(&self, profile: &Profile, up: &Vector3<f64>, top: f64) -> Vec<f64> {
        self.clear_height(profile, &profile.floor, &profile.floor_column, up, top)
    }

    /// [`Scanner::floor_clear_height`] for the profile's part points: how high over each the
    /// vertical is shown clear by the other rays of its line. A point under an overhang (seen at
    /// the fan's slant past the overhang's edge) is shown clear no higher than the overhang.
    pub fn point_clear_height(&self, profile: &Profile, up: &Vector3<f64>, top: f64) -> Vec<f64> {
        self.clear_height(profile, &profile.points, &profile.column, up, top)
    }

    fn clear_height(
        &self,
        profile: &Profile,
        points: &[Point3<f64>],
        columns: &[u32],
        up: &Vector3<f64>,
        top: f64,
    ) -> Vec<f64> {
        let n = self.dirs.len();
        // How far along each ray its return lies (NaN: no return).
        let mut ret = vec![f64::NAN; n];
        let returns =
            profile.points.iter().zip(&profile.column).chain(profile.floor.iter().zip(&profile.floor_column));
        for (p, &c) in returns {
            if let Some(slot) = ret.get_mut(c as usize) {
                *slot = (p - self.apex).norm();
            }
        }
        let half = self.spec.fan_half_tan().atan();
        let step = 2.0 * half / (n.max(2) - 1) as f64;
        let cross = |a: (f64, f64), b: (f64, f64)| a.0 * b.1 - a.1 * b.0;
        let (ax, az) = (self.apex.x, self.apex.z);
        let u = (up.x, up.z);
        let start = 3.0 * CLEAR_PAST_MM;
        points
            .iter()
            .zip(columns)
            .map(|(p, &col)| {
                let height = top - up.dot(&p.coords);
                if !height.is_finite() || height <= start {
                    return height.max(start);
                }
                // The rays crossing the vertical higher up lie to this side of the point's own.
                let q = p + up * height;
                let outward = (q.x - ax).atan2(q.z - az) >= -half + step * f64::from(col);
                let rel = (p.x - ax, p.z - az);
                let mut clear = start;
                let mut j = col as i64;
                while (0..n as i64).contains(&j) {
                    let d = (self.dirs[j as usize].x, self.dirs[j as usize].z);
                    let den = cross(d, u);
                    if den.abs() > 1e-12 {
                        // Where ray j crosses the vertical, and how high over the point.
                        let t = cross(rel, u) / den;
                        let above = (d.0 * t - rel.0) * u.0 + (d.1 * t - rel.1) * u.1;
                        if above >= start {
                            let returned_past = ret[j as usize] >= t + CLEAR_PAST_MM; // NaN: no return
                            if !returned_past {
                                return clear;
                            }
                            clear = above;
                            if above >= height {
                                return above;
                            }
                        }
                    }
                    j += if outward { 1 } else { -1 };
                }
                clear
            })
            .collect()
    }

    /// Acquire one line with the sensor at `world_from_sensor`; frame number `frame`. The noise
    /// comes from the scanner's own generator (seeded at construction), so successive calls draw
    /// successive noise.
    pub fn profile(&mut self, world_from_sensor: &Isometry3<f64>, frame: u64) -> Profile {
        let mut rng = std::mem::replace(&mut self.rng, StdRng::seed_from_u64(0));
        let out = self.acquire(world_from_sensor, frame, &mut rng);
        self.rng = rng;
        out
    }

    /// Like [`Scanner::profile`] with the noise drawn from a generator seeded by `(seed, frame)`:
    /// takes `&self`, so frames can be acquired in parallel and in any order, each replaying the
    /// same noise for the same seed and frame.
    pub fn profile_seeded(&self, world_from_sensor: &Isometry3<f64>, frame: u64, seed: u64) -> Profile {
        // SplitMix64-style mixing so neighbouring frames get unrelated streams.
        let mut z = seed ^ frame.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        let mut rng = StdRng::seed_from_u64(z ^ (z >> 31));
        self.acquire(world_from_sensor, frame, &mut rng)
    }

    fn acquire(&self, world_from_sensor: &Isometry3<f64>, frame: u64, rng: &mut StdRng) -> Profile {
        let n = self.dirs.len();
        let mut out = Profile {
            frame,
            time_s: frame as f64 / self.spec.line_rate_hz,
            points: Vec::with_capacity(n),
            intensity: Vec::with_capacity(n),
            column: Vec::with_capacity(n),
            dropped: DropCounts::default(),
            floor: Vec::new(),
            floor_column: Vec::new(),
        };
        let origin_w = world_from_sensor * self.apex;
        let camera_w = world_from_sensor * self.camera_in_sensor();
        for i in 0..n {
            let d = self.dirs[i];
            let dw = world_from_sensor.rotation * d;
            let Some(hit) = self.bvh.cast(&origin_w, &dw, f64::INFINITY) else {
                out.dropped.miss += 1;
                // Past the part, the table: seen like any surface (window, incidence, the
                // camera's line of sight past the part), it says there is no part along the ray.
                if let Some(t) = self.floor_hit(&origin_w, &dw) {
                    let z = self.apex.z + t * d.z;
                    let p_w = origin_w + dw * t;
                    if z >= self.spec.standoff_min_mm
                        && z <= self.spec.standoff_max_mm
                        && dw.z.abs() >= self.cos_limit
                        && !self.bvh.occluded(&p_w, &camera_w)
                    {
                        let t = t + self.spec.noise_sigma_mm * gauss(rng);
                        out.floor.push(self.apex + d * t);
                        out.floor_column.push(i as u32);
                    }
                }
                continue;
            };
            let z = self.apex.z + hit.t * d.z;
            if z < self.spec.standoff_min_mm || z > self.spec.standoff_max_mm {
                out.dropped.out_of_window += 1;
                continue;
            }
            let cos_inc = hit.normal.dot(&dw).abs();
            if cos_inc < self.cos_limit {
                out.dropped.incidence += 1;
                continue;
            }
            let p_w = origin_w + dw * hit.t;
            // The camera must be on the lit side of the surface (an open sheet seen from behind
            // hides the spot too), and nothing may block its line of sight.
            let lit_side = hit.normal.dot(&(origin_w - p_w)) * hit.normal.dot(&(camera_w - p_w)) > 0.0;
            if !lit_side || self.bvh.occluded(&p_w, &camera_w) {
                out.dropped.occluded += 1;
                continue;
            }
            let t = hit.t + self.spec.noise_sigma_mm * gauss(rng);
            let r = z / self.spec.intensity_ref_mm;
            let i0 = self.spec.intensity_gain * cos_inc / (r * r);
            let inten = (i0 + self.spec.intensity_noise * gauss(rng)).clamp(0.0, 1.0);
            out.points.push(self.apex + d * t);
            out.intensity.push(inten as f32);
            out.column.push(i as u32);
        }
        out
    }
}

/// A standard normal deviate (Box–Muller; u1 in (0, 1] keeps the log finite).
fn gauss(rng: &mut StdRng) -> f64 {
    let u1: f64 = 1.0 - rng.random::<f64>();
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use nalgebra::{Rotation3, Translation3, UnitQuaternion};

    /// Square plate of half size `h` centred at (0, 0, z), tilted by `tilt_deg` about +Y.
    fn plate(z: f64, h: f64, tilt_deg: f64) -> Mesh {
        let r = Rotation3::from_axis_angle(&Vector3::y_axis(), tilt_deg.to_radians());
        let c = Vector3::new(0.0, 0.0, z);
        let vertices = [(-h, -h), (h, -h), (h, h), (-h, h)]
            .iter()
            .map(|&(x, y)| Point3::from(r * Vector3::new(x, y, 0.0) + c))
            .collect();
        Mesh { vertices, triangles: vec![[0, 1, 2], [0, 2, 3]] }
    }

    /// Closed axis-aligned box.
    /// Appends the axis-aligned box `lo`..`hi` to `m` (12 triangles, outward faces).
    pub(crate) fn add_box(m: &mut Mesh, lo: [f64; 3], hi: [f64; 3]) {
        let b = m.vertices.len() as u32;
        for k in 0..8 {
            m.vertices.push(Point3::new(
                if k & 1 == 0 { lo[0] } else { hi[0] },
                if k & 2 == 0 { lo[1] } else { hi[1] },
                if k & 4 == 0 { lo[2] } else { hi[2] },
            ));
        }
        let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        for q in quads {
            m.triangles.push([b + q[0], b + q[1], b + q[2]]);
            m.triangles.push([b + q[0], b + q[2], b + q[3]]);
        }
    }

    fn brute_cast(m: &Mesh, o: &Point3<f64>, d: &Vector3<f64>, max_t: f64) -> Option<(f64, usize)> {
        let d = d.normalize();
        let mut best: Option<(f64, usize)> = None;
        for t in 0..m.triangles.len() {
            let lim = best.map_or(max_t, |b| b.0);
            if let Some(x) = intersect(o, &d, &m.triangle(t), 1e-9, lim) {
                best = Some((x, t));
            }
        }
        best
    }

    fn random_soup(rng: &mut StdRng, n: usize, size: f64) -> Mesh {
        let mut m = Mesh::default();
        for _ in 0..n {
            let c = Vector3::new(
                rng.random_range(-50.0..50.0),
                rng.random_range(-50.0..50.0),
                rng.random_range(-50.0..50.0),
            );
            let b = m.vertices.len() as u32;
            for _ in 0..3 {
                let off = Vector3::new(
                    rng.random_range(-size..size),
                    rng.random_range(-size..size),
                    rng.random_range(-size..size),
                );
                m.vertices.push(Point3::from(c + off));
            }
            m.triangles.push([b, b + 1, b + 2]);
        }
        m
    }

    fn random_dir(rng: &mut StdRng) -> Vector3<f64> {
        loop {
            let v = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            );
            if v.norm() > 0.1 && v.norm() < 1.0 {
                return v.normalize();
            }
        }
    }

    #[test]
    fn bvh_matches_brute_force_on_random_rays() {
        let mut rng = StdRng::seed_from_u64(7);
        for (n, size) in [(1, 20.0), (7, 15.0), (300, 12.0), (1000, 5.0)] {
            let m = random_soup(&mut rng, n, size);
            let bvh = Bvh::build(&m).expect("valid mesh");
            assert_eq!(bvh.triangle_count(), n);
            let mut hits = 0;
            for _ in 0..600 {
                let o = Point3::new(
                    rng.random_range(-80.0..80.0),
                    rng.random_range(-80.0..80.0),
                    rng.random_range(-80.0..80.0),
                );
                // Half the rays aim at a random triangle's centroid, so many hit.
                let d = if rng.random::<bool>() {
                    let [a, b, c] = m.triangle(rng.random_range(0..n));
                    let target = Point3::from((a.coords + b.coords + c.coords) / 3.0);
                    (target - o).normalize()
                } else {
                    random_dir(&mut rng)
                };
                let max_t = if rng.random::<bool>() { f64::INFINITY } else { rng.random_range(1.0..150.0) };
                let fast = bvh.cast(&o, &d, max_t);
                let slow = brute_cast(&m, &o, &d, max_t);
                match (fast, slow) {
                    (None, None) => {}
                    (Some(h), Some((t, k))) => {
                        hits += 1;
                        assert!((h.t - t).abs() < 1e-9, "t {} vs {}", h.t, t);
                        if h.triangle as usize != k {
                            // A tie on a shared distance: the BVH's triangle must be hit at t too.
                            let x = intersect(&o, &d, &m.triangle(h.triangle as usize), 1e-9, f64::INFINITY);
                            assert!(x.is_some_and(|x| (x - t).abs() < 1e-9));
                        }
                        let [a, b, c] = m.triangle(h.triangle as usize);
                        assert!(h.normal.dot(&(b - a)).abs() < 1e-9 && h.normal.dot(&(c - a)).abs() < 1e-9);
                        assert!((h.normal.norm() - 1.0).abs() < 1e-12);
                    }
                    (f, s) => panic!("bvh {f:?} vs brute {s:?}"),
                }
                // Segment occlusion against the brute-force any-hit.
                let to = o + d * rng.random_range(1.0..150.0);
                let len = (to - o).norm();
                let eps = 1e-6 * len + 1e-7;
                let slow_occ = (0..n).any(|t| intersect(&o, &d, &m.triangle(t), eps, len - eps).is_some());
                assert_eq!(bvh.occluded(&o, &to), slow_occ);
            }
            assert!(hits > 150, "only {hits} hits for n = {n}");
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]
        /// Random triangle soups and rays: the BVH's nearest `t` equals the brute-force one.
        #[test]
        fn bvh_cast_equals_brute_force(
            coords in proptest::collection::vec(-30.0f64..30.0, 9..360),
            o in proptest::array::uniform3(-60.0f64..60.0),
            d in proptest::array::uniform3(-1.0f64..1.0),
        ) {
            let n = coords.len() / 9;
            let vertices: Vec<Point3<f64>> =
                coords.chunks_exact(3).take(3 * n).map(|c| Point3::new(c[0], c[1], c[2])).collect();
            let triangles = (0..n as u32).map(|t| [3 * t, 3 * t + 1, 3 * t + 2]).collect();
            let m = Mesh { vertices, triangles };
            let bvh = Bvh::build(&m).expect("valid mesh");
            let o = Point3::from(o);
            let d = Vector3::from(d);
            proptest::prop_assume!(d.norm() > 1e-3);
            let fast = bvh.cast(&o, &d, f64::INFINITY).map(|h| h.t);
            let slow = brute_cast(&m, &o, &d, f64::INFINITY).map(|h| h.0);
            match (fast, slow) {
                (Some(a), Some(b)) => proptest::prop_assert!((a - b).abs() < 1e-9, "{a} vs {b}"),
                (a, b) => proptest::prop_assert_eq!(a, b),
            }
        }
    }

    #[test]
    fn bvh_on_empty_and_bad_meshes() {
        let empty = Bvh::build(&Mesh::default()).expect("empty is fine");
        assert!(empty.cast(&Point3::origin(), &Vector3::z(), f64::INFINITY).is_none());
        assert!(!empty.occluded(&Point3::origin(), &Point3::new(0.0, 0.0, 1.0)));
        let bad = Mesh { vertices: vec![Point3::origin(); 3], triangles: vec![[0, 1, 3]] };
        assert_eq!(
            Bvh::build(&bad).err(),
            Some(ScannerError::MeshIndex { triangle: 0, index: 3, vertices: 3 })
        );
        let nan = Mesh { vertices: vec![Point3::new(f64::NAN, 0.0, 0.0)], triangles: vec![] };
        assert_eq!(Bvh::build(&nan).err(), Some(ScannerError::NonFiniteVertex { vertex: 0 }));
        let m = plate(10.0, 5.0, 0.0);
        let bvh = Bvh::build(&m).expect("valid");
        assert!(bvh.cast(&Point3::origin(), &Vector3::zeros(), 100.0).is_none());
        let h = bvh.cast(&Point3::origin(), &Vector3::new(0.0, 0.0, 3.0), 100.0).expect("hit");
        assert!((h.t - 10.0).abs() < 1e-12);
    }

    #[test]
    fn fan_geometry_matches_the_class_figures() {
        let s = ScannerSpec::slp400();
        assert!((s.fan_angle_deg() - 17.37).abs() < 0.01, "{}", s.fan_angle_deg());
        assert!((s.apex_z_mm() + 33.18).abs() < 0.01, "{}", s.apex_z_mm());
        assert!((s.line_length_at(65.0) - 30.0).abs() < 1e-9);
        assert!((s.line_length_at(245.0) - 85.0).abs() < 1e-9);
    }

    #[test]
    fn flat_plate_at_150_gives_a_full_line_of_the_right_length() {
        let spec = ScannerSpec::slp400();
        let mut sc = Scanner::new(spec.clone(), &plate(150.0, 100.0, 0.0), 1).expect("scanner");
        let p = sc.profile(&Isometry3::identity(), 0);
        assert!(p.points.len() >= 450);
        assert_eq!(p.dropped.total(), 0);
        assert_eq!(p.intensity.len(), p.points.len());
        let (lo, hi) =
            p.points.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), q| (l.min(q.x), h.max(q.x)));
        let want = spec.line_length_at(150.0);
        assert!(((hi - lo) - want).abs() < 0.01 * want, "length {} vs {want}", hi - lo);
        assert!(p.points.iter().all(|q| (q.z - 150.0).abs() < 0.25 && q.y.abs() < 1e-9));
    }

    #[test]
    fn noise_is_gaussian_with_the_class_sigma_along_the_ray() {
        let spec = ScannerSpec::slp400();
        let mut sc = Scanner::new(spec, &plate(150.0, 100.0, 0.0), 42).expect("scanner");
        let apex = sc.apex_in_sensor();
        let (mut n, mut s1, mut s2) = (0.0, 0.0, 0.0);
        for f in 0..100 {
            for q in sc.profile(&Isometry3::identity(), f).points {
                let v = q - apex;
                let d = v.normalize();
                let r = v.norm() - (150.0 - apex.z) / d.z;
                n += 1.0;
                s1 += r;
                s2 += r * r;
            }
        }
        let mean = s1 / n;
        let sigma = (s2 / n - mean * mean).sqrt();
        assert!(n >= 45_000.0);
        assert!(mean.abs() < 0.002, "mean {mean}");
        assert!((sigma - 0.035).abs() < 0.035 * 0.03, "sigma {sigma}");
    }

    #[test]
    fn nothing_outside_the_standoff_window() {
        for (z, inside) in [
            (50.0, false),
            (64.0, false),
            (66.0, true),
            (150.0, true),
            (244.0, true),
            (246.0, false),
            (300.0, false),
        ] {
            let mut sc = Scanner::new(ScannerSpec::slp400(), &plate(z, 200.0, 0.0), 3).expect("scanner");
            let p = sc.profile(&Isometry3::identity(), 0);
            if inside {
                assert_eq!(p.points.len(), 450, "z = {z}");
            } else {
                assert!(p.points.is_empty(), "z = {z}");
                assert_eq!(p.dropped.out_of_window, 450);
            }
        }
        // Nothing in front of the scanner at all: every ray misses.
        let mut sc = Scanner::new(ScannerSpec::slp400(), &plate(-100.0, 50.0, 0.0), 3).expect("scanner");
        assert_eq!(sc.profile(&Isometry3::identity(), 0).dropped.miss, 450);
    }

    #[test]
    fn rays_past_the_part_see_the_floor_and_only_there() {
        // A 20 mm plate at z = 0 over a floor at z = -5; the sensor 150 mm above, looking down.
        let floor = Floor { z_mm: -5.0, center_xy_mm: [0.0, 0.0], radius_mm: 200.0 };
        let mut sc = Scanner::new(ScannerSpec::slp400(), &plate(0.0, 10.0, 0.0), 3)
            .expect("scanner")
            .with_floor(floor);
        let down = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 150.0),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        );
        let p = sc.profile(&down, 0);
        assert!(!p.points.is_empty() && !p.floor.is_empty(), "{} / {}", p.points.len(), p.floor.len());
        // Every ray that missed the plate met the floor (nothing hides it here).
        assert_eq!(p.floor.len() as u32, p.dropped.miss);
        for q in p.floor.iter().map(|q| down * q) {
            assert!((q.z + 5.0).abs() < 0.3 && q.x.abs() > 9.9, "{q:?}");
        }
        for q in p.points.iter().map(|q| down * q) {
            assert!(q.z.abs() < 0.3 && q.x.abs() < 10.1, "{q:?}");
        }
        // Outside the table's disc there is nothing to see.
        let small = Floor { radius_mm: 12.0, ..floor };
        let mut sc = Scanner::new(ScannerSpec::slp400(), &plate(0.0, 10.0, 0.0), 3)
            .expect("scanner")
            .with_floor(small);
        let p = sc.profile(&down, 0);
        assert!(p.floor.iter().map(|q| down * q).all(|q| q.x.hypot(q.y) <= 12.5));
        assert!((p.floor.len() as u32) < p.dropped.miss);
    }

    #[test]
    fn a_table_point_is_clear_above_only_when_every_ray_over_it_reached_the_table() {
        // Blocks on the floor and slabs floating over it (an overhang on every side), seen by a
        // sensor looking straight down: the fan's slanted rays reach the floor under a slab's
        // edges, and pass over the floor next to a block's wall. The
        // reference is the vertical itself, cast up from the floor point against the mesh.
        let mut rng = StdRng::seed_from_u64(7);
        let (mut under, mut clear, mut open) = (0usize, 0usize, 0usize);
        for _ in 0..60 {
            let hx = rng.random_range(3.0..15.0);
            let hy = rng.random_range(3.0..15.0);
            // Every other one stands on the floor: walls, no overhang.
            let z0 = if rng.random_bool(0.5) { 0.0 } else { rng.random_range(5.0..25.0) };
            let z1 = z0 + rng.random_range(1.0..8.0);
            let mut m = Mesh { vertices: Vec::new(), triangles: Vec::new() };
            add_box(&mut m, [-hx, -hy, z0], [hx, hy, z1]);
            let floor = Floor { z_mm: 0.0, center_xy_mm: [0.0, 0.0], radius_mm: 500.0 };
            let sc = Scanner::new(ScannerSpec::slp400(), &m, 3).expect("scanner").with_floor(floor);
            let world_from_sensor = Isometry3::from_parts(
                Translation3::new(
                    rng.random_range(-25.0..25.0),
                    rng.random_range(-hy - 3.0..hy + 3.0),
                    z1 + rng.random_range(90.0..200.0),
                ),
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
            );
            let p = sc.profile_seeded(&world_from_sensor, 0, 11);
            let up = world_from_sensor.rotation.inverse() * Vector3::z();
            let top = z1 + 1.0 - world_from_sensor.translation.vector.z;
            let heights = sc.floor_clear_height(&p, &up, top);
            assert_eq!(heights.len(), p.floor.len());
            for (q, h) in p.floor.iter().zip(heights) {
                // The verticals at the point and 0.02 mm around it (the range noise moves a
                // slanted ray's point sideways by a few micrometres): all blocked or all open.
                let w = world_from_sensor * q;
                let first_hits: Vec<Option<f64>> =
                    [(0.0, 0.0), (0.02, 0.0), (-0.02, 0.0), (0.0, 0.02), (0.0, -0.02)]
                        .iter()
                        .map(|(dx, dy)| {
                            let o = Point3::new(w.x + dx, w.y + dy, 0.01);
                            sc.bvh().cast(&o, &Vector3::z(), z1 + 1.0).map(|hit| hit.t + 0.01)
                        })
                        .collect();
                if first_hits.iter().all(Option::is_some) {
                    under += 1;
                    // The reference: what the vertical meets first. Shown clear no higher.
                    let hit = first_hits.iter().flatten().fold(f64::INFINITY, |a, b| a.min(*b));
                    assert!(
                        h <= hit + 0.05,
                        "a table point's vertical shown clear to {h} mm meets the part at {hit} mm: {w:?}"
                    );
                } else if first_hits.iter().all(Option::is_none) {
                    open += 1;
                    clear += usize::from(h >= z1 + 1.0);
                }
            }
        }
        assert!(under > 50, "the fan reaches under the slabs: {under}");
        // Of the table points with nothing over them, those near the slab's edge on the
        // fan's outer side and at the fan's ends are not shown clear; the rest are.
        assert!(clear as f64 > 0.7 * open as f64, "{clear} of {open} clear");
    }

    #[test]
    fn a_part_point_is_clear_above_only_when_every_ray_over_it_returned_past_it() {
        // A block on the floor and a slab floating over part of it (an overhang), seen by a
        // sensor looking straight down, or rolled up to 20° about its pass direction (sensor Y,
        // the normal of its laser plane: the plane still holds the vertical): the fan's slanted
        // rays reach the block's top under the slab's edge. The reference is the vertical cast
        // up from the point against the mesh.
        let mut rng = StdRng::seed_from_u64(17);
        let (mut under, mut clear, mut open) = (0usize, 0usize, 0usize);
        for scene in 0..60 {
            let roll = if scene % 2 == 0 { 0.0 } else { rng.random_range(-20f64..20.0).to_radians() };
            let (hx, hy) = (rng.random_range(8.0..20.0), rng.random_range(8.0..20.0));
            let z0 = rng.random_range(2.0..10.0);
            let s0 = z0 + rng.random_range(1.0..8.0);
            let s1 = s0 + rng.random_range(1.0..5.0);
            let sx = rng.random_range(-hx..hx);
            let mut m = Mesh { vertices: Vec::new(), triangles: Vec::new() };
            add_box(&mut m, [-hx, -hy, 0.0], [hx, hy, z0]);
            add_box(&mut m, [sx, -hy - 5.0, s0], [sx + 12.0, hy + 5.0, s1]);
            let sc = Scanner::new(ScannerSpec::slp400(), &m, 3).expect("scanner");
            let world_from_sensor = Isometry3::from_parts(
                Translation3::new(
                    rng.random_range(-25.0..25.0),
                    rng.random_range(-hy..hy),
                    s1 + rng.random_range(90.0..200.0),
                ),
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
                    * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), roll),
            );
            let p = sc.profile_seeded(&world_from_sensor, 0, 11);
            let up = world_from_sensor.rotation.inverse() * Vector3::z();
            let top = s1 + 1.0 - world_from_sensor.translation.vector.z;
            let heights = sc.point_clear_height(&p, &up, top);
            assert_eq!(heights.len(), p.points.len());
            for (q, h) in p.points.iter().zip(heights) {
                let w = world_from_sensor * q;
                if w.z > z0 + 0.5 {
                    continue; // the slab's own top
                }
                let first_hits: Vec<Option<f64>> =
                    [(0.0, 0.0), (0.02, 0.0), (-0.02, 0.0), (0.0, 0.02), (0.0, -0.02)]
                        .iter()
                        .map(|(dx, dy)| {
                            let o = Point3::new(w.x + dx, w.y + dy, z0 + 0.2);
                            sc.bvh().cast(&o, &Vector3::z(), s1 + 1.0).map(|hit| hit.t + z0 + 0.2 - w.z)
                        })
                        .collect();
                if first_hits.iter().all(Option::is_some) {
                    under += 1;
                    let hit = first_hits.iter().flatten().fold(f64::INFINITY, |a, b| a.min(*b));
                    assert!(
                        h <= hit + 0.05,
                        "a point's vertical shown clear to {h} mm meets the slab at {hit} mm: {w:?}"
                    );
                } else if first_hits.iter().all(Option::is_none) {
                    open += 1;
                    clear += usize::from(h >= s1 + 1.0 - w.z - 1e-9);
                }
            }
        }
        assert!(under > 50, "the fan reaches under the slab: {under}");
        assert!(clear as f64 > 0.7 * open as f64, "{clear} of {open} clear");
    }

    #[test]
    fn incidence_limit_drops_steep_surfaces() {
        let mut steep = Scanner::new(ScannerSpec::slp400(), &plate(150.0, 150.0, 40.0), 5).expect("scanner");
        let p = steep.profile(&Isometry3::identity(), 0);
        assert!(p.points.is_empty());
        assert_eq!(p.dropped.incidence, 450);
        let mut mild = Scanner::new(ScannerSpec::slp400(), &plate(150.0, 150.0, 20.0), 5).expect("scanner");
        let p = mild.profile(&Isometry3::identity(), 0);
        assert!(p.points.len() > 300, "{}", p.points.len());
        assert_eq!(p.points.len() as u32 + p.dropped.incidence, 450);
    }

    #[test]
    fn a_step_occludes_the_camera_view() {
        // Floor at z = 200; a block from z = 150 to 199 over x in [0, 50], y in [5, 100], on the
        // camera's side (+Y) of the laser plane y = 0 and not cut by it. The line of sight from a
        // floor spot with x > 0 to the camera at (0, 60, 0) passes through the block's y = 5 wall.
        let mut m = plate(200.0, 200.0, 0.0);
        let mut open = Scanner::new(ScannerSpec::slp400(), &m, 9).expect("scanner");
        assert_eq!(open.profile(&Isometry3::identity(), 0).dropped.occluded, 0);
        add_box(&mut m, [0.0, 5.0, 150.0], [50.0, 100.0, 199.0]);
        let mut sc = Scanner::new(ScannerSpec::slp400(), &m, 9).expect("scanner");
        let p = sc.profile(&Isometry3::identity(), 0);
        assert!(p.dropped.occluded >= 200, "{:?}", p.dropped);
        assert!(p.points.len() >= 200);
        assert!(p.points.iter().all(|q| q.x < 0.2), "a visible point on the hidden side");
        // Flip the block to the other side of the laser plane: the camera sees everything.
        let mut m2 = plate(200.0, 200.0, 0.0);
        add_box(&mut m2, [0.0, -100.0, 150.0], [50.0, -5.0, 199.0]);
        let mut sc2 = Scanner::new(ScannerSpec::slp400(), &m2, 9).expect("scanner");
        assert_eq!(sc2.profile(&Isometry3::identity(), 0).dropped.occluded, 0);
    }

    #[test]
    fn a_surface_facing_away_from_the_camera_is_hidden() {
        // Camera 400 mm off the laser plane; a plate at 100 mm tilted 20° about X (within the
        // incidence limit). Tilted towards the camera it is seen; tilted away, the camera is
        // behind its plane and sees nothing.
        let mut spec = ScannerSpec::slp400();
        spec.camera_baseline_mm = 400.0;
        for (deg, visible) in [(20.0f64, true), (-20.0, false)] {
            let mut m = plate(0.0, 100.0, 0.0);
            m.transform(&Isometry3::from_parts(
                Translation3::new(0.0, 0.0, 100.0),
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), deg.to_radians()),
            ));
            let mut sc = Scanner::new(spec.clone(), &m, 4).expect("scanner");
            let p = sc.profile(&Isometry3::identity(), 0);
            if visible {
                assert_eq!(p.points.len(), 450, "{deg}: {:?}", p.dropped);
            } else {
                assert_eq!(p.dropped.occluded, 450, "{deg}: {:?}", p.dropped);
            }
        }
    }

    fn mean_intensity(z: f64, tilt: f64) -> f64 {
        let mut sc = Scanner::new(ScannerSpec::slp400(), &plate(z, 200.0, tilt), 11).expect("scanner");
        let p = sc.profile(&Isometry3::identity(), 0);
        // Central columns only, so the incidence spread of the fan is small.
        let v: Vec<f64> = p
            .column
            .iter()
            .zip(&p.intensity)
            .filter(|(c, _)| (200..250).contains(*c))
            .map(|(_, &i)| i as f64)
            .collect();
        assert!(!v.is_empty());
        v.iter().sum::<f64>() / v.len() as f64
    }

    #[test]
    fn intensity_falls_with_incidence_and_distance() {
        let near = mean_intensity(100.0, 0.0);
        let far = mean_intensity(200.0, 0.0);
        assert!((near - (65.0f64 / 100.0).powi(2)).abs() < 0.01, "{near}");
        assert!(far < near * 0.3, "{far} vs {near}");
        let flat = mean_intensity(150.0, 0.0);
        let tilted = mean_intensity(150.0, 20.0);
        assert!(tilted < flat * 0.97, "{tilted} vs {flat}");
        let mut sc = Scanner::new(ScannerSpec::slp400(), &plate(66.0, 200.0, 0.0), 11).expect("scanner");
        assert!(sc.profile(&Isometry3::identity(), 0).intensity.iter().all(|&i| (0.0..=1.0).contains(&i)));
    }

    #[test]
    fn profile_maps_to_world_with_its_pose() {
        // Sensor 150 mm above a plate at world z = 0, looking down (sensor +Z = world −Z).
        let pose = Isometry3::from_parts(
            Translation3::new(10.0, -20.0, 150.0),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        );
        let mut m = plate(0.0, 200.0, 0.0);
        m.vertices.iter_mut().for_each(|v| *v += Vector3::new(10.0, -20.0, 0.0));
        let mut sc = Scanner::new(ScannerSpec::slp400(), &m, 2).expect("scanner");
        let p = sc.profile(&pose, 7);
        assert_eq!(p.points.len(), 450);
        assert!((p.time_s - 0.07).abs() < 1e-12);
        for w in p.to_world(&pose) {
            assert!(w.z.abs() < 0.25 && (w.y + 20.0).abs() < 1e-9);
        }
    }

    #[test]
    fn same_seed_same_profile() {
        let m = plate(120.0, 100.0, 10.0);
        let mut a = Scanner::new(ScannerSpec::slp400(), &m, 77).expect("scanner");
        let mut b = Scanner::new(ScannerSpec::slp400(), &m, 77).expect("scanner");
        assert_eq!(a.profile(&Isometry3::identity(), 3), b.profile(&Isometry3::identity(), 3));
    }

    #[test]
    fn line_rate_and_spec_validation() {
        let t = frame_times(1.0, 100.0, 3).expect("valid");
        assert!((t[0] - 1.0).abs() < 1e-12 && (t[1] - 1.01).abs() < 1e-12 && (t[2] - 1.02).abs() < 1e-12);
        assert!(frame_times(0.0, 50.0, 2).is_ok() && frame_times(0.0, 150.0, 2).is_ok());
        for bad in [40.0, 49.9, 150.1, f64::NAN, f64::INFINITY] {
            let e = frame_times(0.0, bad, 2).expect_err("out of range");
            assert!(matches!(e, ScannerError::LineRate { .. }));
        }
        let msg = frame_times(0.0, 40.0, 1).expect_err("low").to_string();
        assert!(msg.contains("40") && msg.contains("50") && msg.contains("150"), "{msg}");
        assert!(frame_times(f64::NAN, 100.0, 1).is_err());
        let mut s = ScannerSpec::slp400();
        s.points_per_line = 449;
        let msg = s.validate().expect_err("too few").to_string();
        assert!(msg.contains("points_per_line") && msg.contains("449"), "{msg}");
        let mut s = ScannerSpec::slp400();
        s.line_rate_hz = 200.0;
        assert!(Scanner::new(s, &Mesh::default(), 0).is_err());
        let mut s = ScannerSpec::slp400();
        s.line_length_far_mm = 30.0;
        assert!(s.validate().expect_err("parallel").to_string().contains("line_length_far_mm"));
        let mut s = ScannerSpec::slp400();
        s.points_per_line = 900;
        let mut sc = Scanner::new(s, &plate(150.0, 100.0, 0.0), 0).expect("scanner");
        assert_eq!(sc.profile(&Isometry3::identity(), 0).points.len(), 900);
    }
}
