//! Camera paths and a headless, real-time runner that measures a [`Session`] along one.
//!
//! A [`Flight`] is a list of legs. Each leg moves the camera linearly from one pose to
//! another (or holds it) for a duration. A leg that starts with a *jump* is timed: the
//! runner records how long the session takes to reach full quality after it (every
//! visible diamond within the tolerance, nothing waiting for data), and may end the leg
//! early once the view has been at full quality for a while.
//!
//! Built-in flights are generated from the repository's world box
//! ([`Session::bounds`], after [`Session::warm_up`]: the heights are a conservative
//! bound on the raster's):
//! - `approach`: from high above the whole raster down to a low, oblique view, with the
//!   altitude falling exponentially over 12 s;
//! - `low-flight`: 30 s at 150 m/s, 300 m above the bound on the highest point, looking
//!   ahead and 20° down;
//! - `jump`: 6 low views at seeded random places and headings, jumping between them.
//!
//! Flights from a file are JSON:
//! `{"legs": [{"duration_s": 5, "from": {"eye": [x, y, z], "target": [x, y, z]},
//! "to": {...}, "jump": true, "settle_s": 0.5}]}` (world metres; `to` absent = hold;
//! `settle_s`: end a jump leg that long after full quality).
//!
//! The runner's own crack and coverage checks (`FlyOptions::check_every`) are not part
//! of what it measures: the flight runs on a clock that stops while a check runs (the
//! camera, the frame schedule, leg durations and times to full quality all use it), and
//! the checks' cost is reported on its own (`check_ms_*`, `wall_seconds`). The network
//! thread does not stop during a check, so answers that arrive meanwhile are on hand at
//! the next frame: on a link that is the bottleneck the flight clock is optimistic by up
//! to the check time. `docs/streaming.md` has the figures.

use std::time::{Duration, Instant};

use glam::DVec3;
use serde::{Deserialize, Serialize};

use quincunx_decoder::incremental::{PlanarRefiner, SphereRefiner};

use crate::domain::{Domain, World};
use crate::session::{CutBlobs, Session, SessionError};
use crate::view::{Aabb, View};

/// Why a flight could not be made.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FlightError {
    /// Not a built-in flight name.
    #[error("unknown flight {0:?} (approach, low-flight, jump, or a JSON file)")]
    Unknown(String),
    /// The flight file is not valid.
    #[error("flight file: {0}")]
    File(String),
    /// The session failed while warming up.
    #[error(transparent)]
    Session(#[from] SessionError),
}

/// A camera position and a point it looks at (world metres).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Eye.
    pub eye: [f64; 3],
    /// Looked-at point.
    pub target: [f64; 3],
}

impl Pose {
    fn lerp(&self, to: &Pose, s: f64) -> Pose {
        let l = |a: [f64; 3], b: [f64; 3]| {
            (DVec3::from_array(a) + (DVec3::from_array(b) - DVec3::from_array(a)) * s).to_array()
        };
        Pose {
            eye: l(self.eye, to.eye),
            target: l(self.target, to.target),
        }
    }
}

/// One leg of a flight.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Leg {
    /// Longest duration, seconds.
    pub duration_s: f64,
    /// Pose at the start.
    pub from: Pose,
    /// Pose at the end (`None`: hold `from`).
    #[serde(default)]
    pub to: Option<Pose>,
    /// The leg starts with a jump: time to full quality is measured.
    #[serde(default)]
    pub jump: bool,
    /// End the leg this long after it reached full quality (jump legs).
    #[serde(default)]
    pub settle_s: Option<f64>,
}

/// A camera path.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Flight {
    /// Name (built-in name or file name).
    #[serde(default)]
    pub name: String,
    /// The legs, in order.
    pub legs: Vec<Leg>,
}

/// Built-in flight names.
pub const BUILTIN: [&str; 3] = ["approach", "low-flight", "jump"];

/// Altitude of the low views above the highest point of the raster (metres).
pub const LOW_ALTITUDE_M: f64 = 300.0;

impl Flight {
    /// A built-in flight over the world box `bounds`; `seed` places the jumps.
    pub fn builtin(name: &str, bounds: Aabb, seed: u64) -> Result<Flight, FlightError> {
        let size = (bounds.max - bounds.min).truncate();
        let centre = (bounds.min + bounds.max) / 2.0;
        let ground = bounds.max.z;
        let at = |fx: f64, fy: f64| bounds.min.truncate() + size * glam::DVec2::new(fx, fy);
        // A low, oblique view at `p` heading `heading` (radians): 20° down.
        let low = |p: glam::DVec2, heading: f64| {
            let eye = p.extend(ground + LOW_ALTITUDE_M);
            let dir = DVec3::new(heading.cos(), heading.sin(), -(20f64.to_radians().tan()));
            Pose {
                eye: eye.to_array(),
                target: (eye + dir * 1_000.0).to_array(),
            }
        };
        let legs = match name {
            "approach" => {
                let span = size.max_element().max(1.0);
                let (high, lowest) = (2.0 * span, LOW_ALTITUDE_M);
                let steps = 24;
                let pose = |k: usize| {
                    let s = k as f64 / steps as f64;
                    let alt = high * (lowest / high).powf(s);
                    // Looking down at the centre from the south, steeply at first.
                    let eye = centre.truncate() - glam::DVec2::new(0.0, 0.3 * alt + 1_000.0 * s);
                    Pose {
                        eye: eye.extend(ground + alt).to_array(),
                        target: centre.truncate().extend(ground).to_array(),
                    }
                };
                (0..steps)
                    .map(|k| Leg {
                        duration_s: 12.0 / steps as f64,
                        from: pose(k),
                        to: Some(pose(k + 1)),
                        jump: false,
                        settle_s: None,
                    })
                    .chain(std::iter::once(Leg {
                        duration_s: 3.0,
                        from: pose(steps),
                        to: None,
                        jump: false,
                        settle_s: None,
                    }))
                    .collect()
            }
            "low-flight" => {
                let (a, b) = (at(0.25, 0.3), at(0.75, 0.7));
                let heading = (b - a).y.atan2((b - a).x);
                let dir = (b - a).normalize_or_zero();
                let len = (150.0 * 30.0f64).min((b - a).length());
                vec![Leg {
                    duration_s: len / 150.0,
                    from: low(a, heading),
                    to: Some(low(a + dir * len, heading)),
                    jump: false,
                    settle_s: None,
                }]
            }
            "jump" => {
                let mut rng = SplitMix(seed);
                (0..6)
                    .map(|_| Leg {
                        duration_s: 10.0,
                        from: low(
                            at(0.1 + 0.8 * rng.unit(), 0.1 + 0.8 * rng.unit()),
                            rng.unit() * std::f64::consts::TAU,
                        ),
                        to: None,
                        jump: true,
                        settle_s: Some(0.5),
                    })
                    .collect()
            }
            other => return Err(FlightError::Unknown(other.to_string())),
        };
        Ok(Flight {
            name: name.to_string(),
            legs,
        })
    }

    /// A built-in flight over what `session` streams. Warms the session up first (the
    /// root refined, so its height bounds are conservative and low views stay above the
    /// highest point), for at most 10 s.
    pub fn builtin_for<R: BuiltinFlights>(
        name: &str,
        session: &mut Session<R>,
        seed: u64,
    ) -> Result<Flight, FlightError> {
        if !BUILTIN.contains(&name) {
            return Err(FlightError::Unknown(name.to_string()));
        }
        if !session.warm_up(Duration::from_secs(10))? {
            tracing::warn!("the root did not arrive within 10 s: heights bounded by its grid only");
        }
        R::builtin(name, session, seed)
    }

    /// A built-in flight over a planet: `approach` from two radii above the surface down
    /// to a low view; `low-flight` 30 s at 150 m/s along a great circle; `jump` between
    /// 6 low views at seeded places on the whole planet. Low views are
    /// [`LOW_ALTITUDE_M`] above a conservative bound on the heights around them
    /// ([`Session::height_range_near`]), 20° down, with `up` away from the centre.
    pub fn builtin_planet(
        name: &str,
        session: &Session<SphereRefiner>,
        seed: u64,
    ) -> Result<Flight, FlightError> {
        let radius = session.world().radius_m;
        let ground = |d: DVec3| radius + session.height_range_near(d).1;
        // East and north at direction d (any tangent pair at the poles).
        let frame = |d: DVec3| {
            let east = DVec3::Z.cross(d).try_normalize().unwrap_or(DVec3::Y);
            (east, d.cross(east))
        };
        let low = |d: DVec3, heading: f64, r: f64| {
            let (east, north) = frame(d);
            let eye = d * (r + LOW_ALTITUDE_M);
            let ahead = east * heading.cos() + north * heading.sin();
            let dir = ahead - d * 20f64.to_radians().tan();
            Pose {
                eye: eye.to_array(),
                target: (eye + dir * 1_000.0).to_array(),
            }
        };
        let mut rng = SplitMix(seed);
        let mut place = || {
            // Uniform on the sphere.
            let z = 2.0 * rng.unit() - 1.0;
            let lon = rng.unit() * std::f64::consts::TAU;
            let r = (1.0 - z * z).max(0.0).sqrt();
            (DVec3::new(r * lon.cos(), r * lon.sin(), z), rng.unit())
        };
        let legs = match name {
            "approach" => {
                let (d, _) = place();
                let r0 = ground(d);
                let (north, steps) = (frame(d).1, 24);
                let (high, lowest) = (2.0 * radius, LOW_ALTITUDE_M);
                let pose = |k: usize| {
                    let s = k as f64 / steps as f64;
                    let alt = high * (lowest / high).powf(s);
                    // Looking at the place from the south, steeply at first.
                    let eye = d * (r0 + alt) - north * (0.3 * alt + 1_000.0 * s);
                    Pose {
                        eye: eye.to_array(),
                        target: (d * r0).to_array(),
                    }
                };
                (0..steps)
                    .map(|k| (12.0 / steps as f64, pose(k), Some(pose(k + 1))))
                    .chain(std::iter::once((3.0, pose(steps), None)))
                    .map(|(duration_s, from, to)| Leg {
                        duration_s,
                        from,
                        to,
                        jump: false,
                        settle_s: None,
                    })
                    .collect()
            }
            "low-flight" => {
                let (d, h) = place();
                let heading = h * std::f64::consts::TAU;
                let (east, north) = frame(d);
                let axis = d.cross(east * heading.cos() + north * heading.sin());
                // 1 s legs along the great circle: the chords stay within 0.5 mm of it.
                let at = |t: f64| {
                    let q = glam::DQuat::from_axis_angle(axis, 150.0 * t / radius);
                    q * d
                };
                let r = (0..=30)
                    .map(|t| ground(at(f64::from(t))))
                    .fold(radius, f64::max);
                (0..30)
                    .map(|t| {
                        let (a, b) = (at(f64::from(t)), at(f64::from(t + 1)));
                        let tangent = |p: DVec3| {
                            let (e, n) = frame(p);
                            let fwd = axis.cross(p);
                            fwd.dot(n).atan2(fwd.dot(e))
                        };
                        Leg {
                            duration_s: 1.0,
                            from: low(a, tangent(a), r),
                            to: Some(low(b, tangent(b), r)),
                            jump: false,
                            settle_s: None,
                        }
                    })
                    .collect()
            }
            "jump" => (0..6)
                .map(|_| {
                    let (d, h) = place();
                    Leg {
                        duration_s: 10.0,
                        from: low(d, h * std::f64::consts::TAU, ground(d)),
                        to: None,
                        jump: true,
                        settle_s: Some(0.5),
                    }
                })
                .collect(),
            other => return Err(FlightError::Unknown(other.to_string())),
        };
        Ok(Flight {
            name: name.to_string(),
            legs,
        })
    }

    /// A flight from its JSON text.
    pub fn from_json(name: &str, text: &str) -> Result<Flight, FlightError> {
        let mut f: Flight =
            serde_json::from_str(text).map_err(|e| FlightError::File(e.to_string()))?;
        if f.legs.is_empty() {
            return Err(FlightError::File("no legs".into()));
        }
        for (i, leg) in f.legs.iter().enumerate() {
            let finite = |p: &Pose| p.eye.iter().chain(&p.target).all(|v| v.is_finite());
            let ok = leg.duration_s.is_finite()
                && leg.duration_s > 0.0
                && finite(&leg.from)
                && leg.to.as_ref().is_none_or(finite)
                && leg.settle_s.is_none_or(|s| s.is_finite() && s >= 0.0);
            if !ok {
                return Err(FlightError::File(format!(
                    "leg {i}: durations must be positive and coordinates finite"
                )));
            }
        }
        if f.name.is_empty() {
            f.name = name.to_string();
        }
        Ok(f)
    }

    /// Longest total duration, seconds.
    pub fn duration_s(&self) -> f64 {
        self.legs.iter().map(|l| l.duration_s).sum()
    }
}

/// A tiny deterministic generator (SplitMix64) for jump places.
struct SplitMix(u64);

impl SplitMix {
    fn unit(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// How a flight is run.
#[derive(Clone, Copy, Debug)]
pub struct FlyOptions {
    /// Frames per second the loop aims at (it never runs ahead of real time).
    pub fps: f64,
    /// Refinement budget per frame.
    pub frame_budget: Duration,
    /// Viewport, pixels.
    pub viewport_px: [u32; 2],
    /// Vertical field of view, radians.
    pub fov_y_rad: f64,
    /// Screen-space tolerance, pixels.
    pub tolerance_px: f64,
    /// Check the cut for cracks and coverage every this many frames (0 = never).
    pub check_every: usize,
    /// Largest share of the flight's time the checks may take: a frame due for a check
    /// is skipped while the checks so far exceed `share x` the flight clock, so the run
    /// takes at most about `1 + share` times the flight in wall-clock time. `None`: check
    /// every due frame, whatever it costs (a korea cut at 1 px costs 0.2-0.4 s).
    pub check_max_share: Option<f64>,
    /// Test hook: extra time each check takes (sleeps), to show that checks are kept off
    /// the flight's clock. Zero in real use.
    pub check_delay: Duration,
}

impl Default for FlyOptions {
    fn default() -> Self {
        FlyOptions {
            fps: 60.0,
            frame_budget: Duration::from_millis(4),
            viewport_px: [1920, 1080],
            fov_y_rad: 60f64.to_radians(),
            tolerance_px: 1.0,
            check_every: 1,
            check_max_share: None,
            check_delay: Duration::ZERO,
        }
    }
}

/// One frame of a flight.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct FrameRecord {
    /// Seconds since the flight started, on the flight clock (checks excluded).
    pub t_s: f64,
    /// Leg index.
    pub leg: usize,
    /// `Session::update` time, milliseconds.
    pub update_ms: f64,
    /// Refinement time within it, milliseconds.
    pub refine_ms: f64,
    /// Halves in the cut.
    pub cut_halves: usize,
    /// Diamonds in the DAG.
    pub dag_nodes: usize,
    /// Refined and coarsened this frame.
    pub refined: usize,
    /// Coarsened this frame.
    pub coarsened: usize,
    /// Diamonds waiting for data.
    pub pending: usize,
    /// Keys submitted as wanted.
    pub wanted: usize,
    /// Keys submitted as prefetch.
    pub prefetched: usize,
    /// Largest projected error of a visible diamond still wanting refinement.
    pub max_error_px: f64,
    /// Full quality (see `FrameStats::full_quality`).
    pub full_quality: bool,
    /// Cracks found (when checked).
    pub cracks: usize,
    /// Coverage errors (uncovered + overlapping probes) found (when checked).
    pub coverage_errors: usize,
    /// Time the check of this frame took, milliseconds (0 when not checked); not on the
    /// flight clock.
    pub check_ms: f64,
    /// Body bytes fetched so far.
    pub bytes_fetched: u64,
    /// Requests outstanding, and how many the bandwidth estimate allows.
    pub in_flight: usize,
    /// Allowed outstanding.
    pub window: usize,
    /// Estimated delivered rate, bit/s.
    pub bandwidth_bit_s: f64,
}

/// Time to full quality after one jump.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct JumpResult {
    /// Leg index.
    pub leg: usize,
    /// Seconds from the jump to the first frame at full quality; `None` if the leg
    /// ended first. Where a budget (the DAG's memory, or the cut a renderer's GPU pool
    /// holds) keeps the view from the tolerance, to the first frame at the best quality
    /// the budgets allow (refinement converged under them; `budget_limited`).
    pub time_to_full_quality_s: Option<f64>,
    /// The budgets, not the tolerance, ended refinement: the view was drawn coarser
    /// than the tolerance asks.
    pub budget_limited: bool,
    /// Body bytes fetched during the leg until then (or the leg's end).
    pub bytes_fetched: u64,
}

/// What a flight measured. Field names are those of `quincunx fly --json`.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FlightReport {
    /// Flight name.
    pub flight: String,
    /// Transport used.
    pub transport: String,
    /// Tolerance, pixels.
    pub tolerance_px: f64,
    /// Frames run.
    pub frames: usize,
    /// Seconds flown, on the flight clock: wall time less the runner's checks.
    pub seconds: f64,
    /// `frames / seconds`: the frame rate the session kept up (checks excluded).
    pub frames_per_s: f64,
    /// Wall-clock seconds of the whole run, checks included.
    pub wall_seconds: f64,
    /// Per jump leg.
    pub jumps: Vec<JumpResult>,
    /// Median and largest time to full quality over the jumps that reached it.
    pub time_to_full_quality_s_p50: Option<f64>,
    /// Largest.
    pub time_to_full_quality_s_max: Option<f64>,
    /// Jumps that never reached full quality within their leg.
    pub jumps_unfinished: usize,
    /// Jumps whose time is to the best quality the budgets allow, not to the tolerance
    /// ([`JumpResult::budget_limited`]).
    pub jumps_budget_limited: usize,
    /// Body bytes fetched (prefetch included).
    pub bytes_fetched: u64,
    /// Of them, the colour layer's (0 without one).
    pub colour_bytes_fetched: u64,
    /// Of them, what was not a blob or package (both layers): opening repository files
    /// and reading their directories, gaps and checksums between coalesced blobs (range
    /// reads; 0 from a server).
    pub overhead_bytes: u64,
    /// Body bytes of the distinct blobs of the final cuts: the cut at the last frame of
    /// each leg ([`Session::cut_blobs`]), united over the legs.
    pub bytes_in_final_cuts: u64,
    /// Body bytes of the distinct blobs refinement used at any time of the flight (the
    /// final cuts' and those of every cut on the way).
    pub bytes_used_any_cut: u64,
    /// `bytes_fetched / bytes_in_final_cuts`.
    pub fetch_waste: f64,
    /// The view of the last frame of each leg (in leg order; a leg that ran no frame has
    /// none).
    #[serde(skip)]
    pub final_views: Vec<View>,
    /// The final cuts' blobs, united.
    #[serde(skip)]
    pub final_blobs: CutBlobs,
    /// Requests written (retries included).
    pub requests: u64,
    /// Answers that were empty (diamonds without a blob).
    pub leaves: u64,
    /// Fetch failures reported to the session.
    pub failures: u64,
    /// Errors counted by the network thread (each failed attempt).
    pub fetch_errors: u64,
    /// Of those, attempts that timed out: no progress within the timeout, or no whole
    /// answer within the request deadline.
    pub fetch_timeouts: u64,
    /// Halves in the cut per frame: median and largest.
    pub diamonds_per_frame_p50: usize,
    /// Largest.
    pub diamonds_per_frame_max: usize,
    /// Refinement time per frame, milliseconds.
    pub refine_ms_p50: f64,
    /// 99th percentile.
    pub refine_ms_p99: f64,
    /// Whole `update` time per frame (polling and submitting included), median.
    pub update_ms_p50: f64,
    /// 99th percentile.
    pub update_ms_p99: f64,
    /// Frames whose cut was checked.
    pub frames_checked: usize,
    /// Time spent in the checks, milliseconds: in all (not on the flight clock), the
    /// median and the largest per checked frame.
    pub check_ms_total: f64,
    /// Median per checked frame.
    pub check_ms_p50: f64,
    /// Largest.
    pub check_ms_max: f64,
    /// Cracks over all checked frames (must be 0).
    pub cracks: usize,
    /// Uncovered or doubly covered probes over all checked frames (must be 0).
    pub coverage_errors: usize,
    /// Largest DAG memory, bytes.
    pub dag_bytes_max: usize,
}

/// Percentile of a sorted slice (nearest rank).
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// Flies `flight` with `session` in real time, calling `on_frame` after every frame.
pub fn fly<R: Domain>(
    session: &mut Session<R>,
    flight: &Flight,
    opts: &FlyOptions,
    mut on_frame: impl FnMut(&FrameRecord),
) -> Result<FlightReport, SessionError> {
    fly_with(session, flight, opts, |_, _, rec| on_frame(rec))
}

/// [`fly`] with the session and the frame's view handed to `on_frame` after each update
/// (a renderer draws there; its time is on the flight clock, as a real frame's would be).
pub fn fly_with<R: Domain>(
    session: &mut Session<R>,
    flight: &Flight,
    opts: &FlyOptions,
    mut on_frame: impl FnMut(&mut Session<R>, &View, &FrameRecord),
) -> Result<FlightReport, SessionError> {
    let start = Instant::now();
    // The flight clock: wall time since `start` less the time spent checking.
    let mut checking = Duration::ZERO;
    let clock = |checking: Duration| start.elapsed().saturating_sub(checking);
    let mut check_ms = Vec::new();
    let period = Duration::from_secs_f64(1.0 / opts.fps.max(1.0));
    let mut report = FlightReport {
        flight: flight.name.clone(),
        transport: String::new(),
        tolerance_px: opts.tolerance_px,
        ..FlightReport::default()
    };
    let (mut refine_ms, mut update_ms, mut halves) = (Vec::new(), Vec::new(), Vec::new());
    let mut frame_no = 0usize;
    for (li, leg) in flight.legs.iter().enumerate() {
        let mut last_view: Option<View> = None;
        let leg_start = clock(checking);
        let bytes_at_start = session.fetch_stats().bytes_fetched;
        let mut full_at: Option<Duration> = None;
        let mut jump = leg.jump.then_some(JumpResult {
            leg: li,
            time_to_full_quality_s: None,
            budget_limited: false,
            bytes_fetched: 0,
        });
        loop {
            let now = clock(checking);
            let t_leg = now.saturating_sub(leg_start).as_secs_f64();
            if t_leg >= leg.duration_s {
                break;
            }
            let pose = match &leg.to {
                Some(to) => leg.from.lerp(to, t_leg / leg.duration_s),
                None => leg.from,
            };
            let view = View {
                eye: DVec3::from_array(pose.eye),
                target: DVec3::from_array(pose.target),
                up: session.world().up(DVec3::from_array(pose.eye)),
                fov_y_rad: opts.fov_y_rad,
                viewport_px: opts.viewport_px,
                tolerance_px: opts.tolerance_px,
            };
            let frame = session.update(&view, now, opts.frame_budget)?;
            let fetch = session.fetch_stats();
            let mut rec = FrameRecord {
                t_s: now.as_secs_f64(),
                leg: li,
                update_ms: frame.elapsed.as_secs_f64() * 1e3,
                refine_ms: frame.refine.elapsed.as_secs_f64() * 1e3,
                cut_halves: frame.refine.cut_halves,
                dag_nodes: frame.refine.dag_nodes,
                refined: frame.refine.refined,
                coarsened: frame.refine.coarsened,
                pending: frame.refine.pending,
                wanted: frame.wanted,
                prefetched: frame.prefetched,
                max_error_px: frame.refine.max_error_px,
                full_quality: frame.refine.full_quality,
                cracks: 0,
                coverage_errors: 0,
                check_ms: 0.0,
                bytes_fetched: fetch.bytes_fetched,
                in_flight: fetch.in_flight,
                window: fetch.window,
                bandwidth_bit_s: fetch.bandwidth_bit_s,
            };
            let within_share = opts.check_max_share.is_none_or(|share| {
                checking.as_secs_f64() <= share * clock(checking).as_secs_f64()
            });
            if opts.check_every > 0 && frame_no.is_multiple_of(opts.check_every) && within_share {
                let check_started = Instant::now();
                let check = session.dag().check_cut();
                if !opts.check_delay.is_zero() {
                    std::thread::sleep(opts.check_delay);
                }
                let took = check_started.elapsed();
                checking += took;
                rec.check_ms = took.as_secs_f64() * 1e3;
                check_ms.push(rec.check_ms);
                // Height and colour cracks alike.
                rec.cracks = check.cracks + check.colour_cracks;
                rec.coverage_errors = check.uncovered + check.overlaps;
                report.frames_checked += 1;
                report.cracks += rec.cracks;
                report.coverage_errors += rec.coverage_errors;
            }
            if frame_no.is_multiple_of(16) {
                // A pass over the DAG: sampled.
                report.dag_bytes_max = report.dag_bytes_max.max(session.dag().memory_bytes());
            }
            refine_ms.push(rec.refine_ms);
            update_ms.push(rec.update_ms);
            halves.push(rec.cut_halves as f64);
            frame_no += 1;
            last_view = Some(view);
            on_frame(session, &view, &rec);
            // As good as it gets: the tolerance met, or the budgets reached.
            let mut leg_done = false;
            if frame.refine.settled() {
                let at = *full_at.get_or_insert(now);
                if let Some(j) = jump.as_mut()
                    && j.time_to_full_quality_s.is_none()
                {
                    j.time_to_full_quality_s = Some(t_leg);
                    j.budget_limited = !rec.full_quality;
                    j.bytes_fetched = fetch.bytes_fetched - bytes_at_start;
                }
                leg_done = leg
                    .settle_s
                    .is_some_and(|s| now.saturating_sub(at).as_secs_f64() >= s);
            } else {
                full_at = None;
            }
            // The next frame: no earlier than one period after this one started, also
            // when the leg ends here (the frame stays on screen for its period, so the
            // frame rate never exceeds `fps`).
            let next = now + period;
            let after = clock(checking);
            if next > after {
                std::thread::sleep(next - after);
            }
            if leg_done {
                break;
            }
        }
        if let Some(view) = last_view {
            // The leg's final cut: noted off the flight clock, like the checks.
            let noting = Instant::now();
            report.final_blobs.extend(&session.cut_blobs());
            report.final_views.push(view);
            checking += noting.elapsed();
        }
        if let Some(mut j) = jump {
            if j.time_to_full_quality_s.is_none() {
                j.bytes_fetched = session.fetch_stats().bytes_fetched - bytes_at_start;
                report.jumps_unfinished += 1;
            }
            if j.budget_limited {
                report.jumps_budget_limited += 1;
            }
            report.jumps.push(j);
        }
    }
    let fetch = session.fetch_stats();
    report.frames = frame_no;
    report.wall_seconds = start.elapsed().as_secs_f64();
    report.seconds = clock(checking).as_secs_f64();
    report.frames_per_s = if report.seconds > 0.0 {
        frame_no as f64 / report.seconds
    } else {
        0.0
    };
    report.check_ms_total = checking.as_secs_f64() * 1e3;
    check_ms.sort_by(f64::total_cmp);
    report.check_ms_p50 = percentile(&check_ms, 0.5);
    report.check_ms_max = check_ms.last().copied().unwrap_or(0.0);
    report.bytes_fetched = fetch.bytes_fetched;
    report.colour_bytes_fetched = session.colour_fetch_stats().map_or(0, |c| c.bytes_fetched);
    report.overhead_bytes = fetch.overhead_bytes;
    report.bytes_in_final_cuts = session.blob_bytes(&report.final_blobs);
    report.bytes_used_any_cut = session.bytes_used();
    report.fetch_waste = if report.bytes_in_final_cuts > 0 {
        report.bytes_fetched as f64 / report.bytes_in_final_cuts as f64
    } else {
        0.0
    };
    report.requests = fetch.requests;
    report.leaves = fetch.leaves;
    report.failures = session.failures();
    report.fetch_errors = fetch.errors.total();
    report.fetch_timeouts = fetch.errors.timeout;
    let mut ttfq: Vec<f64> = report
        .jumps
        .iter()
        .filter_map(|j| j.time_to_full_quality_s)
        .collect();
    ttfq.sort_by(f64::total_cmp);
    report.time_to_full_quality_s_p50 = (!ttfq.is_empty()).then(|| percentile(&ttfq, 0.5));
    report.time_to_full_quality_s_max = ttfq.last().copied();
    for v in [&mut refine_ms, &mut update_ms, &mut halves] {
        v.sort_by(f64::total_cmp);
    }
    report.refine_ms_p50 = percentile(&refine_ms, 0.5);
    report.refine_ms_p99 = percentile(&refine_ms, 0.99);
    report.update_ms_p50 = percentile(&update_ms, 0.5);
    report.update_ms_p99 = percentile(&update_ms, 0.99);
    report.diamonds_per_frame_p50 = percentile(&halves, 0.5) as usize;
    report.diamonds_per_frame_max = halves.last().copied().unwrap_or(0.0) as usize;
    report.transport = session_transport(session);
    Ok(report)
}

/// What the views of a flight needed: see [`needed_for_views`].
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct NeededSet {
    /// Body bytes of the union of the views' blob sets.
    pub bytes: u64,
    /// Blobs in the union.
    pub blobs: usize,
    /// Per view.
    pub views: Vec<NeededView>,
    /// The union.
    #[serde(skip)]
    pub set: CutBlobs,
}

/// One view's smallest cut that meets the tolerance.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct NeededView {
    /// Whether the cut reached full quality (every visible diamond within the tolerance,
    /// nothing waiting) before the timeout.
    pub full_quality: bool,
    /// Largest projected error of a visible diamond still wanting refinement (px).
    pub max_error_px: f64,
    /// Halves in the cut.
    pub cut_halves: usize,
    /// Blobs and their body bytes.
    pub blobs: usize,
    /// Body bytes.
    pub bytes: u64,
}

/// The smallest set of blobs whose cuts meet the tolerance of each of `views`: for each
/// view, a fresh session from `open` refines it until full quality (or `timeout`), and
/// the blobs of its cut ([`Session::cut_blobs`]) are added to the union. Refinement
/// refines a diamond only when its projected error is above the tolerance (and the 4-8
/// rule asks for its parents first), so a fresh session's cut is the coarsest that meets
/// the tolerance, and its blobs the fewest that can give it. Open the sessions without
/// prefetch, look-ahead or packages (they would fetch more, not use more) and against
/// the data without an emulated link: only what is used is counted, but time is wasted.
pub fn needed_for_views<R: Domain>(
    mut open: impl FnMut() -> Result<Session<R>, SessionError>,
    views: &[View],
    timeout: Duration,
) -> Result<NeededSet, SessionError> {
    let mut needed = NeededSet::default();
    for view in views {
        let mut session = open()?;
        let start = Instant::now();
        let frame = loop {
            let frame = session.update(view, start.elapsed(), Duration::from_millis(50))?;
            if frame.refine.settled() || start.elapsed() >= timeout {
                break frame;
            }
            if frame.refine.refined == 0 {
                std::thread::sleep(Duration::from_millis(2));
            }
        };
        let blobs = session.cut_blobs();
        let new = CutBlobs {
            elevation: blobs
                .elevation
                .difference(&needed.set.elevation)
                .copied()
                .collect(),
            colour: blobs
                .colour
                .difference(&needed.set.colour)
                .copied()
                .collect(),
        };
        needed.bytes += session.blob_bytes(&new);
        needed.set.extend(&blobs);
        needed.views.push(NeededView {
            full_quality: frame.refine.full_quality,
            max_error_px: frame.refine.max_error_px,
            cut_halves: frame.refine.cut_halves,
            blobs: blobs.len(),
            bytes: session.blob_bytes(&blobs),
        });
    }
    needed.blobs = needed.set.len();
    Ok(needed)
}

/// Domains with built-in flights.
pub trait BuiltinFlights: Domain {
    /// The built-in flight `name` over what `session` streams (warmed up).
    fn builtin(name: &str, session: &Session<Self>, seed: u64) -> Result<Flight, FlightError>;
}

impl BuiltinFlights for PlanarRefiner {
    fn builtin(name: &str, session: &Session<Self>, seed: u64) -> Result<Flight, FlightError> {
        Flight::builtin(name, session.bounds(), seed)
    }
}

impl BuiltinFlights for SphereRefiner {
    fn builtin(name: &str, session: &Session<Self>, seed: u64) -> Result<Flight, FlightError> {
        Flight::builtin_planet(name, session, seed)
    }
}

fn session_transport<R: Domain>(session: &Session<R>) -> String {
    session.config().transport.name().to_string()
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn bounds() -> Aabb {
        Aabb {
            min: DVec3::new(0.0, 0.0, -10.0),
            max: DVec3::new(100_000.0, 50_000.0, 2_000.0),
        }
    }

    #[test]
    fn builtin_flights_stay_over_the_raster_and_above_its_highest_point() {
        for name in BUILTIN {
            let f = Flight::builtin(name, bounds(), 5).unwrap();
            assert!(!f.legs.is_empty() && f.duration_s() > 0.0, "{name}");
            for leg in &f.legs {
                for p in std::iter::once(&leg.from).chain(leg.to.as_ref()) {
                    assert!(p.eye[2] >= 2_000.0 + LOW_ALTITUDE_M - 1e-6, "{name}: {p:?}");
                    assert!((-1e4..=1.1e5).contains(&p.eye[0]), "{name}: {p:?}");
                    assert!(p.eye != p.target, "{name}");
                }
            }
        }
        let jump = Flight::builtin("jump", bounds(), 5).unwrap();
        assert!(jump.legs.iter().all(|l| l.jump && l.to.is_none()));
        // Seeded: the same places for the same seed, others for another.
        assert_eq!(jump, Flight::builtin("jump", bounds(), 5).unwrap());
        assert_ne!(jump, Flight::builtin("jump", bounds(), 6).unwrap());
        assert!(matches!(
            Flight::builtin("orbit", bounds(), 0),
            Err(FlightError::Unknown(_))
        ));
    }

    #[test]
    fn flight_files_are_checked() {
        let ok =
            r#"{"legs": [{"duration_s": 2, "from": {"eye": [0, 0, 10], "target": [1, 1, 0]}}]}"#;
        let f = Flight::from_json("f.json", ok).unwrap();
        assert_eq!(
            (f.name.as_str(), f.legs.len(), f.duration_s()),
            ("f.json", 1, 2.0)
        );
        for bad in [
            "",
            "{}",
            r#"{"legs": []}"#,
            r#"{"legs": [{"duration_s": 0, "from": {"eye": [0, 0, 10], "target": [1, 1, 0]}}]}"#,
            r#"{"legs": [{"duration_s": 1, "from": {"eye": [0, 0, 1e999], "target": [1, 1, 0]}}]}"#,
            r#"{"legs": [{"duration_s": 1, "from": {"eye": [0, 0], "target": [1, 1, 0]}}]}"#,
            r#"{"legs": [{"duration_s": 1, "settle_s": -1, "from": {"eye": [0, 0, 1], "target": [1, 1, 0]}}]}"#,
        ] {
            assert!(Flight::from_json("x", bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn poses_interpolate_linearly() {
        let a = Pose {
            eye: [0.0, 0.0, 100.0],
            target: [10.0, 0.0, 0.0],
        };
        let b = Pose {
            eye: [100.0, 0.0, 300.0],
            target: [110.0, 0.0, 0.0],
        };
        let m = a.lerp(&b, 0.5);
        assert_eq!(m.eye, [50.0, 0.0, 200.0]);
        assert_eq!(m.target, [60.0, 0.0, 0.0]);
    }
}
