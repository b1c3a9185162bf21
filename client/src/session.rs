//! A streaming session: one served elevation repository (planar or planet) and,
//! optionally, a colour repository matched to it ([`Session::open_with_colour`], see
//! [`crate::colour`]), with their DAG, refinement and data access layers, driven one frame
//! at a time. [`Session`] is planar by default; [`PlanetSession`] streams planets (the
//! world is then centred on the planet). [`quincunx_meta::Metadata::domain`] says which
//! one a repository needs.
//!
//! ```no_run
//! use std::time::{Duration, Instant};
//! use glam::DVec3;
//! use quincunx_client::session::{Session, SessionConfig};
//! use quincunx_client::view::View;
//!
//! let mut session: Session =
//!     Session::open("http://127.0.0.1:8080", "korea", SessionConfig::default())?;
//! let start = Instant::now();
//! let b = session.bounds();
//! let view = View {
//!     eye: DVec3::new(b.min.x, b.min.y, b.max.z + 2_000.0),
//!     target: (b.min + b.max) / 2.0,
//!     up: DVec3::Z,
//!     fov_y_rad: 60f64.to_radians(),
//!     viewport_px: [1920, 1080],
//!     tolerance_px: 1.0,
//! };
//! loop {
//!     let frame = session.update(&view, start.elapsed(), Duration::from_millis(4))?;
//!     // Draw `session.dag().cut()` here.
//!     if frame.refine.converged {
//!         break;
//!     }
//!     std::thread::sleep(Duration::from_millis(16));
//! }
//! # Ok::<(), quincunx_client::session::SessionError>(())
//! ```
//!
//! Each [`Session::update`]:
//! 1. takes what the network thread delivered since the last frame;
//! 2. runs [`Refinement::update`] within the budget. Details come from what arrived or
//!    from the fetcher's decoded cache; everything else the frame wanted is collected
//!    with its priority (projected error; parents above their children);
//! 3. submits those wants (which replace the previous frame's) and, a few times a
//!    second, prefetch keys for the camera predicted [`SessionConfig::prefetch_ahead`]
//!    ahead; the network thread requests prefetch keys only when every wanted key is in
//!    flight and the bandwidth allows more.
//!
//! The frame never waits for the network: a diamond whose details have not arrived stays
//! unrefined and the cut stays consistent (crack-free) whatever arrives when.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::Bytes;
use glam::DVec3;
use quincunx_decoder::diamond::PlanarId;
use quincunx_decoder::incremental::{Details, PlanarRefiner, Procedural, Refiner, SphereRefiner};
use quincunx_meta::Metadata;
use quincunx_meta::answer;

use crate::colour::{ColourDetails, ColourLayer};
use crate::dag::Dag;
use crate::domain::Domain;
use crate::fetch::{
    Decoded, FetchConfig, FetchStats, Fetched, Fetcher, Key, Remote, Transport, Unpack, Weigh, lock,
};
use crate::refine::{
    Arrival, Availability, DetailSource, FrameStats, RefineConfig, Refinement, SystemClock,
};
use crate::view::{Aabb, PlanarWorld, View};

pub use crate::dag::{Patch, PatchChanges};
use crate::open::metadata_error;
pub use crate::open::{
    EARTH_RADIUS_M, SessionError, planar_channel_refiner, planar_refiner, planar_world,
    sphere_channel_refiner, sphere_refiner, sphere_world,
};

/// Settings of a [`Session`]. `Default` gives pipelined HTTP/1.1, 2 connections, a
/// 64 MiB decoded cache and prefetch half a second ahead.
#[derive(Clone, Debug)]
pub struct SessionConfig {
    /// How blobs travel.
    pub transport: Transport,
    /// Persistent connections (pipelined and plain).
    pub connections: usize,
    /// Requests outstanding per pipelined connection.
    pub pipeline_depth: usize,
    /// Requests outstanding in total, whatever the bandwidth estimate allows.
    pub max_in_flight: usize,
    /// Optional cap on the blob request rate, bit/s.
    pub bandwidth_cap_bit_s: Option<f64>,
    /// Byte budget of the decoded-details cache (per layer: a colour layer has its own).
    pub cache_bytes: usize,
    /// Refinement tuning.
    pub refine: RefineConfig,
    /// How far ahead the camera is predicted for prefetching; zero disables prefetch.
    pub prefetch_ahead: Duration,
    /// How often the predicted camera is evaluated (it costs a pass over the DAG).
    pub prefetch_every: Duration,
    /// Most prefetch keys submitted at once.
    pub prefetch_max: usize,
    /// Levels below each wanted diamond whose blobs are requested ahead (as prefetch)
    /// while the wanted diamond's projected error says they will be wanted too (about
    /// `error / sqrt(2)^depth` above the tolerance). This hides the round trip per level
    /// a view would otherwise pay on its way down; 0 disables it. See also
    /// [`SessionConfig::lookahead_min_blobs`].
    pub lookahead_levels: usize,
    /// No lookahead while one round trip of the link (estimated bandwidth x RTT) carries
    /// fewer than this many mean-sized blobs and the link queues (answers take more than
    /// 1.25 times the RTT): on such a link the bandwidth, not the round trips, bounds how fast
    /// a view fills, and lookahead answers would only queue ahead of wanted ones.
    pub lookahead_min_blobs: f64,
    /// Metres between samples; `None` derives it from the metadata's georeference
    /// (latitude/longitude grids on a sphere of [`EARTH_RADIUS_M`]; projected grids in
    /// their units) and falls back to 1 m.
    pub spacing_m: Option<f64>,
    /// Timeout of the metadata request (the whole exchange) and progress timeout of each
    /// blob request ([`crate::fetch::FetchConfig::request_timeout`]).
    pub timeout: Duration,
    /// Overall deadline of each blob request, however steadily its bytes come
    /// ([`crate::fetch::FetchConfig::request_deadline`], default 30 s).
    pub request_deadline: Duration,
    /// With a colour layer, the details made up below the shallower layer's finest level
    /// so the DAG refines to the deeper one's (zero: smooth interpolation).
    pub procedural: Procedural,
    /// Ask for packages (a blob with its small owned children's, for repositories with an
    /// inlining limit) where the diamond's children and grandchildren will want refining
    /// too: projected error at least `package_factor x tolerance`. `None`: bare blobs
    /// only. The default, 2, is where the grandchildren's error (about half the
    /// diamond's) still exceeds the tolerance. With a 300-byte limit, 1 or sqrt(2)
    /// fetched 1.28 or 1.19 times what the planet's jump flight used, 2 1.10
    /// (`docs/streaming.md`, "Packages").
    pub package_factor: Option<f64>,
    /// How to reach the server beyond its URL: an extra trusted CA for `https://` (PEM,
    /// besides the system's roots) and an address to connect to instead of the host's.
    pub connect: crate::fetch::tls::ConnectOptions,
}

impl Default for SessionConfig {
    fn default() -> Self {
        SessionConfig {
            transport: Transport::Pipelined,
            connections: 2,
            pipeline_depth: 128,
            max_in_flight: 256,
            bandwidth_cap_bit_s: None,
            cache_bytes: 64 << 20,
            refine: RefineConfig::default(),
            prefetch_ahead: Duration::from_millis(500),
            prefetch_every: Duration::from_millis(100),
            prefetch_max: 1024,
            lookahead_levels: 2,
            lookahead_min_blobs: 32.0,
            spacing_m: None,
            timeout: Duration::from_secs(10),
            request_deadline: crate::fetch::DEFAULT_REQUEST_DEADLINE,
            procedural: Procedural::Zero,
            package_factor: Some(2.0),
            connect: crate::fetch::tls::ConnectOptions::default(),
        }
    }
}

/// What one [`Session::update`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SessionFrame {
    /// The refinement's statistics.
    pub refine: FrameStats,
    /// Keys wanted and not here (submitted to the network thread).
    pub wanted: usize,
    /// Prefetch keys submitted this frame.
    pub prefetched: usize,
    /// Keys whose fetch failed since the last frame (they are asked for again).
    pub failed: usize,
    /// The whole update, including polling and submitting.
    pub elapsed: Duration,
}

/// What a renderer reads after a frame: the cut as patches, with the mapping to metres.
/// Neighbouring patches agree bit for bit on shared edges, so drawing them as they are
/// gives a surface without cracks or T-junctions.
#[derive(Clone, Debug)]
pub struct Snapshot<I = PlanarId, W = PlanarWorld> {
    /// Diamond size `N` (each grid is `(N+1)^2`).
    pub n: usize,
    /// Ids and integer samples to metres.
    pub world: W,
    /// The cut, in a stable order.
    pub patches: Vec<Patch<I>>,
    /// Colour diamond size `Nc` (0 without a colour layer).
    pub colour_n: usize,
}

/// A colour layer and its data access.
type ColourStream<R> = (
    Arc<ColourLayer<R>>,
    Layer<ColourDetails<<R as Refiner>::Id>>,
);

/// One layer's data access: its repository, network thread and what it delivered.
struct Layer<T> {
    name: String,
    remote: Remote,
    meta: Metadata,
    fetcher: Fetcher<T>,
    /// Body bytes of each fetched blob (written on the network thread).
    blob_bytes: Arc<Mutex<HashMap<Key, u32>>>,
    /// Delivered since the last frame.
    arrived: HashMap<Key, Option<Arc<T>>>,
    /// Diamonds refined with a blob at least once (for waste accounting).
    used: HashSet<Key>,
    /// Diamonds known to have no blob without asking: a diamond without a blob has no
    /// descendant with one (docs/blob-format.md), so the children of a leaf are leaves;
    /// and a blob flags its owned children that have none.
    inferred_leaves: HashSet<Key>,
    /// Wanted this frame, with priorities.
    wants: HashMap<Key, f64>,
    /// How the repository's packages carry small owned children, if it serves any.
    packing: Option<Packing>,
}

/// How a repository's answers carry small owned children (`quincunx_meta::answer`).
#[derive(Clone, Debug)]
struct Packing {
    domain: answer::IdSpace,
    levels: u32,
    /// Per level: whether its blobs are small enough, on average, to be carried by their
    /// owners' answers (mean blob at most the inlining limit).
    carried: Vec<bool>,
}

impl Packing {
    fn of(meta: &Metadata) -> Result<Option<Packing>, String> {
        let Some(limit) = meta.inline_max_bytes else {
            return Ok(None);
        };
        let mut carried = vec![false; meta.levels as usize];
        for s in &meta.level_stats {
            if let Some(c) = carried.get_mut(s.level as usize) {
                *c = s.blobs > 0 && s.bytes <= u64::from(limit) * s.blobs;
            }
        }
        Ok(Some(Packing {
            domain: answer::IdSpace::of(meta)?,
            levels: meta.levels,
            carried,
        }))
    }

    /// Whether `key` is likely to arrive inside its owner's answer.
    fn likely_carried(&self, key: Key) -> bool {
        self.domain
            .level(key)
            .is_ok_and(|l| self.carried.get(l as usize).copied().unwrap_or(false))
    }

    /// Splits the answer of `key` into its own value and the carried owned descendants
    /// (decoded).
    fn unpack<T, D: Fn(Key, &[u8]) -> Result<T, String>>(
        &self,
        key: Key,
        bytes: &[u8],
        decode: &D,
        carried: &mut Vec<(Key, T)>,
    ) -> Result<T, String> {
        let parsed = answer::parse(bytes, true).map_err(|e| e.to_string())?;
        let value = decode(key, parsed.blob)?;
        if parsed.children.is_empty() {
            return Ok(value);
        }
        let level = self.domain.level(key)?;
        if level + 1 >= self.levels {
            return Err(format!("a level {level} answer carries children"));
        }
        let owned = self.domain.owned_children(key)?;
        for &(i, bytes) in &parsed.children {
            let &child = owned
                .get(i)
                .ok_or_else(|| format!("carries owned child {i} of {}", owned.len()))?;
            let v = self.unpack(child, bytes, decode, carried)?;
            carried.push((child, v));
        }
        Ok(value)
    }
}

impl<T: Weigh + Send + Sync + 'static> Layer<T> {
    /// Starts the network thread of repository `remote` whose blobs `decode` decodes.
    fn spawn(
        remote: Remote,
        meta: Metadata,
        config: &SessionConfig,
        decode: impl Fn(Key, &[u8]) -> Result<T, String> + Send + Sync + 'static,
    ) -> Result<Layer<T>, SessionError> {
        let blob_bytes: Arc<Mutex<HashMap<Key, u32>>> = Arc::default();
        let packing = Packing::of(&meta).map_err(|e| metadata_error(&remote.name, e))?;
        let decode: Unpack<T> = {
            let sizes = Arc::clone(&blob_bytes);
            let decode = move |key: Key, bytes: &[u8]| {
                lock(&sizes).insert(key, u32::try_from(bytes.len()).unwrap_or(u32::MAX));
                decode(key, bytes)
            };
            let packing = packing.clone();
            Arc::new(move |key: Key, bytes: Bytes, packaged: bool| {
                let Some(packing) = packing.as_ref().filter(|_| packaged) else {
                    return Ok(Decoded {
                        value: decode(key, &bytes)?,
                        carried: Vec::new(),
                    });
                };
                let mut carried = Vec::new();
                let value = packing.unpack(key, &bytes, &decode, &mut carried)?;
                Ok(Decoded { value, carried })
            })
        };
        let mut fetch = FetchConfig::new(remote.clone());
        fetch.transport = config.transport;
        fetch.connections = config.connections.max(1);
        fetch.pipeline_depth = config.pipeline_depth.max(1);
        fetch.max_in_flight = config.max_in_flight.max(1);
        fetch.bandwidth_cap_bit_s = config.bandwidth_cap_bit_s;
        fetch.cache_bytes = config.cache_bytes;
        fetch.request_timeout = config.timeout;
        fetch.request_deadline = config.request_deadline;
        let fetcher = Fetcher::spawn_unpacking(fetch, decode)?;
        Ok(Layer {
            name: remote.name.clone(),
            remote,
            meta,
            fetcher,
            blob_bytes,
            arrived: HashMap::new(),
            used: HashSet::new(),
            inferred_leaves: HashSet::new(),
            wants: HashMap::new(),
            packing,
        })
    }

    /// Takes what the network thread delivered; returns the failures.
    fn poll(&mut self) -> usize {
        let mut failed = 0;
        for (key, fetched) in self.fetcher.poll() {
            match fetched {
                Fetched::Data(d) => {
                    self.arrived.insert(key, Some(d));
                }
                Fetched::Leaf => {
                    self.arrived.insert(key, None);
                }
                Fetched::Failed(e) => {
                    tracing::debug!(repo = %self.name, ?key, error = %e, "fetch failed");
                    failed += 1;
                }
            }
        }
        failed
    }

    fn is_leaf(&self, key: Key) -> bool {
        self.inferred_leaves.contains(&key) || self.fetcher.is_leaf(key)
    }

    /// The data of `key` if it is here (`Some(None)`: a leaf, zero details); `parents`
    /// gives its parents' keys, asked only when nothing else answers (a leaf's children
    /// are leaves).
    fn lookup(&mut self, key: Key, parents: impl FnOnce() -> Vec<Key>) -> Option<Option<Arc<T>>> {
        if let Some(d) = self.arrived.get(&key) {
            return Some(d.clone());
        }
        if self.is_leaf(key) {
            return Some(None);
        }
        if let Some(d) = self.fetcher.cached(key) {
            return Some(Some(d));
        }
        if parents().into_iter().any(|p| self.is_leaf(p)) {
            self.inferred_leaves.insert(key);
            return Some(None);
        }
        None
    }

    /// The data of `key` for refinement: marks it used and learns its empty children
    /// (`empty`), or records it as wanted.
    fn take(
        &mut self,
        key: Key,
        priority: f64,
        parents: impl FnOnce() -> Vec<Key>,
        empty: impl FnOnce(&T) -> Vec<Key>,
    ) -> Arrival<T> {
        match self.lookup(key, parents) {
            Some(d) => {
                if let Some(data) = &d {
                    self.used.insert(key);
                    self.inferred_leaves.extend(empty(data));
                }
                Arrival::Ready(d)
            }
            None => {
                self.record(key, priority);
                Arrival::Pending
            }
        }
    }

    /// Wants `key`: asks for the answer likely to carry it (see [`Layer::route`]).
    fn record(&mut self, key: Key, priority: f64) {
        let key = self.route(key);
        let p = self.wants.entry(key).or_insert(priority);
        *p = p.max(priority);
    }

    /// The key to ask for to get `key`: while a key is likely carried by its owner's
    /// answer and that answer has not come, the owner; else the key itself (its owner's
    /// answer came without it, or it is not likely carried).
    fn route(&self, key: Key) -> Key {
        let Some(packing) = &self.packing else {
            return key;
        };
        let mut at = key;
        while packing.likely_carried(at) {
            let Ok(Some(owner)) = packing.domain.owner(at) else {
                break;
            };
            if self.fetcher.contains(owner) || self.is_leaf(owner) {
                break;
            }
            at = owner;
        }
        at
    }

    /// The priority (projected error) from which this layer asks for packages.
    fn package_above(&self, factor: Option<f64>, tolerance_px: f64) -> Option<f32> {
        let factor = factor.filter(|_| self.packing.is_some())?;
        Some((factor * tolerance_px) as f32)
    }

    /// Keys to prefetch for `ahead`: routed (see [`Layer::route`]), each once, skipping
    /// known leaves.
    fn prefetch_keys(&self, ahead: impl Iterator<Item = (Key, f32)>) -> Vec<(Key, f32)> {
        let mut out: Vec<(Key, f32)> = Vec::new();
        let mut seen = HashSet::new();
        for (key, p) in ahead {
            let key = self.route(key);
            if !self.is_leaf(key) && seen.insert(key) {
                out.push((key, p));
            }
        }
        out
    }

    /// Body bytes of the distinct blobs refinement used.
    fn bytes_used(&self) -> u64 {
        let sizes = lock(&self.blob_bytes);
        self.used
            .iter()
            .map(|k| u64::from(sizes.get(k).copied().unwrap_or(0)))
            .sum()
    }
}

/// A set of blobs by layer (see [`Session::cut_blobs`]).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct CutBlobs {
    /// Keys of elevation blobs.
    pub elevation: HashSet<Key>,
    /// Keys of colour blobs.
    pub colour: HashSet<Key>,
}

impl CutBlobs {
    /// Adds `other`'s blobs.
    pub fn extend(&mut self, other: &CutBlobs) {
        self.elevation.extend(other.elevation.iter().copied());
        self.colour.extend(other.colour.iter().copied());
    }

    /// Blobs in all.
    pub fn len(&self) -> usize {
        self.elevation.len() + self.colour.len()
    }

    /// No blob.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether every blob of `other` is in this set.
    pub fn contains_all(&self, other: &CutBlobs) -> bool {
        other.elevation.is_subset(&self.elevation) && other.colour.is_subset(&self.colour)
    }
}

/// A planet streamed from a server.
pub type PlanetSession = Session<SphereRefiner>;

/// A session of the domain the repository's metadata names.
pub enum AnySession {
    /// A planar repository.
    Planar(Session<PlanarRefiner>),
    /// A planet.
    Planet(PlanetSession),
}

impl AnySession {
    /// Opens repository `name` at `base_url` as a planar or planet session, as its
    /// metadata says.
    pub fn open(
        base_url: &str,
        name: &str,
        config: SessionConfig,
    ) -> Result<AnySession, SessionError> {
        AnySession::open_with_colour(base_url, name, None, config)
    }

    /// [`AnySession::open`] with an optional colour repository matched to it.
    pub fn open_with_colour(
        base_url: &str,
        name: &str,
        colour: Option<&str>,
        config: SessionConfig,
    ) -> Result<AnySession, SessionError> {
        let (remote, meta) = Remote::open_with(base_url, name, config.timeout, &config.connect)?;
        let colour = colour
            .map(|c| Remote::open_with(base_url, c, config.timeout, &config.connect))
            .transpose()?;
        Ok(if meta.domain == SphereRefiner::KIND {
            AnySession::Planet(Session::with_layers(remote, meta, colour, config)?)
        } else {
            AnySession::Planar(Session::with_layers(remote, meta, colour, config)?)
        })
    }
}

/// An elevation repository streamed from a server (planar unless `R` says otherwise).
pub struct Session<R: Domain = PlanarRefiner> {
    world: R::World,
    refiner: Arc<R>,
    dag: Dag<R>,
    refinement: Refinement<R::Id>,
    config: SessionConfig,
    /// The elevation repository's data access.
    elevation: Layer<Details<R::Id>>,
    /// The colour layer (matched to the elevation) and its data access.
    colour: Option<ColourStream<R>>,
    /// Camera motion, for prediction.
    camera: CameraTrack,
    last_prefetch: Option<Duration>,
    failures: u64,
    /// The conservative lowest height went into the world mapping.
    lowest_known: bool,
    /// The highest delivered rate estimated so far (bit/s).
    peak_bandwidth_bit_s: f64,
}

impl<R: Domain> Session<R> {
    /// Opens repository `name` served at `base_url` (`http://host[:port][/prefix]`):
    /// fetches its metadata once and starts the network thread.
    pub fn open(
        base_url: &str,
        name: &str,
        config: SessionConfig,
    ) -> Result<Session<R>, SessionError> {
        let (remote, meta) = Remote::open_with(base_url, name, config.timeout, &config.connect)?;
        Session::with_metadata(remote, meta, config)
    }

    /// Starts a session on a repository whose metadata is already known.
    pub fn with_metadata(
        remote: Remote,
        meta: Metadata,
        config: SessionConfig,
    ) -> Result<Session<R>, SessionError> {
        Session::with_layers(remote, meta, None, config)
    }

    /// Opens elevation repository `name` with colour repository `colour` (both served at
    /// `base_url`), matched at run time ([`ColourLayer::match_to`]).
    pub fn open_with_colour(
        base_url: &str,
        name: &str,
        colour: &str,
        config: SessionConfig,
    ) -> Result<Session<R>, SessionError> {
        let (remote, meta) = Remote::open_with(base_url, name, config.timeout, &config.connect)?;
        let colour = Remote::open_with(base_url, colour, config.timeout, &config.connect)?;
        Session::with_layers(remote, meta, Some(colour), config)
    }

    /// Starts a session on an elevation repository and, optionally, a colour repository
    /// whose metadata are already known.
    pub fn with_layers(
        remote: Remote,
        meta: Metadata,
        colour: Option<(Remote, Metadata)>,
        config: SessionConfig,
    ) -> Result<Session<R>, SessionError> {
        let name = remote.name.clone();
        let (refiner, world) = R::from_metadata(&name, &meta, config.spacing_m)?;
        let (refiner, colour) = match colour {
            Some((colour_remote, colour_meta)) => {
                let (refiner, layer) = ColourLayer::match_to(
                    refiner,
                    &meta,
                    &colour_remote.name,
                    &colour_meta,
                    config.procedural,
                )?;
                (refiner, Some((Arc::new(layer), colour_remote, colour_meta)))
            }
            None => (refiner, None),
        };
        let refiner = Arc::new(refiner);
        let elevation = {
            let refiner = Arc::clone(&refiner);
            Layer::spawn(remote, meta, &config, move |key, bytes| {
                refiner
                    .decode(R::id_of(key), bytes)
                    .map_err(|e| e.to_string())
            })?
        };
        let colour = match colour {
            Some((layer, remote, meta)) => {
                let decoder = Arc::clone(&layer);
                let stream = Layer::spawn(remote, meta, &config, move |key, bytes| {
                    decoder.decode(R::id_of(key), bytes)
                })?;
                Some((layer, stream))
            }
            None => None,
        };
        Ok(Session {
            world,
            dag: Dag::with_colour(
                Arc::clone(&refiner),
                colour.as_ref().map(|(layer, _)| Arc::clone(layer)),
            ),
            refiner,
            refinement: Refinement::with_config(config.refine),
            config,
            elevation,
            colour,
            camera: CameraTrack::default(),
            last_prefetch: None,
            failures: 0,
            lowest_known: false,
            peak_bandwidth_bit_s: 0.0,
        })
    }

    /// The settings it was opened with.
    pub fn config(&self) -> &SessionConfig {
        &self.config
    }

    /// Sets the most halves the cut may hold ([`RefineConfig::max_cut_halves`]): a
    /// renderer passes the patches its GPU pool holds.
    pub fn set_max_cut_halves(&mut self, max: Option<usize>) {
        self.refinement.config.max_cut_halves = max;
        self.config.refine.max_cut_halves = max;
    }

    /// The most halves the cut may hold, if bounded.
    pub fn max_cut_halves(&self) -> Option<usize> {
        self.refinement.config.max_cut_halves
    }

    /// Repository name.
    pub fn name(&self) -> &str {
        &self.elevation.name
    }

    /// The colour repository's name and metadata, with a colour layer.
    pub fn colour(&self) -> Option<(&str, &Metadata)> {
        self.colour
            .as_ref()
            .map(|(_, l)| (l.name.as_str(), &l.meta))
    }

    /// Where the blobs come from.
    pub fn remote(&self) -> &Remote {
        &self.elevation.remote
    }

    /// The repository's metadata.
    pub fn metadata(&self) -> &Metadata {
        &self.elevation.meta
    }

    /// How ids and integer samples map to world metres.
    pub fn world(&self) -> R::World {
        self.world
    }

    /// The DAG: the current cut ([`Dag::cut`]) is what a renderer draws.
    pub fn dag(&self) -> &Dag<R> {
        &self.dag
    }

    /// The current cut for a renderer.
    pub fn snapshot(&self) -> Snapshot<R::Id, R::World> {
        let patches = self
            .dag
            .cut()
            .into_iter()
            .filter_map(|(id, half)| self.dag.patch(id, half))
            .collect();
        Snapshot {
            n: self.refiner.n(),
            world: self.world,
            patches,
            colour_n: self.dag.colour().map_or(0, ColourLayer::n),
        }
    }

    /// How the cut changed since the previous call, with the patches that entered (the
    /// first call reports the whole cut): what a retained-mode renderer uploads and frees
    /// each frame, in time proportional to the changes ([`Dag::take_cut_changes`]).
    pub fn cut_changes(&mut self) -> PatchChanges<R::Id> {
        self.dag.take_patch_changes()
    }

    /// Makes the next [`Session::cut_changes`] report the whole cut again.
    pub fn restart_cut_changes(&mut self) {
        self.dag.restart_cut_changes();
    }

    /// A conservative range of the surface's heights (metres): over the cut, each
    /// unrefined diamond's grid range widened by the bound its parent's blob carries for
    /// its whole subtree. Conservative once every cut diamond's bound is known, which is
    /// the case as soon as the roots are refined ([`Session::warm_up`]); before that it is
    /// the root grids' range only, and real peaks may rise above it.
    pub fn height_range(&self) -> (f64, f64) {
        self.height_range_where(|_| true)
    }

    /// [`Session::height_range`] over the cut diamonds `keep` accepts.
    fn height_range_where(&self, keep: impl Fn(&crate::dag::Node<R::Id>) -> bool) -> (f64, f64) {
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for n in self.dag.nodes().filter(|n| n.refined.is_none() && keep(n)) {
            let (a, b) = n.height_bounds_m(&self.world);
            lo = lo.min(a);
            hi = hi.max(b);
        }
        if lo.is_finite() && hi.is_finite() {
            (lo, hi)
        } else {
            (0.0, 0.0)
        }
    }

    /// Runs frames of overviews (the whole raster from as high as it is wide, or the
    /// planet from three radii away on opposite sides; 1 px) until each is at full
    /// quality or `timeout` passes; returns whether every root got refined, which makes
    /// the height bounds ([`Session::height_range`]) conservative (and lets planets cull
    /// by their horizon). The finer the overviews' cuts, the tighter the bounds.
    pub fn warm_up(&mut self, timeout: Duration) -> Result<bool, SessionError> {
        let start = std::time::Instant::now();
        let views = self.refiner.overviews(&self.world, self.height_range());
        // The overviews refine by sampling density whatever the session's metric: their
        // purpose is tight height bounds everywhere (the built-in flights stand on them),
        // and the geometric metric leaves a whole-raster view coarse, its bounds loose.
        let metric = self.refinement.config.metric;
        self.refinement.config.metric = crate::refine::Metric::Sampling;
        let result = self.warm_up_views(views, start, timeout);
        self.refinement.config.metric = metric;
        result?;
        Ok(self.roots_refined())
    }

    fn warm_up_views(
        &mut self,
        views: Vec<View>,
        start: std::time::Instant,
        timeout: Duration,
    ) -> Result<(), SessionError> {
        // Each overview gets its share of the time, so a slow link still sees them all.
        let share = timeout / views.len().max(1) as u32;
        for (k, view) in views.into_iter().enumerate() {
            let until = share * (k as u32 + 1);
            while start.elapsed() < until {
                let f = self.update(&view, start.elapsed(), Duration::from_millis(4))?;
                if f.refine.full_quality {
                    break;
                }
                std::thread::sleep(Duration::from_millis(2));
            }
        }
        Ok(())
    }

    /// Whether every root is refined.
    fn roots_refined(&self) -> bool {
        self.refiner
            .roots()
            .iter()
            .all(|r| self.dag.node(r.0).is_some_and(|n| n.refined.is_some()))
    }

    /// Once every root is refined, a conservative lowest height: the lowest point of the
    /// roots' children's grids less the bounds the roots' blobs carry for them.
    fn lowest_height(&self) -> Option<f64> {
        if !self.roots_refined() {
            return None;
        }
        let mut lowest = f64::INFINITY;
        for (root, _) in self.refiner.roots() {
            for c in self.dag.children(root).iter() {
                lowest = lowest.min(self.dag.node(*c)?.height_bounds_m(&self.world).0);
            }
        }
        lowest.is_finite().then_some(lowest)
    }

    /// The colour layer's network thread's counters (`None` without a colour layer); the
    /// elevation's are [`Session::fetch_stats`] less these.
    pub fn colour_fetch_stats(&self) -> Option<FetchStats> {
        self.colour
            .as_ref()
            .map(|(_, colour)| colour.fetcher.stats())
    }

    /// The network threads' counters (elevation and colour added up).
    pub fn fetch_stats(&self) -> FetchStats {
        let mut stats = self.elevation.fetcher.stats();
        if let Some((_, colour)) = &self.colour {
            stats.add(&colour.fetcher.stats());
        }
        stats
    }

    /// Fetch failures reported so far (each is asked for again while wanted).
    pub fn failures(&self) -> u64 {
        self.failures
    }

    /// Body bytes of the distinct blobs that refinement has used so far (each counted
    /// once, however often it was refined), in every cut since the session opened.
    pub fn bytes_used(&self) -> u64 {
        self.elevation.bytes_used() + self.colour.as_ref().map_or(0, |(_, c)| c.bytes_used())
    }

    /// The blobs the current cut is built from: those of the diamonds refined now (each
    /// refined diamond's elevation blob and the colour blob its refinement used). A
    /// cut's patches are synthesised from exactly these, so they are what a client
    /// must have fetched to show it.
    pub fn cut_blobs(&self) -> CutBlobs {
        let dag = &self.dag;
        let mut blobs = CutBlobs::default();
        for node in dag.nodes().filter(|n| n.refined.is_some()) {
            blobs.elevation.insert(R::key_of(node.id));
            if let Some(c) = dag.colour_blob_id(node.id) {
                blobs.colour.insert(R::key_of(c));
            }
        }
        blobs
    }

    /// Body bytes of `blobs` (as fetched; blobs this session never fetched, and
    /// diamonds without a blob, count 0).
    pub fn blob_bytes(&self, blobs: &CutBlobs) -> u64 {
        let sum = |sizes: &Mutex<HashMap<Key, u32>>, keys: &HashSet<Key>| -> u64 {
            let sizes = lock(sizes);
            keys.iter()
                .map(|k| u64::from(sizes.get(k).copied().unwrap_or(0)))
                .sum()
        };
        sum(&self.elevation.blob_bytes, &blobs.elevation)
            + self
                .colour
                .as_ref()
                .map_or(0, |(_, c)| sum(&c.blob_bytes, &blobs.colour))
    }

    /// Runs one frame for `view` at time `now` (any monotonic origin, used for camera
    /// prediction): refines and coarsens within `budget` and keeps the network busy.
    pub fn update(
        &mut self,
        view: &View,
        now: Duration,
        budget: Duration,
    ) -> Result<SessionFrame, SessionError> {
        let started = std::time::Instant::now();
        let mut frame = SessionFrame {
            failed: self.elevation.poll() + self.colour.as_mut().map_or(0, |(_, c)| c.poll()),
            ..SessionFrame::default()
        };
        self.failures += frame.failed as u64;
        if !self.lowest_known
            && let Some(lowest) = self.lowest_height()
        {
            // Planets start culling by their horizon.
            self.world = R::with_lowest_height(self.world, lowest);
            tracing::debug!(lowest, world = ?self.world, "lowest height known");
            self.lowest_known = true;
        }
        let clock = SystemClock(started);
        let mut source = FetchSource {
            refiner: &*self.refiner,
            elevation: &mut self.elevation,
            colour: self.colour.as_mut().map(|(l, c)| (&**l, c)),
        };
        frame.refine =
            self.refinement
                .update(&mut self.dag, view, self.world, &mut source, &clock, budget)?;
        let wants: Vec<(Key, f32)> = take_wants(&mut self.elevation);
        let colour_wants: Vec<(Key, f32)> = self
            .colour
            .as_mut()
            .map(|(_, c)| take_wants(c))
            .unwrap_or_default();
        frame.wanted = wants.len() + colour_wants.len();
        self.elevation.arrived.clear();
        if let Some((_, c)) = &mut self.colour {
            c.arrived.clear();
        }

        let stats = self.elevation.fetcher.stats();
        self.peak_bandwidth_bit_s = self.peak_bandwidth_bit_s.max(stats.bandwidth_bit_s);
        let levels = self.lookahead_levels_for(&stats);
        // The diamonds any layer wants (elevation ids), for lookahead.
        let mut wanted: HashMap<R::Id, f32> =
            wants.iter().map(|&(k, p)| (R::id_of(k), p)).collect();
        if let Some((layer, _)) = &self.colour {
            for &(k, p) in &colour_wants {
                if let Some(id) = layer.elevation_id(R::id_of(k)) {
                    let e = wanted.entry(id).or_insert(p);
                    *e = e.max(p);
                }
            }
        }
        let mut ahead = self.lookahead(&wanted, levels, view.tolerance_px);
        ahead.extend(self.prefetch(view, now, &wanted));
        ahead.sort_by(|a, b| b.1.total_cmp(&a.1));
        ahead.dedup_by_key(|(id, _)| *id);
        ahead.truncate(self.config.prefetch_max);
        // Each layer fetches the diamonds it codes and does not know to be leaves.
        let elevation_ahead = self.elevation.prefetch_keys(
            ahead
                .iter()
                .filter(|(id, _)| self.refiner.is_coded(*id))
                .map(|&(id, p)| (R::key_of(id), p)),
        );
        frame.prefetched = elevation_ahead.len();
        if let Some((layer, colour)) = &mut self.colour {
            let colour_ahead = colour.prefetch_keys(ahead.iter().filter_map(|&(id, p)| {
                let c = layer.colour_id(id)?;
                layer.is_coded(c).then_some((R::key_of(c), p))
            }));
            frame.prefetched += colour_ahead.len();
            let above = colour.package_above(self.config.package_factor, view.tolerance_px);
            colour
                .fetcher
                .submit_packaged(colour_wants, colour_ahead, above);
        }
        let above = self
            .elevation
            .package_above(self.config.package_factor, view.tolerance_px);
        self.elevation
            .fetcher
            .submit_packaged(wants, elevation_ahead, above);
        frame.elapsed = started.elapsed();
        Ok(frame)
    }

    /// Whether some layer would fetch data for diamond `id` (coded there and not known
    /// to be a leaf).
    fn fetchable(&self, id: R::Id) -> bool {
        (self.refiner.is_coded(id) && !self.elevation.is_leaf(R::key_of(id)))
            || self.colour.as_ref().is_some_and(|(layer, colour)| {
                layer
                    .colour_id(id)
                    .is_some_and(|c| layer.is_coded(c) && !colour.is_leaf(R::key_of(c)))
            })
    }

    /// The descendants of wanted diamonds that will be wanted once these arrive, while
    /// their projected error (about the parent's over `sqrt(2)` per level) exceeds the
    /// tolerance, and that some layer would fetch.
    fn lookahead(
        &self,
        wanted: &HashMap<R::Id, f32>,
        levels: usize,
        tolerance_px: f64,
    ) -> Vec<(R::Id, f32)> {
        if levels == 0 {
            return Vec::new();
        }
        let mut out: HashMap<R::Id, f32> = HashMap::new();
        let mut frontier: Vec<(R::Id, f64)> =
            wanted.iter().map(|(&id, &p)| (id, f64::from(p))).collect();
        for _ in 0..levels {
            let mut next = Vec::new();
            for (id, p) in frontier {
                let child_error = p / std::f64::consts::SQRT_2;
                if child_error <= tolerance_px {
                    continue;
                }
                for &c in self.dag.children(id).iter() {
                    if wanted.contains_key(&c) || !self.fetchable(c) {
                        continue;
                    }
                    let e = out.entry(c).or_insert(0.0);
                    if child_error as f32 > *e {
                        *e = child_error as f32;
                        next.push((c, child_error));
                    }
                }
            }
            frontier = next;
        }
        out.into_iter().collect()
    }

    /// Lookahead depth for the link as measured: lookahead hides round trips, which
    /// cost only while the link has room for more answers. There is none while the link
    /// both carries fewer than [`SessionConfig::lookahead_min_blobs`] blobs per round
    /// trip (delivered bandwidth x RTT over the mean blob) *and* queues (answers take
    /// more than 1.25 times the RTT): there the link itself is the bottleneck, and lookahead
    /// answers would queue ahead of wanted ones. A link that does not queue has room,
    /// however little it delivered: the delivered rate of a lightly used link is what
    /// was asked of it, not what it can carry. Before the first estimate: the configured
    /// depth.
    pub fn lookahead_levels(&self) -> usize {
        self.lookahead_levels_for(&self.elevation.fetcher.stats())
    }

    /// [`Session::lookahead_levels`] from the network thread's counters.
    fn lookahead_levels_for(&self, stats: &FetchStats) -> usize {
        let levels = self.config.lookahead_levels;
        // The link carries at least the most it ever delivered.
        let bandwidth = stats.bandwidth_bit_s.max(self.peak_bandwidth_bit_s);
        match (stats.rtt, stats.latency) {
            (Some(rtt), Some(latency)) if bandwidth > 0.0 && stats.mean_blob_bytes > 0.0 => {
                let per_trip = bandwidth / 8.0 * rtt.as_secs_f64() / stats.mean_blob_bytes;
                let queues = latency > rtt + rtt / 4;
                if per_trip < self.config.lookahead_min_blobs && queues {
                    0
                } else {
                    levels
                }
            }
            _ => levels,
        }
    }

    /// Tracks the camera and, when due, lists what the predicted view wants that the
    /// current one does not.
    fn prefetch(
        &mut self,
        view: &View,
        now: Duration,
        wanted: &HashMap<R::Id, f32>,
    ) -> Vec<(R::Id, f32)> {
        self.camera.observe(now, view.eye);
        let ahead = self.config.prefetch_ahead.as_secs_f64();
        let due = self
            .last_prefetch
            .is_none_or(|t| now.saturating_sub(t) >= self.config.prefetch_every);
        let velocity = self.camera.velocity();
        if ahead <= 0.0 || !due || velocity.length_squared() == 0.0 {
            return Vec::new();
        }
        self.last_prefetch = Some(now);
        let shift = velocity * ahead;
        let predicted = View {
            eye: view.eye + shift,
            target: view.target + shift,
            ..*view
        };
        self.refinement
            .wanted_splits(&self.dag, &predicted, self.world)
            .into_iter()
            .filter(|(id, _)| !wanted.contains_key(id) && self.fetchable(*id))
            .map(|(id, e)| (id, e as f32))
            .collect()
    }
}

impl Session<PlanarRefiner> {
    /// The world box of the raster: its extent times [`Session::height_range`].
    pub fn bounds(&self) -> Aabb {
        let (w, h) = self.dag.refiner().raster_size();
        let (lo, hi) = self.height_range();
        let a = self.world.point([0, 0], 0);
        let b = self.world.point([w as i64 - 1, h as i64 - 1], 0);
        Aabb {
            min: DVec3::new(a.x.min(b.x), a.y.min(b.y), lo),
            max: DVec3::new(a.x.max(b.x), a.y.max(b.y), hi),
        }
    }
}

impl Session<SphereRefiner> {
    /// A conservative bound on the surface height (metres) around `direction` (from
    /// the planet's centre): the height range of the cut diamonds whose caps hold it.
    pub fn height_range_near(&self, direction: DVec3) -> (f64, f64) {
        let dir = direction.normalize_or_zero();
        let world = self.world;
        let refiner = &*self.refiner;
        self.height_range_where(|n| {
            let (bbox, _) = refiner.footprint(&world, n.id, &n.corners, (0.0, 0.0));
            // The cap's box at radius R holds the direction's point when it is in it.
            let p = dir * world.radius_m;
            let slack = (bbox.max - bbox.min).length() * 1e-9 + 1.0;
            (p - bbox.min).min_element() >= -slack && (bbox.max - p).min_element() >= -slack
        })
    }
}

/// The camera's smoothed velocity, for prediction. A jump is not motion: a frame that
/// moves the eye ten times farther than the frame before it (and over 100 m) resets the
/// velocity to zero, and so does time running backwards (a new time origin).
#[derive(Clone, Copy, Debug, Default)]
struct CameraTrack {
    last: Option<(Duration, DVec3)>,
    /// Distance moved by the last frame (metres).
    last_step_m: f64,
    velocity: DVec3,
}

impl CameraTrack {
    fn observe(&mut self, now: Duration, eye: DVec3) {
        let Some((then, last_eye)) = self.last.replace((now, eye)) else {
            return;
        };
        if now < then || !eye.is_finite() {
            self.velocity = DVec3::ZERO;
            self.last_step_m = 0.0;
            return;
        }
        let dt = (now - then).as_secs_f64();
        if dt <= 0.0 {
            return;
        }
        let step = (eye - last_eye).length();
        let jump = step > 10.0 * self.last_step_m + 100.0;
        self.last_step_m = step;
        let v = (eye - last_eye) / dt;
        self.velocity = if jump {
            DVec3::ZERO
        } else if self.velocity == DVec3::ZERO {
            v
        } else {
            self.velocity * 0.7 + v * 0.3
        };
    }

    fn velocity(&self) -> DVec3 {
        self.velocity
    }
}

/// A colour layer and its data access, borrowed for a frame.
type ColourSource<'a, R> = (
    &'a ColourLayer<R>,
    &'a mut Layer<ColourDetails<<R as Refiner>::Id>>,
);

/// A layer's wants, for submitting.
fn take_wants<T>(layer: &mut Layer<T>) -> Vec<(Key, f32)> {
    layer.wants.drain().map(|(k, p)| (k, p as f32)).collect()
}

/// Details for the refinement from what arrived, the fetchers' caches, or the network.
struct FetchSource<'a, R: Domain> {
    refiner: &'a R,
    elevation: &'a mut Layer<Details<R::Id>>,
    colour: Option<ColourSource<'a, R>>,
}

impl<R: Domain> DetailSource<R::Id> for FetchSource<'_, R> {
    fn details(&mut self, id: R::Id, priority: f64) -> Availability<R::Id> {
        let refiner = self.refiner;
        let parents = || refiner.parents(id).into_iter().map(R::key_of).collect();
        self.elevation.take(R::key_of(id), priority, parents, |d| {
            d.empty_children.iter().map(|&c| R::key_of(c)).collect()
        })
    }

    fn want(&mut self, id: R::Id, priority: f64) {
        let refiner = self.refiner;
        let parents = || refiner.parents(id).into_iter().map(R::key_of).collect();
        let key = R::key_of(id);
        if self.elevation.lookup(key, parents).is_none() {
            self.elevation.record(key, priority);
        }
    }

    fn colour(
        &mut self,
        _id: R::Id,
        colour: R::Id,
        priority: f64,
    ) -> Arrival<ColourDetails<R::Id>> {
        let Some((layer, stream)) = &mut self.colour else {
            return Arrival::Ready(None);
        };
        let channel = &layer.channels()[0];
        let parents = || channel.parents(colour).into_iter().map(R::key_of).collect();
        stream.take(R::key_of(colour), priority, parents, |d| {
            let children = channel.children(colour).unwrap_or_default();
            d.empty_children(&children)
                .into_iter()
                .map(R::key_of)
                .collect()
        })
    }

    fn want_colour(&mut self, _id: R::Id, colour: R::Id, priority: f64) {
        let Some((layer, stream)) = &mut self.colour else {
            return;
        };
        let channel = &layer.channels()[0];
        let parents = || channel.parents(colour).into_iter().map(R::key_of).collect();
        let key = R::key_of(colour);
        if stream.lookup(key, parents).is_none() {
            stream.record(key, priority);
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn ms(v: u64) -> Duration {
        Duration::from_millis(v)
    }

    #[test]
    fn steady_motion_is_predicted_and_jumps_are_not() {
        let mut c = CameraTrack::default();
        // 150 m/s along x at 50 frames/s.
        for k in 0..20u64 {
            c.observe(ms(20 * k), DVec3::new(3.0 * k as f64, 0.0, 500.0));
        }
        assert!((c.velocity() - DVec3::new(150.0, 0.0, 0.0)).length() < 1e-6);
        // A jump of 50 km: no prediction from it, nor on the frame that holds still.
        c.observe(ms(400), DVec3::new(50_000.0, 0.0, 500.0));
        assert_eq!(c.velocity(), DVec3::ZERO);
        c.observe(ms(420), DVec3::new(50_000.0, 0.0, 500.0));
        assert_eq!(c.velocity(), DVec3::ZERO);
        // Moving again from rest is motion.
        c.observe(ms(440), DVec3::new(50_003.0, 0.0, 500.0));
        assert!((c.velocity() - DVec3::new(150.0, 0.0, 0.0)).length() < 1e-6);
        // A new time origin forgets the motion.
        c.observe(ms(10), DVec3::new(50_006.0, 0.0, 500.0));
        assert_eq!(c.velocity(), DVec3::ZERO);
    }

    #[test]
    fn a_fast_but_smooth_descent_is_motion() {
        // The approach flight's first frames: kilometres per frame, each like the last.
        let mut c = CameraTrack::default();
        let mut z = 700_000.0;
        for k in 0..10u64 {
            c.observe(ms(16 * k), DVec3::new(0.0, 0.0, z));
            z -= 1_700.0;
        }
        assert!(c.velocity().z < -50_000.0, "{:?}", c.velocity());
    }
}
