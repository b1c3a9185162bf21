//! Realistic request streams: what a view-dependent client asks for while a camera flies
//! over the domain.
//!
//! At each camera step the client walks the diamond hierarchy from the roots, coarse to fine
//! (breadth first), and refines a diamond while its distance to the camera is below
//! [`FlightPlan::refine_factor`] times its size and its level is below `levels - 1`. Each
//! diamond is requested once per flight (the client's cache), and always after its parents
//! (a diamond is synthesised from both parents, so a client needs them first). The camera
//! flies low: straight segments between random points of the square (planar), great-circle
//! arcs between random directions mapped onto the cube (sphere).
//!
//! Streams are deterministic functions of the plan and the seed.

use std::collections::{HashSet, VecDeque};
use std::hash::Hash;
use std::io::Write as _;

use quincunx_codec::diamond::sphere::unit_sphere_to_cube;
use quincunx_codec::diamond::{IdError, PlanarDomain, PlanarId, SphereDomain, SphereId};
use quincunx_store::Metadata;

/// Why a stream cannot be planned.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FlightError {
    /// The domain parameters are invalid.
    #[error("invalid domain: {0}")]
    Domain(#[from] IdError),
    /// The repository has no levels.
    #[error("the repository has no levels")]
    NoLevels,
}

/// The domain a stream is generated for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Geometry {
    /// The square `[0, 2^m]^2`.
    Planar(PlanarDomain),
    /// The cube surface `[-2^m, 2^m]^3`.
    Sphere(SphereDomain),
}

/// How streams are generated.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlightPlan {
    /// The domain.
    pub geometry: Geometry,
    /// Levels that carry blobs (`0 .. levels`); refinement stops at `levels - 1`.
    pub levels: u32,
    /// A diamond is refined while its distance to the camera is below this times its size.
    pub refine_factor: f64,
    /// Camera steps of one flight (the flight may end earlier, see `max_requests`).
    pub max_steps: usize,
    /// Longest stream, in requests.
    pub max_requests: usize,
}

/// Default [`FlightPlan::refine_factor`]: deep enough that a few hundred steps reach the
/// deepest level over thousands of requests, shallow enough that far terrain stays coarse.
pub const REFINE_FACTOR: f64 = 3.0;

impl FlightPlan {
    /// The default plan for a repository: 400 steps, at most `max_requests` requests.
    pub fn for_metadata(meta: &Metadata, max_requests: usize) -> Result<FlightPlan, FlightError> {
        let geometry = match meta.domain {
            quincunx_store::Domain::Planar => Geometry::Planar(PlanarDomain::new(meta.m)?),
            quincunx_store::Domain::Sphere => Geometry::Sphere(SphereDomain::new(meta.m)?),
        };
        if meta.levels == 0 {
            return Err(FlightError::NoLevels);
        }
        Ok(FlightPlan {
            geometry,
            levels: meta.levels,
            refine_factor: REFINE_FACTOR,
            max_steps: 400,
            max_requests,
        })
    }

    /// The stream of one flight: diamond centres in request order.
    pub fn generate(&self, seed: u64) -> Stream {
        let mut rng = Rng::new(seed);
        match self.geometry {
            Geometry::Planar(d) => {
                let camera = PlanarCamera::new(&d, self.deepest_size(), &mut rng);
                fly(self, &PlanarSpace(d), camera, rng)
            }
            Geometry::Sphere(d) => {
                let camera = SphereCamera::new(&d, self.deepest_size(), &mut rng);
                fly(self, &SphereSpace(d), camera, rng)
            }
        }
    }

    /// Size (id units) of a diamond of `level`: the root's side halves every two levels.
    fn level_size(&self, level: u32) -> f64 {
        let root = match self.geometry {
            Geometry::Planar(d) => d.size() as f64,
            Geometry::Sphere(d) => 2.0 * d.size() as f64,
        };
        root * (-(level as f64) / 2.0).exp2()
    }

    fn deepest_size(&self) -> f64 {
        self.level_size(self.levels - 1)
    }
}

/// A request stream: the centres of the requested diamonds as URL path suffixes
/// (`x/y` planar, `x/y/z` sphere, as `quincunx export` names the files).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Stream {
    text: Vec<u8>,
    ends: Vec<u32>,
}

impl Stream {
    /// Number of requests.
    pub fn len(&self) -> usize {
        self.ends.len()
    }

    /// Whether the stream has no request.
    pub fn is_empty(&self) -> bool {
        self.ends.is_empty()
    }

    /// The path suffix of request `i` (panics if `i >= len`, like slice indexing).
    pub fn get(&self, i: usize) -> &[u8] {
        let start = if i == 0 { 0 } else { self.ends[i - 1] as usize };
        &self.text[start..self.ends[i] as usize]
    }

    /// All path suffixes in order.
    pub fn iter(&self) -> impl Iterator<Item = &[u8]> + '_ {
        (0..self.len()).map(|i| self.get(i))
    }

    fn push(&mut self, write: impl FnOnce(&mut Vec<u8>)) {
        write(&mut self.text);
        self.ends.push(self.text.len() as u32);
    }
}

/// The hierarchy operations a flight needs, for either domain.
trait Space {
    type Id: Copy + Eq + Hash;
    fn roots(&self) -> Vec<Self::Id>;
    fn children(&self, id: Self::Id) -> Vec<Self::Id>;
    fn parents(&self, id: Self::Id) -> Vec<Self::Id>;
    fn level(&self, id: Self::Id) -> u32;
    fn position(&self, id: Self::Id) -> [f64; 3];
    fn write(&self, id: Self::Id, out: &mut Vec<u8>);
}

struct PlanarSpace(PlanarDomain);

// Ids reaching these methods come from `roots`/`children`/`parents`, so they are valid;
// the fallbacks only keep the generator total.
impl Space for PlanarSpace {
    type Id = PlanarId;
    fn roots(&self) -> Vec<PlanarId> {
        vec![self.0.root()]
    }
    fn children(&self, id: PlanarId) -> Vec<PlanarId> {
        self.0.children(id).unwrap_or_default()
    }
    fn parents(&self, id: PlanarId) -> Vec<PlanarId> {
        self.0.parents(id).unwrap_or_default()
    }
    fn level(&self, id: PlanarId) -> u32 {
        self.0.level(id).unwrap_or(u32::MAX)
    }
    fn position(&self, id: PlanarId) -> [f64; 3] {
        [id.x as f64, id.y as f64, 0.0]
    }
    fn write(&self, id: PlanarId, out: &mut Vec<u8>) {
        let _ = write!(out, "{}/{}", id.x, id.y);
    }
}

struct SphereSpace(SphereDomain);

impl Space for SphereSpace {
    type Id = SphereId;
    fn roots(&self) -> Vec<SphereId> {
        self.0.roots().to_vec()
    }
    fn children(&self, id: SphereId) -> Vec<SphereId> {
        self.0.children(id).unwrap_or_default()
    }
    fn parents(&self, id: SphereId) -> Vec<SphereId> {
        self.0.parents(id).unwrap_or_default()
    }
    fn level(&self, id: SphereId) -> u32 {
        self.0.level(id).unwrap_or(u32::MAX)
    }
    fn position(&self, id: SphereId) -> [f64; 3] {
        id.c.map(|v| v as f64)
    }
    fn write(&self, id: SphereId, out: &mut Vec<u8>) {
        let [x, y, z] = id.c;
        let _ = write!(out, "{x}/{y}/{z}");
    }
}

/// A camera path: one position (id units) per step.
trait Camera {
    fn step(&mut self, rng: &mut Rng) -> [f64; 3];
}

/// Straight segments between random points of the square, at a low altitude.
struct PlanarCamera {
    side: f64,
    pos: [f64; 2],
    target: [f64; 2],
    speed: f64,
    altitude: f64,
}

impl PlanarCamera {
    fn new(d: &PlanarDomain, deepest: f64, rng: &mut Rng) -> Self {
        let side = d.size() as f64;
        PlanarCamera {
            side,
            pos: [rng.unit() * side, rng.unit() * side],
            target: [rng.unit() * side, rng.unit() * side],
            speed: deepest,
            altitude: deepest / 2.0,
        }
    }
}

impl Camera for PlanarCamera {
    fn step(&mut self, rng: &mut Rng) -> [f64; 3] {
        let (dx, dy) = (self.target[0] - self.pos[0], self.target[1] - self.pos[1]);
        let left = dx.hypot(dy);
        if left <= self.speed {
            self.pos = self.target;
            self.target = [rng.unit() * self.side, rng.unit() * self.side];
        } else {
            self.pos[0] += dx / left * self.speed;
            self.pos[1] += dy / left * self.speed;
        }
        [self.pos[0], self.pos[1], self.altitude]
    }
}

/// Great-circle arcs between random directions, mapped onto the cube surface (equal-angle
/// map), at a low altitude.
struct SphereCamera {
    half_side: f64,
    dir: [f64; 3],
    target: [f64; 3],
    /// Arc advanced per step, in radians.
    speed: f64,
    altitude: f64,
}

impl SphereCamera {
    fn new(d: &SphereDomain, deepest: f64, rng: &mut Rng) -> Self {
        let half_side = d.size() as f64;
        // A face (2S id units) spans a quarter turn.
        let speed = deepest * std::f64::consts::FRAC_PI_2 / (2.0 * half_side);
        SphereCamera {
            half_side,
            dir: rng.direction(),
            target: rng.direction(),
            speed,
            altitude: deepest / 2.0,
        }
    }
}

impl Camera for SphereCamera {
    fn step(&mut self, rng: &mut Rng) -> [f64; 3] {
        let (a, b) = (self.dir, self.target);
        let cos = dot(a, b).clamp(-1.0, 1.0);
        let left = cos.acos();
        let w = [b[0] - cos * a[0], b[1] - cos * a[1], b[2] - cos * a[2]];
        let wn = dot(w, w).sqrt();
        if left <= self.speed || wn < 1e-12 {
            self.dir = b;
            self.target = rng.direction();
        } else {
            let (s, c) = self.speed.sin_cos();
            self.dir = normalise([
                c * a[0] + s * w[0] / wn,
                c * a[1] + s * w[1] / wn,
                c * a[2] + s * w[2] / wn,
            ]);
        }
        let cube = unit_sphere_to_cube(self.dir);
        let scale = self.half_side + self.altitude;
        cube.map(|v| v * scale)
    }
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn normalise(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    if n > 0.0 {
        a.map(|v| v / n)
    } else {
        [1.0, 0.0, 0.0]
    }
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    dot(d, d).sqrt()
}

/// Flies `camera` and records the requests of every step's cut.
fn fly<S: Space>(plan: &FlightPlan, space: &S, mut camera: impl Camera, mut rng: Rng) -> Stream {
    let mut stream = Stream::default();
    let mut seen: HashSet<S::Id> = HashSet::new();
    let mut visited: HashSet<S::Id> = HashSet::new();
    let mut queue: VecDeque<S::Id> = VecDeque::new();
    let sizes: Vec<f64> = (0..plan.levels).map(|l| plan.level_size(l)).collect();
    for _ in 0..plan.max_steps {
        let eye = camera.step(&mut rng);
        visited.clear();
        queue.clear();
        queue.extend(space.roots());
        while let Some(id) = queue.pop_front() {
            if !visited.insert(id) {
                continue;
            }
            request(space, id, &mut seen, &mut stream);
            if stream.len() >= plan.max_requests {
                stream.ends.truncate(plan.max_requests);
                return stream;
            }
            let level = space.level(id);
            if level + 1 < plan.levels
                && distance(eye, space.position(id)) < plan.refine_factor * sizes[level as usize]
            {
                queue.extend(space.children(id));
            }
        }
    }
    stream
}

/// Requests `id` unless already requested, its missing ancestors first.
fn request<S: Space>(space: &S, id: S::Id, seen: &mut HashSet<S::Id>, stream: &mut Stream) {
    if seen.contains(&id) {
        return;
    }
    for p in space.parents(id) {
        request(space, p, seen, stream);
    }
    seen.insert(id);
    stream.push(|out| space.write(id, out));
}

/// SplitMix64: small, fast, good enough for camera paths, and stable across releases.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    /// A generator from a seed.
    pub fn new(seed: u64) -> Self {
        Rng(seed)
    }

    /// The seed of client `index` of a run seeded with `seed`.
    pub fn client_seed(seed: u64, index: u64) -> u64 {
        Rng(seed ^ index.wrapping_mul(0xA076_1D64_78BD_642F)).next_u64()
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// A uniformly distributed unit vector.
    fn direction(&mut self) -> [f64; 3] {
        loop {
            let v = [
                2.0 * self.unit() - 1.0,
                2.0 * self.unit() - 1.0,
                2.0 * self.unit() - 1.0,
            ];
            let n = dot(v, v);
            if n > 1e-6 && n <= 1.0 {
                return normalise(v);
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn plan(geometry: Geometry, levels: u32) -> FlightPlan {
        FlightPlan {
            geometry,
            levels,
            refine_factor: REFINE_FACTOR,
            max_steps: 400,
            max_requests: 20_000,
        }
    }

    fn numbers(s: &[u8]) -> Vec<i64> {
        std::str::from_utf8(s)
            .unwrap()
            .split('/')
            .map(|t| t.parse().unwrap())
            .collect()
    }

    /// Checks validity, uniqueness and parent order; returns the level histogram.
    fn check_planar(d: PlanarDomain, stream: &Stream, levels: u32) -> Vec<usize> {
        let mut index = HashMap::new();
        let mut per_level = vec![0; levels as usize];
        for (i, s) in stream.iter().enumerate() {
            let [x, y] = numbers(s)[..] else {
                panic!("{s:?}")
            };
            let id = PlanarId::new(x, y);
            let level = d.level(id).expect("every URL is a valid centre");
            assert!(level < levels, "{id:?} level {level}");
            per_level[level as usize] += 1;
            for p in d.parents(id).unwrap() {
                let j = index.get(&p).expect("parents are requested first");
                assert!(*j < i);
            }
            assert!(index.insert(id, i).is_none(), "{id:?} requested twice");
        }
        per_level
    }

    fn check_sphere(d: SphereDomain, stream: &Stream, levels: u32) -> Vec<usize> {
        let mut index = HashMap::new();
        let mut per_level = vec![0; levels as usize];
        for (i, s) in stream.iter().enumerate() {
            let [x, y, z] = numbers(s)[..] else {
                panic!("{s:?}")
            };
            let id = SphereId::new([x, y, z]);
            let level = d.level(id).expect("every URL is a valid centre");
            assert!(level < levels, "{id:?} level {level}");
            per_level[level as usize] += 1;
            for p in d.parents(id).unwrap() {
                let j = index.get(&p).expect("parents are requested first");
                assert!(*j < i);
            }
            assert!(index.insert(id, i).is_none(), "{id:?} requested twice");
        }
        per_level
    }

    #[test]
    fn planar_flights_are_valid_ordered_and_reach_the_deepest_level() {
        let d = PlanarDomain::new(14).unwrap();
        let p = plan(Geometry::Planar(d), 16);
        for seed in 0..3 {
            let s = p.generate(seed);
            let per_level = check_planar(d, &s, 16);
            assert!(s.len() >= 2000, "{} requests", s.len());
            assert!(per_level[15] > 0, "{per_level:?}");
            assert_eq!(numbers(s.get(0)), vec![1 << 13, 1 << 13], "root first");
        }
    }

    #[test]
    fn sphere_flights_are_valid_ordered_and_reach_the_deepest_level() {
        let d = SphereDomain::new(8).unwrap();
        let p = plan(Geometry::Sphere(d), 14);
        for seed in 0..3 {
            let s = p.generate(seed);
            let per_level = check_sphere(d, &s, 14);
            assert!(s.len() >= 2000, "{} requests", s.len());
            assert!(per_level[13] > 0, "{per_level:?}");
            assert_eq!(per_level[0], 6, "every face root");
        }
    }

    #[test]
    fn flights_are_deterministic_per_seed() {
        let p = plan(Geometry::Planar(PlanarDomain::new(12).unwrap()), 14);
        assert_eq!(p.generate(7), p.generate(7));
        assert_ne!(p.generate(7), p.generate(8));
        let p = plan(Geometry::Sphere(SphereDomain::new(6).unwrap()), 12);
        assert_eq!(p.generate(7), p.generate(7));
        assert_ne!(p.generate(7), p.generate(8));
        assert_ne!(Rng::client_seed(1, 0), Rng::client_seed(1, 1));
        assert_ne!(Rng::client_seed(1, 0), Rng::client_seed(2, 0));
    }

    #[test]
    fn a_small_repository_is_exhausted_and_the_cap_holds() {
        // Levels 0..3 of a planar domain hold 1 + 4 + 4 + 12 diamonds at most.
        let p = plan(Geometry::Planar(PlanarDomain::new(4).unwrap()), 4);
        let s = p.generate(1);
        check_planar(PlanarDomain::new(4).unwrap(), &s, 4);
        assert!(s.len() <= 21);
        let mut capped = plan(Geometry::Planar(PlanarDomain::new(14).unwrap()), 16);
        capped.max_requests = 100;
        assert_eq!(capped.generate(3).len(), 100);
    }
}
