//! A streamed repository, frame by frame, without I/O: one elevation repository (planar
//! or planet) and optionally a colour repository matched to it, with their DAG,
//! refinement, what each layer has received and wants, lookahead and camera prediction.
//!
//! Each [`StreamCore::frame`] takes the time, the view, the answers delivered since the
//! last frame ([`StreamCore::arrived`]) and each layer's [`Store`] (what the data access
//! layer holds: decoded values, known leaves), refines within a budget read from a
//! [`Clock`], and returns what each layer should ask for ([`Submit`]). Whatever sends the
//! requests and decodes the answers (the native client's network threads, a browser's
//! `fetch` and workers) stays outside.
//!
//! The frame never waits for the network: a diamond whose details have not arrived stays
//! unrefined and the cut stays consistent (crack-free) whatever arrives when.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::Duration;

use glam::DVec3;
use quincunx_decoder::diamond::PlanarId;
use quincunx_decoder::incremental::{Details, PlanarRefiner, Procedural, Refiner, SphereRefiner};
use quincunx_meta::Metadata;
use quincunx_meta::answer;

use crate::colour::{ColourDetails, ColourLayer};
use crate::dag::{Dag, Node, PatchChanges};
use crate::domain::Domain;
use crate::fetch::{FetchStats, Key};
use crate::open::{SessionError, metadata_error};
use crate::refine::{
    Arrival, Availability, Clock, DetailSource, FrameStats, Metric, RefineConfig, Refinement,
};
use crate::view::{Aabb, PlanarWorld, View};

pub use crate::dag::Patch;

/// The frame loop's settings (the native client's `SessionConfig` holds them beside its
/// network settings). `Default` prefetches half a second ahead, looks two levels ahead
/// and asks for packages from twice the tolerance.
#[derive(Clone, Debug)]
pub struct StreamConfig {
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
    /// `error / sqrt(2)^depth` above the tolerance; with the geometric metric, `error`
    /// itself below a diamond whose bound has stopped shrinking). This hides the round
    /// trip per level a view would otherwise pay on its way down; 0 disables it. See also
    /// [`StreamConfig::lookahead_min_blobs`].
    pub lookahead_levels: usize,
    /// No lookahead while one round trip of the link (estimated bandwidth x RTT) carries
    /// fewer than this many mean-sized blobs and the link queues (answers take more than
    /// 1.25 times the RTT): on such a link the bandwidth, not the round trips, bounds how
    /// fast a view fills, and lookahead answers would only queue ahead of wanted ones.
    pub lookahead_min_blobs: f64,
    /// Ask for packages (a blob with its small owned children's, for repositories with an
    /// inlining limit) where the diamond's children and grandchildren will want refining
    /// too: projected error at least `package_factor x tolerance`. `None`: bare blobs
    /// only. The default, 2, is where the grandchildren's error (about half the
    /// diamond's) still exceeds the tolerance. With a 300-byte limit, 1 or sqrt(2)
    /// fetched 1.28 or 1.19 times what the planet's jump flight used, 2 1.10
    /// (`docs/streaming.md`, "Packages").
    pub package_factor: Option<f64>,
}

impl Default for StreamConfig {
    fn default() -> Self {
        StreamConfig {
            refine: RefineConfig::default(),
            prefetch_ahead: Duration::from_millis(500),
            prefetch_every: Duration::from_millis(100),
            prefetch_max: 1024,
            lookahead_levels: 2,
            lookahead_min_blobs: 32.0,
            package_factor: Some(2.0),
        }
    }
}

/// What one frame did ([`StreamCore::frame`], the native client's `Session::update`).
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

/// How a repository's answers carry small owned children (`quincunx_meta::answer`).
#[derive(Clone, Debug)]
pub struct Packing {
    domain: answer::IdSpace,
    levels: u32,
    /// Per level: whether its blobs are small enough, on average, to be carried by their
    /// owners' answers (mean blob at most the inlining limit).
    carried: Vec<bool>,
}

impl Packing {
    /// The packing of a repository's answers; `None` if it serves no packages.
    pub fn of(meta: &Metadata) -> Result<Option<Packing>, String> {
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
    pub fn likely_carried(&self, key: Key) -> bool {
        self.domain
            .level(key)
            .is_ok_and(|l| self.carried.get(l as usize).copied().unwrap_or(false))
    }

    /// Splits the answer of `key` into its own value and the carried owned descendants
    /// (decoded).
    pub fn unpack<T, D: Fn(Key, &[u8]) -> Result<T, String>>(
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

/// What a layer's data access holds, read by the frame (the native client's network
/// thread shares its cache; a browser's would be its own).
pub trait Store<T> {
    /// Whether `key` is known to be a leaf (its answer was empty).
    fn is_leaf(&self, key: Key) -> bool;
    /// The decoded value of `key` if it is held (marking it used).
    fn cached(&self, key: Key) -> Option<Arc<T>>;
    /// Whether `key`'s value is held (without marking it used).
    fn contains(&self, key: Key) -> bool;
}

/// What one layer should ask for after a frame (it replaces the last frame's).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Submit {
    /// Keys the frame wanted and did not have, with priorities (projected error).
    pub wants: Vec<(Key, f32)>,
    /// Keys predicted to be wanted (lookahead and camera prediction).
    pub prefetch: Vec<(Key, f32)>,
    /// Keys from this priority up are asked for as packages.
    pub package_above: Option<f32>,
}

/// One layer's frame-side state: what arrived, what refinement used, leaves inferred
/// without asking, and what it wants.
#[derive(Debug)]
pub struct LayerState<T> {
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
    /// Diamonds refinement took from the store's cache (not delivered this frame).
    cache_hits: u64,
}

impl<T> LayerState<T> {
    /// A layer of the repository `meta` describes.
    pub fn new(name: &str, meta: &Metadata) -> Result<Self, SessionError> {
        Ok(LayerState {
            arrived: HashMap::new(),
            used: HashSet::new(),
            inferred_leaves: HashSet::new(),
            wants: HashMap::new(),
            packing: Packing::of(meta).map_err(|e| metadata_error(name, e))?,
            cache_hits: 0,
        })
    }

    /// How many times refinement took a diamond's data from the store's cache, since the
    /// start (a diamond coarsened away and refined again counts again).
    pub fn cache_hits(&self) -> u64 {
        self.cache_hits
    }

    /// How its answers carry small owned children, if it serves packages.
    pub fn packing(&self) -> Option<&Packing> {
        self.packing.as_ref()
    }

    /// The keys refinement used a blob of, since the start.
    pub fn used(&self) -> &HashSet<Key> {
        &self.used
    }

    fn is_leaf(&self, store: &dyn Store<T>, key: Key) -> bool {
        self.inferred_leaves.contains(&key) || store.is_leaf(key)
    }

    /// The data of `key` if it is here (`Some(None)`: a leaf, zero details); `parents`
    /// gives its parents' keys, asked only when nothing else answers (a leaf's children
    /// are leaves).
    fn lookup(
        &mut self,
        store: &dyn Store<T>,
        key: Key,
        parents: impl FnOnce() -> Vec<Key>,
    ) -> Option<Option<Arc<T>>> {
        if let Some(d) = self.arrived.get(&key) {
            return Some(d.clone());
        }
        if self.is_leaf(store, key) {
            return Some(None);
        }
        if let Some(d) = store.cached(key) {
            self.cache_hits += 1;
            return Some(Some(d));
        }
        if parents().into_iter().any(|p| self.is_leaf(store, p)) {
            self.inferred_leaves.insert(key);
            return Some(None);
        }
        None
    }

    /// The data of `key` for refinement: marks it used and learns its empty children
    /// (`empty`), or records it as wanted.
    fn take(
        &mut self,
        store: &dyn Store<T>,
        key: Key,
        priority: f64,
        parents: impl FnOnce() -> Vec<Key>,
        empty: impl FnOnce(&T) -> Vec<Key>,
    ) -> Arrival<T> {
        match self.lookup(store, key, parents) {
            Some(d) => {
                if let Some(data) = &d {
                    self.used.insert(key);
                    self.inferred_leaves.extend(empty(data));
                }
                Arrival::Ready(d)
            }
            None => {
                self.record(store, key, priority);
                Arrival::Pending
            }
        }
    }

    /// Wants `key`: asks for the answer likely to carry it (see [`LayerState::route`]).
    fn record(&mut self, store: &dyn Store<T>, key: Key, priority: f64) {
        let key = self.route(store, key);
        let p = self.wants.entry(key).or_insert(priority);
        *p = p.max(priority);
    }

    /// The key to ask for to get `key`: while a key is likely carried by its owner's
    /// answer and that answer has not come, the owner; else the key itself (its owner's
    /// answer came without it, or it is not likely carried).
    fn route(&self, store: &dyn Store<T>, key: Key) -> Key {
        let Some(packing) = &self.packing else {
            return key;
        };
        let mut at = key;
        while packing.likely_carried(at) {
            let Ok(Some(owner)) = packing.domain.owner(at) else {
                break;
            };
            if store.contains(owner) || self.is_leaf(store, owner) {
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

    /// Keys to prefetch for `ahead`: routed (see [`LayerState::route`]), each once,
    /// skipping known leaves.
    fn prefetch_keys(
        &self,
        store: &dyn Store<T>,
        ahead: impl Iterator<Item = (Key, f32)>,
    ) -> Vec<(Key, f32)> {
        let mut out: Vec<(Key, f32)> = Vec::new();
        let mut seen = HashSet::new();
        for (key, p) in ahead {
            let key = self.route(store, key);
            if !self.is_leaf(store, key) && seen.insert(key) {
                out.push((key, p));
            }
        }
        out
    }

    /// The frame's wants, for submitting.
    fn take_wants(&mut self) -> Vec<(Key, f32)> {
        self.wants.drain().map(|(k, p)| (k, p as f32)).collect()
    }
}

/// A set of blobs by layer (see [`StreamCore::cut_blobs`]).
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

/// The stores of a frame's layers (the colour one with a colour layer).
pub struct Stores<'a, R: Refiner> {
    /// The elevation layer's.
    pub elevation: &'a dyn Store<Details<R::Id>>,
    /// The colour layer's.
    pub colour: Option<&'a dyn Store<ColourDetails<R::Id>>>,
}

// By hand: a derive would ask `R: Copy` of the refiner, which only names the id type.
impl<R: Refiner> Clone for Stores<'_, R> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<R: Refiner> Copy for Stores<'_, R> {}

/// What a frame asks of the data access layers.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Requests {
    /// The elevation layer's wants and prefetches.
    pub elevation: Submit,
    /// The colour layer's, with a colour layer.
    pub colour: Option<Submit>,
}

/// A colour layer and its frame-side state.
type ColourStream<R> = (
    Arc<ColourLayer<R>>,
    LayerState<ColourDetails<<R as Refiner>::Id>>,
);

/// A streamed elevation repository (planar unless `R` says otherwise) and its optional
/// colour layer, without I/O.
pub struct StreamCore<R: Domain = PlanarRefiner> {
    world: R::World,
    refiner: Arc<R>,
    dag: Dag<R>,
    refinement: Refinement<R::Id>,
    config: StreamConfig,
    elevation: LayerState<Details<R::Id>>,
    colour: Option<ColourStream<R>>,
    /// Camera motion, for prediction.
    camera: CameraTrack,
    last_prefetch: Option<Duration>,
    /// The conservative lowest height went into the world mapping.
    lowest_known: bool,
    /// The highest delivered rate estimated so far (bit/s).
    peak_bandwidth_bit_s: f64,
}

impl<R: Domain> StreamCore<R> {
    /// The stream of elevation repository `name` (`meta`) and, optionally, a colour
    /// repository matched to it ([`ColourLayer::match_to`], with `procedural` details
    /// below the shallower one); `spacing_m` as the native `SessionConfig` says.
    pub fn new(
        name: &str,
        meta: &Metadata,
        colour: Option<(&str, &Metadata)>,
        config: StreamConfig,
        spacing_m: Option<f64>,
        procedural: Procedural,
    ) -> Result<Self, SessionError> {
        let (refiner, world) = R::from_metadata(name, meta, spacing_m)?;
        let (refiner, colour) = match colour {
            Some((colour_name, colour_meta)) => {
                let (refiner, layer) =
                    ColourLayer::match_to(refiner, meta, colour_name, colour_meta, procedural)?;
                let state = LayerState::new(colour_name, colour_meta)?;
                (refiner, Some((Arc::new(layer), state)))
            }
            None => (refiner, None),
        };
        let refiner = Arc::new(refiner);
        Ok(StreamCore {
            world,
            dag: Dag::with_colour(
                Arc::clone(&refiner),
                colour.as_ref().map(|(layer, _)| Arc::clone(layer)),
            ),
            refiner,
            refinement: Refinement::with_config(config.refine),
            elevation: LayerState::new(name, meta)?,
            colour,
            config,
            camera: CameraTrack::default(),
            last_prefetch: None,
            lowest_known: false,
            peak_bandwidth_bit_s: 0.0,
        })
    }

    /// The elevation refiner (what decodes its blobs).
    pub fn refiner(&self) -> &Arc<R> {
        &self.refiner
    }

    /// The colour layer (what decodes its blobs), with one.
    pub fn colour_layer(&self) -> Option<&Arc<ColourLayer<R>>> {
        self.colour.as_ref().map(|(layer, _)| layer)
    }

    /// The elevation layer's frame-side state.
    pub fn elevation(&self) -> &LayerState<Details<R::Id>> {
        &self.elevation
    }

    /// The colour layer's frame-side state, with one.
    pub fn colour(&self) -> Option<&LayerState<ColourDetails<R::Id>>> {
        self.colour.as_ref().map(|(_, state)| state)
    }

    /// How many times refinement took a diamond's data from a store's cache, both layers
    /// together (see [`LayerState::cache_hits`]).
    pub fn cache_hits(&self) -> u64 {
        self.elevation.cache_hits() + self.colour.as_ref().map_or(0, |c| c.1.cache_hits())
    }

    /// The settings.
    pub fn config(&self) -> &StreamConfig {
        &self.config
    }

    /// Sets the most halves the cut may hold ([`RefineConfig::max_cut_halves`]).
    pub fn set_max_cut_halves(&mut self, max: Option<usize>) {
        self.refinement.config.max_cut_halves = max;
        self.config.refine.max_cut_halves = max;
    }

    /// The most halves the cut may hold, if bounded.
    pub fn max_cut_halves(&self) -> Option<usize> {
        self.refinement.config.max_cut_halves
    }

    /// The refinement metric in use.
    pub fn metric(&self) -> Metric {
        self.refinement.config.metric
    }

    /// Sets the refinement metric.
    pub fn set_metric(&mut self, metric: Metric) {
        self.refinement.config.metric = metric;
    }

    /// How ids and integer samples map to world metres.
    pub fn world(&self) -> R::World {
        self.world
    }

    /// The DAG: the current cut ([`Dag::cut`]) is what a renderer draws.
    pub fn dag(&self) -> &Dag<R> {
        &self.dag
    }

    /// An answer delivered to the elevation layer: details, or `None` for a leaf.
    pub fn arrived(&mut self, key: Key, details: Option<Arc<Details<R::Id>>>) {
        self.elevation.arrived.insert(key, details);
    }

    /// An answer delivered to the colour layer (ignored without one).
    pub fn colour_arrived(&mut self, key: Key, details: Option<Arc<ColourDetails<R::Id>>>) {
        if let Some((_, c)) = &mut self.colour {
            c.arrived.insert(key, details);
        }
    }

    /// Runs one frame for `view` at time `now` (any monotonic origin, used for camera
    /// prediction): refines and coarsens within `budget` (read from `clock`) with what
    /// arrived and what `stores` hold, and returns what to ask for. `link` gives the
    /// elevation layer's link estimates (bandwidth, RTT: they set the lookahead).
    pub fn frame(
        &mut self,
        view: &View,
        now: Duration,
        budget: Duration,
        clock: &dyn Clock,
        stores: Stores<'_, R>,
        link: impl FnOnce() -> FetchStats,
    ) -> Result<(SessionFrame, Requests), SessionError> {
        let mut frame = SessionFrame::default();
        if !self.lowest_known
            && let Some(lowest) = self.lowest_height()
        {
            // Planets start culling by their horizon.
            self.world = R::with_lowest_height(self.world, lowest);
            tracing::debug!(lowest, world = ?self.world, "lowest height known");
            self.lowest_known = true;
        }
        let colour_store = stores.colour;
        let mut source = Source {
            refiner: &*self.refiner,
            elevation: (&mut self.elevation, stores.elevation),
            colour: match (self.colour.as_mut(), colour_store) {
                (Some((l, c)), Some(store)) => Some((&**l, c, store)),
                _ => None,
            },
        };
        frame.refine =
            self.refinement
                .update(&mut self.dag, view, self.world, &mut source, clock, budget)?;
        let wants: Vec<(Key, f32)> = self.elevation.take_wants();
        let colour_wants: Vec<(Key, f32)> = self
            .colour
            .as_mut()
            .map(|(_, c)| c.take_wants())
            .unwrap_or_default();
        frame.wanted = wants.len() + colour_wants.len();
        self.elevation.arrived.clear();
        if let Some((_, c)) = &mut self.colour {
            c.arrived.clear();
        }

        let stats = link();
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
        let mut ahead = self.lookahead(&wanted, levels, view.tolerance_px, stores);
        ahead.extend(self.prefetch(view, now, &wanted, stores));
        ahead.sort_by(|a, b| b.1.total_cmp(&a.1));
        ahead.dedup_by_key(|(id, _)| *id);
        ahead.truncate(self.config.prefetch_max);
        // Each layer fetches the diamonds it codes and does not know to be leaves.
        let elevation_ahead = self.elevation.prefetch_keys(
            stores.elevation,
            ahead
                .iter()
                .filter(|(id, _)| self.refiner.is_coded(*id))
                .map(|&(id, p)| (R::key_of(id), p)),
        );
        frame.prefetched = elevation_ahead.len();
        let colour = match (&self.colour, colour_store) {
            (Some((layer, colour)), Some(store)) => {
                let colour_ahead = colour.prefetch_keys(
                    store,
                    ahead.iter().filter_map(|&(id, p)| {
                        let c = layer.colour_id(id)?;
                        layer.is_coded(c).then_some((R::key_of(c), p))
                    }),
                );
                frame.prefetched += colour_ahead.len();
                Some(Submit {
                    wants: colour_wants,
                    prefetch: colour_ahead,
                    package_above: colour
                        .package_above(self.config.package_factor, view.tolerance_px),
                })
            }
            _ => None,
        };
        let elevation = Submit {
            wants,
            prefetch: elevation_ahead,
            package_above: self
                .elevation
                .package_above(self.config.package_factor, view.tolerance_px),
        };
        Ok((frame, Requests { elevation, colour }))
    }

    /// Whether some layer would fetch data for diamond `id` (coded there and not known
    /// to be a leaf).
    fn fetchable(&self, id: R::Id, stores: Stores<'_, R>) -> bool {
        (self.refiner.is_coded(id) && !self.elevation.is_leaf(stores.elevation, R::key_of(id)))
            || match (&self.colour, stores.colour) {
                (Some((layer, state)), Some(store)) => layer
                    .colour_id(id)
                    .is_some_and(|c| layer.is_coded(c) && !state.is_leaf(store, R::key_of(c))),
                _ => false,
            }
    }

    /// The descendants of wanted diamonds that will be wanted once these arrive, while
    /// their projected error (the wanted diamond's times [`StreamCore::child_error_ratio`]
    /// per level) exceeds the tolerance, and that some layer would fetch.
    fn lookahead(
        &self,
        wanted: &HashMap<R::Id, f32>,
        levels: usize,
        tolerance_px: f64,
        stores: Stores<'_, R>,
    ) -> Vec<(R::Id, f32)> {
        if levels == 0 {
            return Vec::new();
        }
        let mut out: HashMap<R::Id, f32> = HashMap::new();
        let mut frontier: Vec<(R::Id, f64, f64)> = wanted
            .iter()
            .map(|(&id, &p)| (id, f64::from(p), self.child_error_ratio(id)))
            .collect();
        for _ in 0..levels {
            let mut next = Vec::new();
            for (id, p, ratio) in frontier {
                let child_error = p * ratio;
                if child_error <= tolerance_px {
                    continue;
                }
                for &c in self.dag.children(id).iter() {
                    if wanted.contains_key(&c) || !self.fetchable(c, stores) {
                        continue;
                    }
                    let e = out.entry(c).or_insert(0.0);
                    if child_error as f32 > *e {
                        *e = child_error as f32;
                        next.push((c, child_error, ratio));
                    }
                }
            }
            frontier = next;
        }
        out.into_iter().collect()
    }

    /// What lookahead expects a child's projected error to be, over `id`'s: `1 /
    /// sqrt(2)` (grid edges halve every two levels, and so do smooth surfaces' bounds),
    /// except with the geometric metric where `id`'s own bound is as large as its
    /// refined parents' (the same side-information class): there, near the finest
    /// levels of rough ground, bounds stop shrinking for levels on end, and its
    /// children are expected to keep it. Lookahead predicting `1 / sqrt(2)` would stop
    /// one level short on each such chain and cost a round trip per level.
    fn child_error_ratio(&self, id: R::Id) -> f64 {
        let own = || self.dag.node(id).and_then(|n| n.class);
        let parents = || {
            self.dag
                .parents(id)
                .into_iter()
                .filter_map(|p| self.dag.node(p)?.class)
                .max()
        };
        lookahead_ratio(self.metric(), own, parents)
    }

    /// Lookahead depth for the link as measured: lookahead hides round trips, which
    /// cost only while the link has room for more answers. There is none while the link
    /// both carries fewer than [`StreamConfig::lookahead_min_blobs`] blobs per round
    /// trip (delivered bandwidth x RTT over the mean blob) *and* queues (answers take
    /// more than 1.25 times the RTT): there the link itself is the bottleneck, and
    /// lookahead answers would queue ahead of wanted ones. A link that does not queue has
    /// room, however little it delivered: the delivered rate of a lightly used link is
    /// what was asked of it, not what it can carry. Before the first estimate: the
    /// configured depth.
    pub fn lookahead_levels_for(&self, stats: &FetchStats) -> usize {
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
        stores: Stores<'_, R>,
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
            .filter(|(id, _)| !wanted.contains_key(id) && self.fetchable(*id, stores))
            .map(|(id, e)| (id, e as f32))
            .collect()
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

    /// Makes the next [`StreamCore::cut_changes`] report the whole cut again.
    pub fn restart_cut_changes(&mut self) {
        self.dag.restart_cut_changes();
    }

    /// A conservative range of the surface's heights (metres), the cut's and the
    /// full-resolution one's: over the cut, each unrefined diamond's grid range widened
    /// by the bound its parent's blob carries for it. Conservative once every cut diamond's bound is known, which is
    /// the case as soon as the roots are refined (the native `Session::warm_up`); before that it is
    /// the root grids' range only, and real peaks may rise above it.
    pub fn height_range(&self) -> (f64, f64) {
        self.height_range_where(|_| true)
    }

    /// [`StreamCore::height_range`] over the cut diamonds `keep` accepts.
    fn height_range_where(&self, keep: impl Fn(&Node<R::Id>) -> bool) -> (f64, f64) {
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

    /// Whether every root is refined.
    pub fn roots_refined(&self) -> bool {
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
}

impl StreamCore<PlanarRefiner> {
    /// The world box of the raster: its extent times [`StreamCore::height_range`].
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

impl StreamCore<SphereRefiner> {
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

/// Details for the refinement from what arrived, the stores, or the network.
struct Source<'a, R: Domain> {
    refiner: &'a R,
    elevation: ElevationSource<'a, R>,
    colour: Option<ColourSource<'a, R>>,
}

/// The elevation layer's state and store, borrowed for a frame.
type ElevationSource<'a, R> = (
    &'a mut LayerState<Details<<R as Refiner>::Id>>,
    &'a dyn Store<Details<<R as Refiner>::Id>>,
);

/// A colour layer, its state and its store, borrowed for a frame.
type ColourSource<'a, R> = (
    &'a ColourLayer<R>,
    &'a mut LayerState<ColourDetails<<R as Refiner>::Id>>,
    &'a dyn Store<ColourDetails<<R as Refiner>::Id>>,
);

impl<R: Domain> DetailSource<R::Id> for Source<'_, R> {
    fn details(&mut self, id: R::Id, priority: f64) -> Availability<R::Id> {
        let refiner = self.refiner;
        let parents = || refiner.parents(id).into_iter().map(R::key_of).collect();
        let (state, store) = &mut self.elevation;
        state.take(*store, R::key_of(id), priority, parents, |d| {
            d.empty_children.iter().map(|&c| R::key_of(c)).collect()
        })
    }

    fn want(&mut self, id: R::Id, priority: f64) {
        let refiner = self.refiner;
        let parents = || refiner.parents(id).into_iter().map(R::key_of).collect();
        let key = R::key_of(id);
        let (state, store) = &mut self.elevation;
        if state.lookup(*store, key, parents).is_none() {
            state.record(*store, key, priority);
        }
    }

    fn colour(
        &mut self,
        _id: R::Id,
        colour: R::Id,
        priority: f64,
    ) -> Arrival<ColourDetails<R::Id>> {
        let Some((layer, state, store)) = &mut self.colour else {
            return Arrival::Ready(None);
        };
        let channel = &layer.channels()[0];
        let parents = || channel.parents(colour).into_iter().map(R::key_of).collect();
        state.take(*store, R::key_of(colour), priority, parents, |d| {
            let children = channel.children(colour).unwrap_or_default();
            d.empty_children(&children)
                .into_iter()
                .map(R::key_of)
                .collect()
        })
    }

    fn want_colour(&mut self, _id: R::Id, colour: R::Id, priority: f64) {
        let Some((layer, state, store)) = &mut self.colour else {
            return;
        };
        let channel = &layer.channels()[0];
        let parents = || channel.parents(colour).into_iter().map(R::key_of).collect();
        let key = R::key_of(colour);
        if state.lookup(*store, key, parents).is_none() {
            state.record(*store, key, priority);
        }
    }
}

/// [`StreamCore::child_error_ratio`] of a diamond of side-information class `own()` whose
/// refined parents' largest class is `parents()` (looked up only for the geometric
/// metric: this runs for every wanted diamond of every frame).
fn lookahead_ratio(
    metric: Metric,
    own: impl FnOnce() -> Option<u8>,
    parents: impl FnOnce() -> Option<u8>,
) -> f64 {
    let halving = std::f64::consts::FRAC_1_SQRT_2;
    if metric != Metric::Geometric {
        return halving;
    }
    match (own(), parents()) {
        (Some(own), Some(parent)) if own >= parent && own > 0 => 1.0,
        _ => halving,
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
    fn lookahead_keeps_a_bound_that_stopped_shrinking() {
        let half = std::f64::consts::FRAC_1_SQRT_2;
        let ratio =
            |m, own: Option<u8>, parents: Option<u8>| lookahead_ratio(m, || own, || parents);
        // As large as its parent's: its children are expected to keep it.
        assert_eq!(ratio(Metric::Geometric, Some(9), Some(9)), 1.0);
        // Shrinking, unknown, zero, or the sampling metric: halving every two levels.
        assert_eq!(ratio(Metric::Geometric, Some(8), Some(9)), half);
        assert_eq!(ratio(Metric::Geometric, Some(9), None), half);
        assert_eq!(ratio(Metric::Geometric, None, Some(9)), half);
        assert_eq!(ratio(Metric::Geometric, Some(0), Some(0)), half);
        assert_eq!(ratio(Metric::Sampling, Some(9), Some(9)), half);
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
