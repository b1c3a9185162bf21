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
//! The frame loop itself is the core's [`StreamCore`] (no I/O); a [`Session`] adds a
//! network thread per layer ([`crate::fetch::Fetcher`]) and the system clock. Each
//! [`Session::update`]:
//! 1. takes what the network threads delivered since the last frame;
//! 2. runs [`crate::refine::Refinement::update`] within the budget. Details come from what arrived or
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
use quincunx_decoder::incremental::{Details, PlanarRefiner, Procedural, SphereRefiner};
use quincunx_meta::Metadata;

use crate::colour::ColourDetails;
use crate::dag::Dag;
use crate::domain::Domain;
use crate::fetch::{
    Decoded, FetchConfig, FetchStats, Fetched, Fetcher, Key, Remote, Transport, Unpack, Weigh, lock,
};
use crate::refine::{RefineConfig, SystemClock};
use crate::view::{Aabb, View};

pub use crate::dag::{Patch, PatchChanges};
pub use crate::open::{
    EARTH_RADIUS_M, SessionError, planar_channel_refiner, planar_refiner, planar_world,
    sphere_channel_refiner, sphere_refiner, sphere_world,
};
pub use quincunx_client_core::stream::{
    CutBlobs, Packing, Requests, SessionFrame, Snapshot, Store, Stores, StreamConfig, StreamCore,
    Submit,
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
    /// Refinement tuning ([`StreamConfig::refine`]).
    pub refine: RefineConfig,
    /// [`StreamConfig::prefetch_ahead`]: how far ahead the camera is predicted.
    pub prefetch_ahead: Duration,
    /// [`StreamConfig::prefetch_every`]: how often the predicted camera is evaluated.
    pub prefetch_every: Duration,
    /// [`StreamConfig::prefetch_max`]: most prefetch keys submitted at once.
    pub prefetch_max: usize,
    /// [`StreamConfig::lookahead_levels`]: levels requested ahead below wanted diamonds.
    pub lookahead_levels: usize,
    /// [`StreamConfig::lookahead_min_blobs`]: no lookahead on a link this narrow that queues.
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
    /// [`StreamConfig::package_factor`]: packages from this multiple of the tolerance.
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

impl SessionConfig {
    /// The frame loop's part of the settings.
    pub fn stream(&self) -> StreamConfig {
        StreamConfig {
            refine: self.refine,
            prefetch_ahead: self.prefetch_ahead,
            prefetch_every: self.prefetch_every,
            prefetch_max: self.prefetch_max,
            lookahead_levels: self.lookahead_levels,
            lookahead_min_blobs: self.lookahead_min_blobs,
            package_factor: self.package_factor,
        }
    }
}

/// One layer's data access: its repository and network thread.
struct Layer<T> {
    name: String,
    remote: Remote,
    meta: Metadata,
    fetcher: Fetcher<T>,
    /// Body bytes of each fetched blob (written on the network thread).
    blob_bytes: Arc<Mutex<HashMap<Key, u32>>>,
}

impl<T: Weigh + Send + Sync + 'static> Store<T> for Fetcher<T> {
    fn is_leaf(&self, key: Key) -> bool {
        Fetcher::is_leaf(self, key)
    }

    fn cached(&self, key: Key) -> Option<Arc<T>> {
        Fetcher::cached(self, key)
    }

    fn contains(&self, key: Key) -> bool {
        Fetcher::contains(self, key)
    }
}

impl<T: Weigh + Send + Sync + 'static> Layer<T> {
    /// Starts the network thread of repository `remote` whose blobs `decode` decodes
    /// (unpacking packages as `packing`, the core's reading of its metadata, says).
    fn spawn(
        remote: Remote,
        meta: Metadata,
        config: &SessionConfig,
        packing: Option<Packing>,
        decode: impl Fn(Key, &[u8]) -> Result<T, String> + Send + Sync + 'static,
    ) -> Result<Layer<T>, SessionError> {
        let blob_bytes: Arc<Mutex<HashMap<Key, u32>>> = Arc::default();
        let decode: Unpack<T> = {
            let sizes = Arc::clone(&blob_bytes);
            let decode = move |key: Key, bytes: &[u8]| {
                lock(&sizes).insert(key, u32::try_from(bytes.len()).unwrap_or(u32::MAX));
                decode(key, bytes)
            };
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
        })
    }

    /// Hands what the network thread delivered to `arrived`; returns the failures.
    fn poll(&mut self, mut arrived: impl FnMut(Key, Option<Arc<T>>)) -> usize {
        let mut failed = 0;
        for (key, fetched) in self.fetcher.poll() {
            match fetched {
                Fetched::Data(d) => arrived(key, Some(d)),
                Fetched::Leaf => arrived(key, None),
                Fetched::Failed(e) => {
                    tracing::debug!(repo = %self.name, ?key, error = %e, "fetch failed");
                    failed += 1;
                }
            }
        }
        failed
    }

    /// Asks the network thread for what a frame wants.
    fn submit(&self, submit: Submit) {
        self.fetcher
            .submit_packaged(submit.wants, submit.prefetch, submit.package_above);
    }

    /// Body bytes of the fetched blobs among `keys`.
    fn bytes_of(&self, keys: &HashSet<Key>) -> u64 {
        let sizes = lock(&self.blob_bytes);
        keys.iter()
            .map(|k| u64::from(sizes.get(k).copied().unwrap_or(0)))
            .sum()
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

/// An elevation repository streamed from a server (planar unless `R` says otherwise):
/// the core's [`StreamCore`] with a network thread per layer.
pub struct Session<R: Domain = PlanarRefiner> {
    core: StreamCore<R>,
    config: SessionConfig,
    /// The elevation repository's data access.
    elevation: Layer<Details<R::Id>>,
    /// The colour repository's data access, with a colour layer.
    colour: Option<Layer<ColourDetails<R::Id>>>,
    failures: u64,
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
    /// `base_url`), matched at run time ([`crate::colour::ColourLayer::match_to`]).
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
        let core = StreamCore::<R>::new(
            &remote.name,
            &meta,
            colour.as_ref().map(|(r, m)| (r.name.as_str(), m)),
            config.stream(),
            config.spacing_m,
            config.procedural,
        )?;
        let elevation = {
            let refiner = Arc::clone(core.refiner());
            let packing = core.elevation().packing().cloned();
            Layer::spawn(remote, meta, &config, packing, move |key, bytes| {
                refiner
                    .decode(R::id_of(key), bytes)
                    .map_err(|e| e.to_string())
            })?
        };
        let colour = match (colour, core.colour_layer(), core.colour()) {
            (Some((remote, meta)), Some(layer), Some(state)) => {
                let decoder = Arc::clone(layer);
                let packing = state.packing().cloned();
                Some(Layer::spawn(
                    remote,
                    meta,
                    &config,
                    packing,
                    move |key, bytes| decoder.decode(R::id_of(key), bytes),
                )?)
            }
            _ => None,
        };
        Ok(Session {
            core,
            config,
            elevation,
            colour,
            failures: 0,
        })
    }

    /// The settings it was opened with.
    pub fn config(&self) -> &SessionConfig {
        &self.config
    }

    /// The frame loop without its network threads.
    pub fn core(&self) -> &StreamCore<R> {
        &self.core
    }

    /// Sets the most halves the cut may hold ([`RefineConfig::max_cut_halves`]): a
    /// renderer passes the patches its GPU pool holds.
    pub fn set_max_cut_halves(&mut self, max: Option<usize>) {
        self.core.set_max_cut_halves(max);
        self.config.refine.max_cut_halves = max;
    }

    /// The most halves the cut may hold, if bounded.
    pub fn max_cut_halves(&self) -> Option<usize> {
        self.core.max_cut_halves()
    }

    /// Repository name.
    pub fn name(&self) -> &str {
        &self.elevation.name
    }

    /// The colour repository's name and metadata, with a colour layer.
    pub fn colour(&self) -> Option<(&str, &Metadata)> {
        self.colour.as_ref().map(|l| (l.name.as_str(), &l.meta))
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
        self.core.world()
    }

    /// The DAG: the current cut ([`Dag::cut`]) is what a renderer draws.
    pub fn dag(&self) -> &Dag<R> {
        self.core.dag()
    }

    /// The current cut for a renderer.
    pub fn snapshot(&self) -> Snapshot<R::Id, R::World> {
        self.core.snapshot()
    }

    /// How the cut changed since the previous call, with the patches that entered (the
    /// first call reports the whole cut): what a retained-mode renderer uploads and frees
    /// each frame, in time proportional to the changes ([`Dag::take_cut_changes`]).
    pub fn cut_changes(&mut self) -> PatchChanges<R::Id> {
        self.core.cut_changes()
    }

    /// Makes the next [`Session::cut_changes`] report the whole cut again.
    pub fn restart_cut_changes(&mut self) {
        self.core.restart_cut_changes();
    }

    /// A conservative range of the surface's heights (metres): over the cut, each
    /// unrefined diamond's grid range widened by the bound its parent's blob carries for
    /// its whole subtree. Conservative once every cut diamond's bound is known, which is
    /// the case as soon as the roots are refined ([`Session::warm_up`]); before that it is
    /// the root grids' range only, and real peaks may rise above it.
    pub fn height_range(&self) -> (f64, f64) {
        self.core.height_range()
    }

    /// Runs frames of overviews (the whole raster from as high as it is wide, or the
    /// planet from three radii away on opposite sides; 1 px) until each is at full
    /// quality or `timeout` passes; returns whether every root got refined, which makes
    /// the height bounds ([`Session::height_range`]) conservative (and lets planets cull
    /// by their horizon). The finer the overviews' cuts, the tighter the bounds.
    pub fn warm_up(&mut self, timeout: Duration) -> Result<bool, SessionError> {
        let start = std::time::Instant::now();
        let views = self
            .core
            .refiner()
            .overviews(&self.core.world(), self.height_range());
        // The overviews refine by sampling density whatever the session's metric: their
        // purpose is tight height bounds everywhere (the built-in flights stand on them),
        // and the geometric metric leaves a whole-raster view coarse, its bounds loose.
        let metric = self.core.metric();
        self.core.set_metric(crate::refine::Metric::Sampling);
        let result = self.warm_up_views(views, start, timeout);
        self.core.set_metric(metric);
        result?;
        Ok(self.core.roots_refined())
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

    /// The colour layer's network thread's counters (`None` without a colour layer); the
    /// elevation's are [`Session::fetch_stats`] less these.
    pub fn colour_fetch_stats(&self) -> Option<FetchStats> {
        self.colour.as_ref().map(|colour| colour.fetcher.stats())
    }

    /// The network threads' counters (elevation and colour added up); `cache_hits` also
    /// counts the diamonds refinement took from the caches itself.
    pub fn fetch_stats(&self) -> FetchStats {
        let mut stats = self.elevation.fetcher.stats();
        if let Some(colour) = &self.colour {
            stats.add(&colour.fetcher.stats());
        }
        stats.cache_hits += self.core.cache_hits();
        stats
    }

    /// Fetch failures reported so far (each is asked for again while wanted).
    pub fn failures(&self) -> u64 {
        self.failures
    }

    /// Body bytes of the distinct blobs that refinement has used so far (each counted
    /// once, however often it was refined), in every cut since the session opened.
    pub fn bytes_used(&self) -> u64 {
        let colour = match (&self.colour, self.core.colour()) {
            (Some(c), Some(state)) => c.bytes_of(state.used()),
            _ => 0,
        };
        self.elevation.bytes_of(self.core.elevation().used()) + colour
    }

    /// The blobs the current cut is built from: those of the diamonds refined now (each
    /// refined diamond's elevation blob and the colour blob its refinement used). A
    /// cut's patches are synthesised from exactly these, so they are what a client
    /// must have fetched to show it.
    pub fn cut_blobs(&self) -> CutBlobs {
        self.core.cut_blobs()
    }

    /// Body bytes of `blobs` (as fetched; blobs this session never fetched, and
    /// diamonds without a blob, count 0).
    pub fn blob_bytes(&self, blobs: &CutBlobs) -> u64 {
        self.elevation.bytes_of(&blobs.elevation)
            + self
                .colour
                .as_ref()
                .map_or(0, |c| c.bytes_of(&blobs.colour))
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
        let core = &mut self.core;
        let mut failed = self.elevation.poll(|k, d| core.arrived(k, d));
        if let Some(colour) = &mut self.colour {
            failed += colour.poll(|k, d| core.colour_arrived(k, d));
        }
        self.failures += failed as u64;
        let clock = SystemClock(started);
        let stores = Stores {
            elevation: &self.elevation.fetcher,
            colour: self
                .colour
                .as_ref()
                .map(|c| &c.fetcher as &dyn Store<ColourDetails<R::Id>>),
        };
        let fetcher = &self.elevation.fetcher;
        let (mut frame, requests) = self
            .core
            .frame(view, now, budget, &clock, stores, || fetcher.stats())?;
        frame.failed = failed;
        if let (Some(colour), Some(submit)) = (&self.colour, requests.colour) {
            colour.submit(submit);
        }
        self.elevation.submit(requests.elevation);
        frame.elapsed = started.elapsed();
        Ok(frame)
    }

    /// Lookahead depth for the link as measured ([`StreamCore::lookahead_levels_for`]
    /// with the elevation network thread's estimates).
    pub fn lookahead_levels(&self) -> usize {
        self.core
            .lookahead_levels_for(&self.elevation.fetcher.stats())
    }
}

impl Session<PlanarRefiner> {
    /// The world box of the raster: its extent times [`Session::height_range`].
    pub fn bounds(&self) -> Aabb {
        self.core.bounds()
    }
}

impl Session<SphereRefiner> {
    /// A conservative bound on the surface height (metres) around `direction` (from
    /// the planet's centre): the height range of the cut diamonds whose caps hold it.
    pub fn height_range_near(&self, direction: DVec3) -> (f64, f64) {
        self.core.height_range_near(direction)
    }
}
