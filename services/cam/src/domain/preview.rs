//! Preview: sweep the planned tools over the stock to render the surface the program leaves, and
//! measure it against the model: gouge (cut below the part) and leftover (material above it).
//!
//! Algorithm: the stock is a Z-map on the depth map's grid, initially flat at the stock top. Every
//! move counts (rapids too: a rapid through material shows up as a gouge). A straight move at
//! constant Z is applied exactly: each cell whose centre is within the tool radius of the segment
//! drops to `z + height_at(distance to the segment)` (the tool's height grows with distance, so the
//! nearest point of the segment is the deepest). A ball end mill's straight moves are exact too: one
//! on its own as a capsule (closed form), consecutive ones whose XY lie on one line (a raster pass)
//! as a [`Run`], cut in each cell's plane parallel to the pass where the swept solid's section is a
//! 2-D offset of the centre polyline, so a cell evaluates the one or two pieces of that offset over
//! it instead of every short move within the tool's reach. Other moves are sampled at no more than half a
//! pixel, and each sample lowers the cells within its radius to `tip_z + height_at(distance)`;
//! between samples the surface can be higher than the true envelope by at most the tool's height
//! change over a quarter pixel, so leftover is slightly over-reported there. Rows are split into bands processed in parallel,
//! each band applying the samples whose footprint reaches it.

use depthmill_geometry::HeightMap;
use nalgebra::Point3;
use rayon::prelude::*;

use super::CamError;
use super::path::Segment;
use super::tool::Tool;

/// One tool's moves, from `start`.
pub struct SweptOp<'a> {
    pub tool: &'a Tool,
    pub start: Point3<f64>,
    pub segments: &'a [Segment],
}

/// What the program leaves.
#[derive(Debug, Clone)]
pub struct PreviewReport {
    /// Top of the machined stock at each cell centre.
    pub final_surface: HeightMap,
    /// `final - target` (NaN where the target has no data); negative values are gouges.
    pub leftover: HeightMap,
    /// Largest depth cut below the target (0 when nothing was gouged).
    pub max_gouge_mm: f64,
    /// Where the largest gouge is (cell centre, mm), when there is one.
    pub gouge_at_mm: Option<[f64; 2]>,
    pub max_leftover_mm: f64,
    pub mean_leftover_mm: f64,
    /// Tool positions applied.
    pub samples: u64,
}

const BAND_ROWS: usize = 16;

/// Sampling step along moves, in pixels.
const SAMPLE_STEP_PX: f64 = 0.5;

/// The tool's height above its tip as a function of the squared distance from its axis, with
/// closed forms for the common shapes (one square root for a ball, none for a flat end).
enum Shape<'a> {
    Ball { r: f64 },
    Flat { r2: f64 },
    Profile(&'a depthmill_geometry::ToolProfile),
}

impl<'a> Shape<'a> {
    fn of(profile: &'a depthmill_geometry::ToolProfile) -> Self {
        match profile.spec() {
            Some(depthmill_geometry::ToolSpec::Ball { diameter_mm }) => Shape::Ball { r: diameter_mm / 2.0 },
            Some(depthmill_geometry::ToolSpec::Flat { diameter_mm }) => {
                Shape::Flat { r2: (diameter_mm / 2.0).powi(2) }
            }
            _ => Shape::Profile(profile),
        }
    }

    #[inline]
    fn height_at_d2(&self, d2: f64) -> Option<f64> {
        match *self {
            Shape::Ball { r } => (d2 <= r * r).then(|| r - (r * r - d2).max(0.0).sqrt()),
            Shape::Flat { r2 } => (d2 <= r2).then_some(0.0),
            Shape::Profile(p) => p.height_at(d2.sqrt()),
        }
    }
}

/// Samples a move from `from` along `seg` at most `step` apart (excluding `from`, including the end).
pub fn sample_segment(from: Point3<f64>, seg: &Segment, step: f64, out: &mut Vec<Point3<f64>>) {
    match *seg {
        Segment::Rapid(to) | Segment::Linear(to) | Segment::Plunge(to) => {
            let n = ((to - from).norm() / step).ceil().max(1.0) as usize;
            for i in 1..=n {
                out.push(from + (to - from) * (i as f64 / n as f64));
            }
        }
        Segment::Arc { end, center, clockwise } => {
            let (cx, cy) = (center[0], center[1]);
            let r = ((from.x - cx).powi(2) + (from.y - cy).powi(2)).sqrt();
            let a0 = (from.y - cy).atan2(from.x - cx);
            let a1 = (end.y - cy).atan2(end.x - cx);
            let tau = std::f64::consts::TAU;
            let mut sweep = if clockwise { a0 - a1 } else { a1 - a0 };
            sweep = sweep.rem_euclid(tau);
            if sweep < 1e-12 {
                sweep = tau;
            }
            let len = (sweep * r).hypot(end.z - from.z);
            let n = (len / step).ceil().max(1.0) as usize;
            for i in 1..=n {
                let t = i as f64 / n as f64;
                let a = if clockwise { a0 - sweep * t } else { a0 + sweep * t };
                let z = from.z + (end.z - from.z) * t;
                out.push(if i == n { end } else { Point3::new(cx + r * a.cos(), cy + r * a.sin(), z) });
            }
        }
    }
}

/// One piece of a tool's motion as the preview applies it.
#[derive(Debug, Clone, Copy)]
enum Sweep {
    /// The tool at one position (moves that change Z are sampled).
    Point(Point3<f64>),
    /// A straight move at constant Z from `a` to `b` (XY): the envelope is exact, each cell takes
    /// the tool's height at its distance from the segment.
    Level { a: [f64; 2], b: [f64; 2], z: f64 },
    /// A ball end mill on a straight sloped move from tip `a` to tip `b`: the swept solid is a
    /// capsule, and each cell takes the lowest point of the capsule above it (closed form).
    BallLine { a: Point3<f64>, b: Point3<f64>, r: f64 },
    /// A ball end mill on consecutive straight moves whose XY lie on one line (a raster pass):
    /// `runs[i]`, exact through its section in each cell's plane.
    Run(usize),
}

/// Consecutive straight moves of a ball end mill whose XY lie on one line (a raster pass, the
/// moves in it sloped or level, forwards or back).
///
/// Exact by sections: the plane parallel to the pass at distance `v` from it cuts the ball of radius
/// `r` around each centre point in a disc of radius `r' = sqrt(r² - v²)`, so the swept solid's
/// section is the union of 2-D stadiums of radius `r'` around the centre polyline (tip + r) in
/// (u, z), `u` the coordinate along the pass. The lowest point of such a union above `u` lies on its
/// boundary, and every boundary point of a polyline grown by a disc is on its raw offset: a
/// segment's lower offset line where the foot falls inside the segment, or a vertex's circle in the
/// directions of its normal cone (those that make an obtuse angle with both neighbouring edges).
/// The pieces are kept with their `u` ranges for any `r' <= r` in buckets of one cell along `u`, so
/// a cell evaluates the few pieces over it instead of every move within the tool's reach.
struct Run {
    /// A point of the line and its unit direction (XY).
    o: [f64; 2],
    d: [f64; 2],
    r: f64,
    /// XY bounds of the tip positions, and their lowest Z.
    bbox: [f64; 4],
    z_min: f64,
    /// Buckets along `u`: bucket `k` covers `[u0 + k·bw, u0 + (k+1)·bw)`; its pieces are the
    /// lines `line_items[line_starts[k]..line_starts[k+1]]` and the arcs likewise, each kind
    /// read in a loop of its own (no branch on the kind).
    u0: f64,
    bw: f64,
    line_starts: Vec<u32>,
    line_items: Vec<u32>,
    lines: Vec<Line>,
    arc_starts: Vec<u32>,
    arc_items: Vec<u32>,
    arcs: Vec<Arc>,
    /// Per bucket, the lowest centre height of its pieces: no piece is below it by more than the
    /// section radius.
    zlo: Vec<f64>,
}

/// One piece of a [`Run`]'s raw lower offset, for a section radius `r'` (`zc`: centre heights).
#[derive(Debug, Clone, Copy)]
enum Piece {
    Line(Line),
    Arc(Arc),
}

/// The lower offset of the centre segment from `(ua, za)` to `(ub, zb)` (`ua < ub`): over `u` in
/// `[ua + r'·sin, ub + r'·sin]` at `za - r'·cos + slope·(u - ua - r'·sin)`.
#[derive(Debug, Clone, Copy)]
struct Line {
    ua: f64,
    ub: f64,
    za: f64,
    sin: f64,
    cos: f64,
    slope: f64,
}

/// The lower circle about the centre vertex `(uk, zk)` in the directions whose `u` component (sine
/// of the angle from straight down) lies in `[slo, shi]`.
#[derive(Debug, Clone, Copy)]
struct Arc {
    uk: f64,
    zk: f64,
    slo: f64,
    shi: f64,
}

/// Slack on a piece's range (mm, or sine): a cell on the boundary between two pieces takes both.
const PIECE_EPS: f64 = 1e-9;

impl Run {
    /// The run through the tip positions `tips` (at least two, all on the XY line `o + t·d`).
    fn new(tips: &[Point3<f64>], o: [f64; 2], d: [f64; 2], r: f64, bw: f64) -> Run {
        let v: Vec<(f64, f64)> =
            tips.iter().map(|t| ((t.x - o[0]) * d[0] + (t.y - o[1]) * d[1], t.z + r)).collect();
        let mut pieces = Vec::with_capacity(2 * v.len());
        for w in v.windows(2) {
            let (a, b) = if w[0].0 <= w[1].0 { (w[0], w[1]) } else { (w[1], w[0]) };
            let (du, dz) = (b.0 - a.0, b.1 - a.1);
            if du <= 0.0 {
                continue; // vertical: its lower end's circle covers it
            }
            let len = du.hypot(dz);
            pieces.push(Piece::Line(Line {
                ua: a.0,
                ub: b.0,
                za: a.1,
                sin: dz / len,
                cos: du / len,
                slope: dz / du,
            }));
        }
        for (k, &(uk, zk)) in v.iter().enumerate() {
            // Normal cone of the vertex, as the sine range of directions (sin φ, -cos φ).
            let (mut slo, mut shi) = (-1.0f64, 1.0f64);
            for n in [k.checked_sub(1), Some(k + 1)].into_iter().flatten() {
                let Some(&(un, zn)) = v.get(n) else { continue };
                let (eu, ez) = (un - uk, zn - zk);
                let len = eu.hypot(ez);
                if len == 0.0 {
                    continue;
                }
                if eu >= 0.0 {
                    shi = shi.min(ez / len);
                } else {
                    slo = slo.max(-ez / len);
                }
            }
            if slo <= shi {
                pieces.push(Piece::Arc(Arc { uk, zk, slo, shi }));
            }
        }
        // Each piece's u range over every r' in [0, r].
        let range = |p: &Piece| match *p {
            Piece::Line(Line { ua, ub, sin, .. }) => (ua + (r * sin).min(0.0), ub + (r * sin).max(0.0)),
            Piece::Arc(Arc { uk, slo, shi, .. }) => (uk + (r * slo).min(0.0), uk + (r * shi).max(0.0)),
        };
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for p in &pieces {
            let (a, b) = range(p);
            lo = lo.min(a);
            hi = hi.max(b);
        }
        let u0 = lo - 2.0 * PIECE_EPS;
        let nb = if hi >= lo { ((hi + 2.0 * PIECE_EPS - u0) / bw).floor() as usize + 1 } else { 0 };
        let bucket = |u: f64| (((u - u0) / bw).floor().max(0.0) as usize).min(nb.saturating_sub(1));
        // Counting sort of (bucket, piece) pairs, lines and arcs apart.
        let (mut lines, mut arcs) = (Vec::new(), Vec::new());
        let (mut line_starts, mut arc_starts) = (vec![0u32; nb + 1], vec![0u32; nb + 1]);
        for p in &pieces {
            let (a, b) = range(p);
            let starts = match *p {
                Piece::Line(l) => {
                    lines.push(l);
                    &mut line_starts
                }
                Piece::Arc(c) => {
                    arcs.push(c);
                    &mut arc_starts
                }
            };
            for k in bucket(a - PIECE_EPS)..=bucket(b + PIECE_EPS) {
                starts[k + 1] += 1;
            }
        }
        for k in 0..nb {
            line_starts[k + 1] += line_starts[k];
            arc_starts[k + 1] += arc_starts[k];
        }
        let (mut line_fill, mut arc_fill) = (line_starts.clone(), arc_starts.clone());
        let mut line_items = vec![0u32; line_starts[nb] as usize];
        let mut arc_items = vec![0u32; arc_starts[nb] as usize];
        let mut zlo = vec![f64::INFINITY; nb];
        let (mut li, mut ai) = (0u32, 0u32);
        for p in &pieces {
            let (a, b) = range(p);
            for k in bucket(a - PIECE_EPS)..=bucket(b + PIECE_EPS) {
                match *p {
                    Piece::Line(l) => {
                        line_items[line_fill[k] as usize] = li;
                        line_fill[k] += 1;
                        zlo[k] = zlo[k].min(l.za.min(l.za + l.slope * (l.ub - l.ua)));
                    }
                    Piece::Arc(c) => {
                        arc_items[arc_fill[k] as usize] = ai;
                        arc_fill[k] += 1;
                        zlo[k] = zlo[k].min(c.zk);
                    }
                }
            }
            match p {
                Piece::Line(_) => li += 1,
                Piece::Arc(_) => ai += 1,
            }
        }
        let mut bbox = [f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY];
        for t in tips {
            bbox = [bbox[0].min(t.x), bbox[1].max(t.x), bbox[2].min(t.y), bbox[3].max(t.y)];
        }
        let z_min = tips.iter().map(|t| t.z).fold(f64::INFINITY, f64::min);
        Run { o, d, r, bbox, z_min, u0, bw, line_starts, line_items, lines, arc_starts, arc_items, arcs, zlo }
    }

    /// The columns of the row at `cy` the swept solid can be above (`|v| <= r` and `u` within the
    /// pieces' range), with a column of margin; `None` when there are none.
    fn columns(&self, cy: f64, g: &Grid) -> Option<(usize, usize)> {
        // Along the row, x = o.x + t: u = t·d.x + ry·d.y, v = ry·d.x - t·d.y.
        let ry = cy - self.o[1];
        let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
        let u_hi = self.u0 + self.bw * (self.line_starts.len() - 1) as f64;
        let mut clip = |k: f64, c: f64, a: f64, b: f64| -> bool {
            // a <= k·t + c <= b
            if k.abs() < 1e-12 {
                return c >= a && c <= b;
            }
            let (t0, t1) = ((a - c) / k, (b - c) / k);
            lo = lo.max(t0.min(t1));
            hi = hi.min(t0.max(t1));
            true
        };
        if !clip(-self.d[1], ry * self.d[0], -self.r, self.r)
            || !clip(self.d[0], ry * self.d[1], self.u0, u_hi)
            || lo > hi
        {
            return None;
        }
        let col = |x: f64| ((x - g.x0) / g.p - 0.5).floor();
        let c_lo = col(self.o[0] + lo) - 1.0;
        let c_hi = col(self.o[0] + hi) + 2.0;
        if c_hi < 0.0 || c_lo > g.w as f64 - 1.0 {
            return None;
        }
        Some((c_lo.max(0.0) as usize, c_hi.min(g.w as f64 - 1.0) as usize))
    }

    /// Lowers `cell` (at `c`, XY) to the lowest point of the swept solid above it.
    #[inline]
    fn lower(&self, c: [f64; 2], cell: &mut f32) {
        let (rx, ry) = (c[0] - self.o[0], c[1] - self.o[1]);
        let u = rx * self.d[0] + ry * self.d[1];
        let v = ry * self.d[0] - rx * self.d[1];
        let rp2 = self.r * self.r - v * v;
        if rp2 < 0.0 {
            return;
        }
        self.lower_at(u, rp2.sqrt(), rp2, cell);
    }

    /// The cells of a row of `g` (`cells`, from column `col0`, all at `cy`) lowered as
    /// [`Run::lower`] does, the section radius worked out once when the run lies along X.
    fn lower_row(&self, g: &Grid, col0: usize, cy: f64, cells: &mut [f32]) {
        let cx = |i: usize| g.x0 + ((col0 + i) as f64 + 0.5) * g.p;
        if self.d[1] != 0.0 {
            for (i, cell) in cells.iter_mut().enumerate() {
                self.lower([cx(i), cy], cell);
            }
            return;
        }
        // Along X: v is the row's offset from the line, the same for every cell.
        let ry = cy - self.o[1];
        let rp2 = self.r * self.r - ry * self.d[0] * (ry * self.d[0]);
        if rp2 < 0.0 {
            return;
        }
        let rp = rp2.sqrt();
        for (i, cell) in cells.iter_mut().enumerate() {
            self.lower_at((cx(i) - self.o[0]) * self.d[0] + ry * self.d[1], rp, rp2, cell);
        }
    }

    /// Lowers `cell` at `u` along the run, where the section radius is `rp` (`rp2` its square).
    #[inline]
    fn lower_at(&self, u: f64, rp: f64, rp2: f64, cell: &mut f32) {
        // Truncation is the floor here (k >= 0), without a libm call per cell.
        let k = (u - self.u0) / self.bw;
        if !(k >= 0.0 && (k as usize) + 1 < self.line_starts.len()) {
            return;
        }
        let k = k as usize;
        if *cell <= (self.zlo[k] - rp) as f32 {
            return; // already at or below anything this run reaches here
        }
        let mut best = f64::INFINITY;
        for &i in &self.line_items[self.line_starts[k] as usize..self.line_starts[k + 1] as usize] {
            let Line { ua, ub, za, sin, cos, slope } = self.lines[i as usize];
            let s = rp * sin;
            if u >= ua + s - PIECE_EPS && u <= ub + s + PIECE_EPS {
                best = best.min(za - rp * cos + slope * (u - ua - s));
            }
        }
        for &i in &self.arc_items[self.arc_starts[k] as usize..self.arc_starts[k + 1] as usize] {
            let Arc { uk, zk, slo, shi } = self.arcs[i as usize];
            let du = u - uk;
            if du >= rp * slo - PIECE_EPS && du <= rp * shi + PIECE_EPS {
                best = best.min(zk - (rp2 - du * du).max(0.0).sqrt());
            }
        }
        let z = best as f32;
        if z < *cell {
            *cell = z;
        }
    }
}

/// The moves of `op` as sweeps: straight moves at constant Z whole, a ball's straight moves along
/// one XY line as [`Run`]s (their tips and line added to `runs`, made into runs afterwards), the
/// rest sampled `step` apart.
fn sweeps(op: &SweptOp<'_>, step: f64, runs: &mut Vec<RunTips>) -> Vec<Sweep> {
    let ball = match op.tool.profile.spec() {
        Some(depthmill_geometry::ToolSpec::Ball { diameter_mm }) => Some(diameter_mm / 2.0),
        _ => None,
    };
    let mut out = vec![Sweep::Point(op.start)];
    let mut samples = Vec::new();
    let mut run = RunBuilder::default();
    let mut at = op.start;
    for seg in op.segments {
        match (*seg, ball) {
            (Segment::Rapid(to) | Segment::Linear(to) | Segment::Plunge(to), Some(r)) => {
                if !run.extend(at, to) {
                    run.flush(r, &mut out, runs);
                    run.extend(at, to);
                }
            }
            (Segment::Rapid(to) | Segment::Linear(to) | Segment::Plunge(to), None)
                if (to.z - at.z).abs() < 1e-12 =>
            {
                out.push(Sweep::Level { a: [at.x, at.y], b: [to.x, to.y], z: at.z });
            }
            // Straight up or down: the tool at the lower end is below every other position.
            (Segment::Rapid(to) | Segment::Linear(to) | Segment::Plunge(to), None)
                if to.x == at.x && to.y == at.y =>
            {
                out.push(Sweep::Point(if to.z < at.z { to } else { at }));
            }
            _ => {
                if let Some(r) = ball {
                    run.flush(r, &mut out, runs);
                }
                samples.clear();
                sample_segment(at, seg, step, &mut samples);
                out.extend(samples.iter().map(|s| Sweep::Point(*s)));
            }
        }
        at = seg.end();
    }
    if let Some(r) = ball {
        run.flush(r, &mut out, runs);
    }
    out
}

/// What a [`Run`] is made from.
struct RunTips {
    tips: Vec<Point3<f64>>,
    o: [f64; 2],
    d: [f64; 2],
    r: f64,
}

/// Largest distance (mm) of a tip position from the XY line of the [`Run`] it joins.
const RUN_LINE_EPS: f64 = 1e-9;

/// Consecutive straight moves of a ball collected while their XY stay on one line.
#[derive(Default)]
struct RunBuilder {
    tips: Vec<Point3<f64>>,
    /// The line (point, unit direction) once two tips differ in XY.
    line: Option<([f64; 2], [f64; 2])>,
}

impl RunBuilder {
    /// Appends the move `from -> to` when it continues the run on its line; false otherwise.
    fn extend(&mut self, from: Point3<f64>, to: Point3<f64>) -> bool {
        if self.tips.is_empty() {
            self.tips.push(from);
        } else if self.tips.last() != Some(&from) {
            return false;
        }
        match self.line {
            Some((o, d)) => {
                if ((to.y - o[1]) * d[0] - (to.x - o[0]) * d[1]).abs() > RUN_LINE_EPS {
                    return false;
                }
            }
            None => {
                let o = [self.tips[0].x, self.tips[0].y];
                let (dx, dy) = (to.x - o[0], to.y - o[1]);
                let len = dx.hypot(dy);
                if len > RUN_LINE_EPS {
                    self.line = Some((o, [dx / len, dy / len]));
                }
            }
        }
        self.tips.push(to);
        true
    }

    /// Emits what was collected: a [`Run`] when there are at least two moves along a line, else
    /// each move on its own.
    fn flush(&mut self, r: f64, out: &mut Vec<Sweep>, runs: &mut Vec<RunTips>) {
        match self.line {
            Some((o, d)) if self.tips.len() > 2 => {
                runs.push(RunTips { tips: std::mem::take(&mut self.tips), o, d, r });
                out.push(Sweep::Run(runs.len() - 1));
            }
            _ => {
                for w in self.tips.windows(2) {
                    let (a, b) = (w[0], w[1]);
                    out.push(if (b.z - a.z).abs() < 1e-12 {
                        Sweep::Level { a: [a.x, a.y], b: [b.x, b.y], z: a.z }
                    } else {
                        Sweep::BallLine { a, b, r }
                    });
                }
            }
        }
        self.tips.clear();
        self.line = None;
    }
}

struct Grid {
    w: usize,
    x0: f64,
    y0: f64,
    p: f64,
}

/// Lowest point, above the horizontal position `c`, of the solid a ball end mill of radius `r`
/// sweeps when its tip moves straight from `a` to `b`: the capsule of radius `r` around the
/// centre segment `a + r·ẑ` .. `b + r·ẑ`. It is the lowest of: the lower intersection of the
/// vertical line through `c` with the infinite cylinder around the centre line, when that point
/// projects inside the segment, and the lowest points of the two end spheres. `None` when the
/// vertical line misses the capsule.
fn capsule_bottom(c: [f64; 2], a: Point3<f64>, b: Point3<f64>, r: f64) -> Option<f64> {
    let sphere = |q: Point3<f64>| {
        let d2 = (c[0] - q.x).powi(2) + (c[1] - q.y).powi(2);
        (d2 <= r * r).then(|| q.z + r - (r * r - d2).sqrt())
    };
    let mut best = match (sphere(a), sphere(b)) {
        (Some(x), Some(y)) => Some(x.min(y)),
        (x, y) => x.or(y),
    };
    let v = b - a;
    let l2 = v.norm_squared();
    let hxy2 = v.x * v.x + v.y * v.y;
    if l2 > 0.0 && hxy2 > 1e-18 {
        // w(z) = (c - centre_a) with the vertical coordinate z - centre_a.z = s: |w|² - (w·v)²/L² = r².
        let (ux, uy) = (c[0] - a.x, c[1] - a.y);
        let uv = ux * v.x + uy * v.y; // horizontal part of w·v; the vertical part is s·v.z
        let alpha = hxy2 / l2;
        let beta = -uv * v.z / l2;
        let gamma = ux * ux + uy * uy - uv * uv / l2 - r * r;
        let disc = beta * beta - alpha * gamma;
        if disc >= 0.0 {
            let s = (-beta - disc.sqrt()) / alpha; // lower root: centre-relative height
            let t = (uv + s * v.z) / l2;
            if (0.0..=1.0).contains(&t) {
                let z = a.z + r + s; // a point on the capsule surface (centre line is at tip + r)
                best = Some(best.map_or(z, |x| x.min(z)));
            }
        }
    }
    best
}

/// Squared distance from `c` to the segment `a`–`b` (XY).
#[inline]
fn dist2_to_segment(c: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let (vx, vy) = (b[0] - a[0], b[1] - a[1]);
    let (wx, wy) = (c[0] - a[0], c[1] - a[1]);
    let len2 = vx * vx + vy * vy;
    let t = if len2 > 0.0 { ((wx * vx + wy * vy) / len2).clamp(0.0, 1.0) } else { 0.0 };
    let (dx, dy) = (wx - t * vx, wy - t * vy);
    dx * dx + dy * dy
}

/// Lowers the cells of one band (rows `row0 .. row0 + rows`) under one sweep.
#[allow(clippy::too_many_arguments)]
fn apply(
    sw: &Sweep,
    runs: &[Run],
    shape: &Shape<'_>,
    r2: f64,
    g: &Grid,
    band: &mut [f32],
    row0: usize,
    rows: usize,
) {
    let radius = r2.sqrt();
    let (xlo, xhi, ylo, yhi) = match *sw {
        Sweep::Point(s) => (s.x, s.x, s.y, s.y),
        Sweep::Level { a, b, .. } => (a[0].min(b[0]), a[0].max(b[0]), a[1].min(b[1]), a[1].max(b[1])),
        Sweep::BallLine { a, b, .. } => (a.x.min(b.x), a.x.max(b.x), a.y.min(b.y), a.y.max(b.y)),
        Sweep::Run(i) => {
            let b = runs[i].bbox;
            (b[0], b[1], b[2], b[3])
        }
    };
    let row_lo = (((ylo - radius - g.y0) / g.p - 0.5).floor() as i64).max(row0 as i64);
    let row_hi = (((yhi + radius - g.y0) / g.p - 0.5).ceil() as i64).min((row0 + rows) as i64 - 1);
    for row in row_lo..=row_hi {
        let cy = g.y0 + (row as f64 + 0.5) * g.p;
        let line = &mut band[(row as usize - row0) * g.w..][..g.w];
        match *sw {
            Sweep::Point(s) => {
                let dy2 = (cy - s.y).powi(2);
                if dy2 > r2 {
                    continue;
                }
                // Only the columns inside the tool's circle on this row.
                let half = (r2 - dy2).sqrt();
                let col_lo = (((s.x - half - g.x0) / g.p - 0.5).floor() as i64).max(0);
                let col_hi = (((s.x + half - g.x0) / g.p - 0.5).ceil() as i64).min(g.w as i64 - 1);
                for col in col_lo..=col_hi {
                    let dx = g.x0 + (col as f64 + 0.5) * g.p - s.x;
                    if let Some(hgt) = shape.height_at_d2(dx * dx + dy2) {
                        let z = (s.z + hgt) as f32;
                        let cell = &mut line[col as usize];
                        if z < *cell {
                            *cell = z;
                        }
                    }
                }
            }
            Sweep::BallLine { a, b, r } => {
                let col_lo = (((xlo - radius - g.x0) / g.p - 0.5).floor() as i64).max(0);
                let col_hi = (((xhi + radius - g.x0) / g.p - 0.5).ceil() as i64).min(g.w as i64 - 1);
                for col in col_lo..=col_hi {
                    let cx = g.x0 + (col as f64 + 0.5) * g.p;
                    if let Some(zz) = capsule_bottom([cx, cy], a, b, r) {
                        let zz = zz as f32;
                        let cell = &mut line[col as usize];
                        if zz < *cell {
                            *cell = zz;
                        }
                    }
                }
            }
            Sweep::Run(i) => {
                let run = &runs[i];
                let Some((col_lo, col_hi)) = run.columns(cy, g) else { continue };
                run.lower_row(g, col_lo, cy, &mut line[col_lo..=col_hi]);
            }
            Sweep::Level { a, b, z } => {
                // Only the row's chord of the stadium; a flat end's cells strictly inside it all
                // drop to `z`, the chord's end cells (and other shapes' cells) are computed.
                let Some((xa, xb)) = stadium_chord(cy, a, b, radius) else { continue };
                let last = g.w as i64 - 1;
                let c0 = (((xa - g.x0) / g.p - 0.5).ceil() as i64 - 1).max(0);
                let c1 = (((xb - g.x0) / g.p - 0.5).floor() as i64 + 1).min(last);
                if c0 > c1 {
                    continue;
                }
                let (c0, c1) = (c0 as usize, c1 as usize);
                let exact = |col: usize, cell: &mut f32| {
                    let cx = g.x0 + (col as f64 + 0.5) * g.p;
                    if let Some(hgt) = shape.height_at_d2(dist2_to_segment([cx, cy], a, b)) {
                        let zz = (z + hgt) as f32;
                        if zz < *cell {
                            *cell = zz;
                        }
                    }
                };
                if matches!(shape, Shape::Flat { .. }) && c1 >= c0 + 4 {
                    let zz = z as f32;
                    for col in [c0, c0 + 1, c1 - 1, c1] {
                        exact(col, &mut line[col]);
                    }
                    for cell in &mut line[c0 + 2..c1 - 1] {
                        *cell = cell.min(zz);
                    }
                } else {
                    for (col, cell) in line[c0..=c1].iter_mut().enumerate() {
                        exact(col + c0, cell);
                    }
                }
            }
        }
    }
}

/// The x range of the row at `cy` within `r` of the segment `a`-`b` (XY): the union of the end
/// discs' chords and the band along the segment (the stadium is convex, so one interval).
fn stadium_chord(cy: f64, a: [f64; 2], b: [f64; 2], r: f64) -> Option<(f64, f64)> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for q in [a, b] {
        let h2 = r * r - (cy - q[1]) * (cy - q[1]);
        if h2 >= 0.0 {
            let h = h2.sqrt();
            lo = lo.min(q[0] - h);
            hi = hi.max(q[0] + h);
        }
    }
    let (vx, vy) = (b[0] - a[0], b[1] - a[1]);
    let len = vx.hypot(vy);
    if len > 0.0 {
        let (dx, dy) = (vx / len, vy / len);
        let ry = cy - a[1];
        // With s = x - a.x: along the segment 0 <= s·dx + ry·dy <= len, across it
        // -r <= s·dy - ry·dx <= r.
        let (mut s0, mut s1) = (f64::NEG_INFINITY, f64::INFINITY);
        let mut ok = true;
        for (k, c, from, to) in [(dx, ry * dy, 0.0, len), (dy, -ry * dx, -r, r)] {
            if k.abs() < 1e-15 {
                ok &= c >= from && c <= to;
            } else {
                let (t0, t1) = ((from - c) / k, (to - c) / k);
                s0 = s0.max(t0.min(t1));
                s1 = s1.min(t0.max(t1));
            }
        }
        if ok && s0 <= s1 {
            lo = lo.min(a[0] + s0);
            hi = hi.max(a[0] + s1);
        }
    }
    (lo <= hi).then_some((lo, hi))
}

/// Sweeps `ops` over a stock flat at `stock_top_mm` on `target`'s grid and compares with `target`.
pub fn simulate(
    target: &HeightMap,
    stock_top_mm: f64,
    ops: &[SweptOp<'_>],
) -> Result<PreviewReport, CamError> {
    if !stock_top_mm.is_finite() {
        return Err(CamError::param("stock_top_mm", format!("must be finite, got {stock_top_mm}")));
    }
    let meta = *target.meta();
    let (w, h) = (meta.width as usize, meta.height as usize);
    let p = meta.pixel_mm;
    let (x0, y0) = (meta.origin_x_mm, meta.origin_y_mm);
    let mut surface = vec![stock_top_mm as f32; w * h];
    let mut samples_total = 0u64;
    for op in ops {
        let radius = op.tool.radius_mm();
        let r2 = radius * radius;
        let mut run_tips = Vec::new();
        let sweeps = sweeps(op, p * SAMPLE_STEP_PX, &mut run_tips);
        // Buckets one cell long along the pass, or a sixteenth of the radius when that is longer
        // (a steep piece spans up to r / bucket buckets: a large ball on fine cells would
        // otherwise list each piece in hundreds of them).
        let bucket = p.max(radius / 16.0);
        let runs: Vec<Run> =
            run_tips.into_par_iter().map(|t| Run::new(&t.tips, t.o, t.d, t.r, bucket)).collect();
        samples_total += sweeps.len() as u64;
        // Bucket sweeps by the row bands their footprint reaches.
        let bands = h.div_ceil(BAND_ROWS);
        let mut buckets: Vec<Vec<Sweep>> = vec![Vec::new(); bands];
        for sw in sweeps {
            let (ylo, yhi, z) = match sw {
                Sweep::Point(s) => (s.y, s.y, s.z),
                Sweep::Level { a, b, z } => (a[1].min(b[1]), a[1].max(b[1]), z),
                Sweep::BallLine { a, b, .. } => (a.y.min(b.y), a.y.max(b.y), a.z.min(b.z)),
                Sweep::Run(i) => (runs[i].bbox[2], runs[i].bbox[3], runs[i].z_min),
            };
            // The tool's lowest point is its tip: a sweep at or above the stock top cuts nothing.
            if z >= stock_top_mm {
                continue;
            }
            let row_lo = (((ylo - radius - y0) / p).floor() as i64).max(0);
            let row_hi = (((yhi + radius - y0) / p).ceil() as i64).min(h as i64 - 1);
            if row_hi < 0 || row_lo > h as i64 - 1 || row_lo > row_hi {
                continue;
            }
            for bucket in &mut buckets[row_lo as usize / BAND_ROWS..=row_hi as usize / BAND_ROWS] {
                bucket.push(sw);
            }
        }
        let shape = Shape::of(&op.tool.profile);
        let grid = Grid { w, x0, y0, p };
        let y_range = |sw: &Sweep| match *sw {
            Sweep::Point(s) => (s.y, s.y),
            Sweep::Level { a, b, .. } => (a[1].min(b[1]), a[1].max(b[1])),
            Sweep::BallLine { a, b, .. } => (a.y.min(b.y), a.y.max(b.y)),
            Sweep::Run(i) => (runs[i].bbox[2], runs[i].bbox[3]),
        };
        surface.par_chunks_mut(BAND_ROWS * w).zip(buckets.par_iter()).enumerate().for_each(
            |(b, (band, items))| {
                let band_row0 = b * BAND_ROWS;
                // Row by row, the sweeps nearest the row first: a raster pass further off then
                // finds the cells already below anything it reaches and skips them (the result
                // is the lowest of all, in any order).
                let mut order: Vec<(f64, usize)> = Vec::with_capacity(items.len());
                for (r, row) in band.chunks_mut(w).enumerate() {
                    let cy = y0 + ((band_row0 + r) as f64 + 0.5) * p;
                    order.clear();
                    order.extend(items.iter().enumerate().map(|(i, sw)| {
                        let (lo, hi) = y_range(sw);
                        ((lo - cy).max(cy - hi).max(0.0), i)
                    }));
                    order.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
                    for &(_, i) in &order {
                        apply(&items[i], &runs, &shape, r2, &grid, row, band_row0 + r, 1);
                    }
                }
            },
        );
    }
    let t = target.data();
    let mut leftover = vec![f32::NAN; w * h];
    let (mut max_gouge, mut gouge_idx, mut max_left, mut sum_left, mut n) =
        (0.0f64, None, 0.0f64, 0.0f64, 0u64);
    for i in 0..w * h {
        if t[i].is_nan() {
            continue;
        }
        let d = f64::from(surface[i]) - f64::from(t[i]);
        leftover[i] = d as f32;
        if -d > max_gouge {
            max_gouge = -d;
            gouge_idx = Some(i);
        }
        if d > 0.0 {
            max_left = max_left.max(d);
            sum_left += d;
        }
        n += 1;
    }
    let gouge_at_mm = gouge_idx.map(|i| {
        let (c, r) = ((i % w) as u32, (i / w) as u32);
        let (x, y) = meta.cell_center(c, r);
        [x, y]
    });
    let map_err = |e: depthmill_geometry::GeometryError| CamError::InvalidMap { message: e.to_string() };
    let mut surface_meta = meta;
    let lo = surface.iter().copied().fold(f32::INFINITY, f32::min);
    surface_meta.z_min_mm = f64::from(lo).min(meta.z_min_mm);
    surface_meta.z_max_mm = stock_top_mm.max(surface_meta.z_min_mm + 1e-3);
    let mut left_meta = meta;
    left_meta.z_min_mm = -max_gouge.max(1e-3);
    left_meta.z_max_mm = max_left.max(1e-3);
    Ok(PreviewReport {
        final_surface: HeightMap::new(surface_meta, surface).map_err(map_err)?,
        leftover: HeightMap::new(left_meta, leftover).map_err(map_err)?,
        max_gouge_mm: max_gouge,
        gouge_at_mm,
        max_leftover_mm: max_left,
        mean_leftover_mm: if n > 0 { sum_left / n as f64 } else { 0.0 },
        samples: samples_total,
    })
}

#[cfg(test)]
mod tests {
    use depthmill_geometry::{HeightMapMeta, ToolSpec};

    use super::*;

    fn flat_target(w: u32, h: u32, z: f32) -> HeightMap {
        let mut meta = HeightMapMeta::new(w, h, 0.1);
        meta.z_max_mm = 10.0;
        HeightMap::filled(meta, z).expect("map")
    }

    /// Brute force, every move against every cell, without the sweeps: a ball's straight moves by
    /// the closed-form capsule of each move on its own, other tools' level moves by the exact
    /// distance to the segment, everything else by samples half a pixel apart.
    fn reference(
        target: &HeightMap,
        stock: f64,
        tool: &Tool,
        start: Point3<f64>,
        segs: &[Segment],
    ) -> Vec<f32> {
        let ball = match tool.profile.spec() {
            Some(ToolSpec::Ball { diameter_mm }) => Some(diameter_mm / 2.0),
            _ => None,
        };
        let mut out = vec![stock as f32; target.data().len()];
        let mut lower = |i: usize, z: f64| out[i] = out[i].min(z as f32);
        let cells: Vec<(usize, f64, f64)> = (0..target.height())
            .flat_map(|r| (0..target.width()).map(move |c| (r, c)))
            .map(|(r, c)| {
                let (x, y) = target.cell_center(c, r);
                ((r * target.width() + c) as usize, x, y)
            })
            .collect();
        let point = |q: Point3<f64>, lower: &mut dyn FnMut(usize, f64)| {
            for &(i, x, y) in &cells {
                if let Some(hh) = tool.profile.height_at(((x - q.x).powi(2) + (y - q.y).powi(2)).sqrt()) {
                    lower(i, q.z + hh);
                }
            }
        };
        point(start, &mut lower);
        let mut at = start;
        for seg in segs {
            match (*seg, ball) {
                (Segment::Rapid(to) | Segment::Linear(to) | Segment::Plunge(to), Some(r)) => {
                    for &(i, x, y) in &cells {
                        if let Some(z) = capsule_bottom([x, y], at, to, r) {
                            lower(i, z);
                        }
                    }
                }
                (Segment::Rapid(to) | Segment::Linear(to) | Segment::Plunge(to), None)
                    if (to.z - at.z).abs() < 1e-12 =>
                {
                    for &(i, x, y) in &cells {
                        let d = dist2_to_segment([x, y], [at.x, at.y], [to.x, to.y]).sqrt();
                        if let Some(hh) = tool.profile.height_at(d) {
                            lower(i, at.z + hh);
                        }
                    }
                }
                _ => {
                    let mut samples = Vec::new();
                    sample_segment(at, seg, target.pixel_mm() * SAMPLE_STEP_PX, &mut samples);
                    for q in samples {
                        point(q, &mut lower);
                    }
                }
            }
            at = seg.end();
        }
        out
    }

    /// Dense samples of a ball's straight move: the lowest tool point above each cell.
    fn dense_ball_line(target: &HeightMap, tool: &Tool, a: Point3<f64>, b: Point3<f64>) -> Vec<f64> {
        let mut out = vec![f64::INFINITY; target.data().len()];
        for r in 0..target.height() {
            for c in 0..target.width() {
                let (x, y) = target.cell_center(c, r);
                for k in 0..=400 {
                    let q = a + (b - a) * (f64::from(k) / 400.0);
                    if let Some(hh) = tool.profile.height_at(((x - q.x).powi(2) + (y - q.y).powi(2)).sqrt()) {
                        let i = (r * target.width() + c) as usize;
                        out[i] = out[i].min(q.z + hh);
                    }
                }
            }
        }
        out
    }

    #[test]
    fn a_ball_groove_matches_the_brute_force_and_its_depth() {
        let target = flat_target(60, 40, 0.0);
        let tool = Tool::from_spec(&"ball-2".parse::<ToolSpec>().expect("spec")).expect("tool");
        let start = Point3::new(-1.0, 2.0, 5.0);
        let segs = [
            Segment::Rapid(Point3::new(0.5, 2.0, 5.0)),
            Segment::Plunge(Point3::new(0.5, 2.0, 1.0)),
            Segment::Linear(Point3::new(5.5, 2.0, 1.0)),
            Segment::Arc { end: Point3::new(5.5, 3.0, 1.0), center: [5.5, 2.5], clockwise: false },
            Segment::Rapid(Point3::new(5.5, 3.0, 5.0)),
        ];
        let op = SweptOp { tool: &tool, start, segments: &segs };
        let rep = simulate(&target, 3.0, &[op]).expect("sim");
        let expect = reference(&target, 3.0, &tool, start, &segs);
        for (a, b) in rep.final_surface.data().iter().zip(&expect) {
            assert!((a - b).abs() <= 1e-5, "{a} vs {b}");
        }
        // The groove bottom is the tip's Z where a centre lies on the path.
        let (c, r) = target.cell_of(3.05, 2.05).expect("cell");
        let z = rep.final_surface.get(c, r).expect("z");
        assert!((f64::from(z) - 1.0).abs() < 0.01, "{z}");
        assert_eq!(rep.max_gouge_mm, 0.0);
        assert!((rep.max_leftover_mm - 3.0).abs() < 1e-6);
    }

    #[test]
    fn sloped_ball_moves_take_the_exact_capsule_bottom() {
        let target = flat_target(60, 40, 0.0);
        let tool = Tool::from_spec(&"ball-2".parse::<ToolSpec>().expect("spec")).expect("tool");
        let start = Point3::new(0.5, 1.0, 2.0);
        let segs = [
            Segment::Linear(Point3::new(5.0, 3.0, 0.5)),
            Segment::Linear(Point3::new(1.0, 3.5, 1.5)),
            Segment::Linear(Point3::new(1.0, 3.5, 1.0)),
        ];
        let rep = simulate(&target, 3.0, &[SweptOp { tool: &tool, start, segments: &segs }]).expect("sim");
        let mut dense = vec![f64::INFINITY; target.data().len()];
        let mut at = start;
        for s in &segs {
            for (d, x) in dense.iter_mut().zip(dense_ball_line(&target, &tool, at, s.end())) {
                *d = d.min(x);
            }
            at = s.end();
        }
        for (exact, sampled) in rep.final_surface.data().iter().zip(&dense) {
            let sampled = sampled.min(3.0) as f32;
            // The exact envelope is never above dense samples of it, and barely below them.
            assert!(*exact <= sampled + 1e-5 && sampled - exact <= 0.01, "{exact} vs {sampled}");
        }
        // The closed-form capsule of one move against the same samples.
        let (a, b) = (start, segs[0].end());
        let dense = dense_ball_line(&target, &tool, a, b);
        for r in 0..target.height() {
            for c in 0..target.width() {
                let (x, y) = target.cell_center(c, r);
                let i = (r * target.width() + c) as usize;
                match capsule_bottom([x, y], a, b, 1.0) {
                    Some(z) => assert!(z <= dense[i] + 1e-9 && dense[i] - z <= 0.01, "{z} vs {}", dense[i]),
                    None => assert!(dense[i].is_infinite()),
                }
            }
        }
    }

    /// Random raster passes (a line at any angle, moves up, down, level, backwards and straight
    /// down along it, several passes side by side) against the reference: a ball's runs against
    /// every move's own capsule, other tools' level chords and vertical moves against the exact
    /// distance and samples.
    #[test]
    fn raster_runs_match_each_moves_capsule() {
        use proptest::prelude::*;
        use proptest::test_runner::{Config, TestRunner};
        let mut runner = TestRunner::new(Config { cases: 64, ..Config::default() });
        let strategy = (
            prop_oneof![
                Just(0.0f64),
                Just(std::f64::consts::PI),
                Just(std::f64::consts::FRAC_PI_2),
                0.0f64..std::f64::consts::TAU
            ],
            prop::sample::select(vec![
                "ball-1", "ball-2", "ball-3", "ball-6", "flat-2", "flat-6", "bull-4-1", "v-6-90",
            ]),
            prop::collection::vec((-0.8f64..1.6, -1.5f64..1.5, 0u8..10), 2..40),
            1usize..4,
            0.1f64..1.5,
        );
        runner
            .run(&strategy, |(angle, name, moves, passes, gap)| {
                let target = flat_target(70, 60, 0.0);
                let tool = Tool::from_spec(&name.parse::<ToolSpec>().expect("spec")).expect("tool");
                let (d, n) = ([angle.cos(), angle.sin()], [-angle.sin(), angle.cos()]);
                let mut segs = Vec::new();
                let start = Point3::new(3.5, 3.0, 4.0);
                for k in 0..passes {
                    let o = [3.5 + n[0] * gap * k as f64, 3.0 + n[1] * gap * k as f64];
                    let (mut t, mut z) = (0.0, 1.0);
                    segs.push(Segment::Rapid(Point3::new(o[0], o[1], 4.0)));
                    segs.push(Segment::Plunge(Point3::new(o[0], o[1], z)));
                    for &(dt, dz, kind) in &moves {
                        match kind {
                            0 => z += dz.abs(), // straight down or up only
                            1 | 2 => t += dt,   // level
                            _ => {
                                t += dt;
                                z += dz * 0.5;
                            }
                        }
                        z = z.clamp(-1.0, 3.5);
                        let p = Point3::new(o[0] + d[0] * t, o[1] + d[1] * t, z);
                        segs.push(if kind == 0 { Segment::Plunge(p) } else { Segment::Linear(p) });
                    }
                    segs.push(Segment::Rapid(Point3::new(o[0] + d[0] * t, o[1] + d[1] * t, 4.0)));
                }
                let rep =
                    simulate(&target, 3.0, &[SweptOp { tool: &tool, start, segments: &segs }]).expect("sim");
                let expect = reference(&target, 3.0, &tool, start, &segs);
                for (i, (a, b)) in rep.final_surface.data().iter().zip(&expect).enumerate() {
                    prop_assert!((a - b).abs() <= 2e-5, "cell {i}: {a} vs {b}");
                }
                Ok(())
            })
            .expect("runs equal the capsules");
    }

    #[test]
    fn cutting_below_the_target_is_reported_as_a_gouge_where_it_happens() {
        let target = flat_target(30, 30, 2.0);
        let tool = Tool::from_spec(&"flat-1".parse::<ToolSpec>().expect("spec")).expect("tool");
        let segs = [Segment::Plunge(Point3::new(1.5, 1.5, 1.5))];
        let rep = simulate(
            &target,
            3.0,
            &[SweptOp { tool: &tool, start: Point3::new(1.5, 1.5, 5.0), segments: &segs }],
        )
        .expect("sim");
        assert!((rep.max_gouge_mm - 0.5).abs() < 1e-6, "{}", rep.max_gouge_mm);
        let at = rep.gouge_at_mm.expect("where");
        assert!((at[0] - 1.5).abs() <= 0.5 && (at[1] - 1.5).abs() <= 0.5, "{at:?}");
    }

    #[test]
    fn full_circle_arcs_sweep_all_the_way_round() {
        let mut pts = Vec::new();
        let from = Point3::new(1.0, 0.0, 0.0);
        sample_segment(
            from,
            &Segment::Arc { end: from, center: [0.0, 0.0], clockwise: true },
            0.01,
            &mut pts,
        );
        let len: f64 = std::iter::once(from)
            .chain(pts.iter().copied())
            .collect::<Vec<_>>()
            .windows(2)
            .map(|w| (w[1] - w[0]).norm())
            .sum();
        assert!((len - std::f64::consts::TAU).abs() < 1e-3, "{len}");
    }
}
