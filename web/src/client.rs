//! The browser's client: the core's [`StreamCore`] (DAG, refinement, lookahead,
//! prefetch) and one [`Planner`] and decoded-details cache per layer, as the native
//! `Session` and its network threads hold them, without the threads. The page sends the
//! requests [`Client::plan`] picks, hands each answer to [`Client::answer`], has the bodies
//! it is told to decode decoded (by a worker's [`crate::decode::AnswerDecoder`]) and hands
//! the result to [`Client::decoded`]; [`Client::frame`] refines.

use std::cell::RefCell;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use glam::DVec3;
use serde_json::{Value, json};

use quincunx_client_core::colour::ColourDetails;
use quincunx_client_core::dag::Half;
use quincunx_client_core::fetch::cache::DecodedCache;
use quincunx_client_core::fetch::planner::{Answer, Planner};
use quincunx_client_core::fetch::{FetchError, FetchStats, Key, Weigh};
use quincunx_client_core::fine::RenderDomain;
use quincunx_client_core::refine::Clock;
use quincunx_client_core::stream::{SessionFrame, Store, Stores, StreamCore, Submit};
use quincunx_client_core::view::View;
use quincunx_decoder::incremental::{Details, Refiner};

use crate::decode::core;
use crate::open::Open;
use crate::wire::{Reader, Wire, WireError, Writer};

/// One layer's data access: the request planner and the decoded cache.
pub struct Layer<T> {
    planner: Planner,
    cache: RefCell<DecodedCache<T>>,
    /// Answers for the next frame (decoded, leaves, cache hits).
    delivered: Vec<(Key, Option<Arc<T>>)>,
    /// Bodies out for decoding, and whether the frame loop wants them reported.
    decoding: HashMap<Key, bool>,
    /// Keys given up since the last frame.
    failed: usize,
    /// Keys given up in all.
    failures: u64,
    /// Wants the planner never saw: answered from the cache (leaves included), as the
    /// native worker counts them.
    cache_hits: u64,
    last_error: Option<String>,
}

impl<T: Weigh> Store<T> for Layer<T> {
    fn is_leaf(&self, key: Key) -> bool {
        self.cache.borrow().is_leaf(key)
    }

    fn cached(&self, key: Key) -> Option<Arc<T>> {
        self.cache.borrow_mut().get(key)
    }

    fn contains(&self, key: Key) -> bool {
        self.cache.borrow().contains(key)
    }
}

impl<T: Weigh> Layer<T> {
    fn new(open: &Open, now: Duration) -> Self {
        Layer {
            planner: Planner::new(open.config.planner(), now),
            cache: RefCell::new(DecodedCache::new(open.config.cache_bytes())),
            delivered: Vec::new(),
            decoding: HashMap::new(),
            failed: 0,
            failures: 0,
            cache_hits: 0,
            last_error: None,
        }
    }

    fn fail(&mut self, key: Key, error: &FetchError) {
        self.failed += 1;
        self.failures += 1;
        self.last_error = Some(format!("{key:?}: {error}"));
    }

    /// An answer: `Some(packaged)` if its body is to be decoded.
    fn answer(
        &mut self,
        key: Key,
        result: Result<(u16, Bytes), FetchError>,
        now: Duration,
    ) -> Option<bool> {
        match self.planner.complete(key, result, now) {
            Answer::Stale | Answer::Failed(None) => None,
            Answer::Failed(Some(e)) => {
                self.fail(key, &e);
                None
            }
            Answer::Leaf { report } => {
                self.cache.borrow_mut().mark_leaf(key);
                if report {
                    self.delivered.push((key, None));
                }
                None
            }
            Answer::Body {
                packaged, report, ..
            } => {
                self.decoding.insert(key, report);
                Some(packaged)
            }
        }
    }

    /// What a worker decoded of `key`'s body.
    fn decoded<R: Refiner>(&mut self, key: Key, bytes: &[u8]) -> Result<(), WireError>
    where
        T: Wire<R>,
    {
        let mut r = Reader::new(bytes);
        let value = T::read(key, &mut r)?;
        let n = r.count(24)?;
        let mut carried = Vec::with_capacity(n);
        for _ in 0..n {
            let k = r.key()?;
            carried.push((k, T::read(k, &mut r)?));
        }
        r.finish()?;
        let report = self.decoding.remove(&key).unwrap_or(false);
        let delivered = &mut self.delivered;
        self.planner
            .store_decoded(self.cache.get_mut(), key, value, carried, report, |k, v| {
                delivered.push((k, Some(v)))
            });
        Ok(())
    }

    fn decode_failed(&mut self, key: Key, reason: String, now: Duration) {
        let report = self.decoding.remove(&key).unwrap_or(false);
        if let Some(e) = self.planner.decode_failed(key, reason, now, report) {
            self.fail(key, &e);
        }
    }

    /// A frame's requests: wants held here are answered at once (next frame), the rest
    /// go to the planner.
    fn submit(&mut self, submit: Submit, now: Duration) {
        let (held, wants, prefetch) = self
            .cache
            .get_mut()
            .answer_held(submit.wants, submit.prefetch);
        self.cache_hits += held.len() as u64;
        self.delivered.extend(held);
        self.planner
            .submit(&wants, &prefetch, submit.package_above, now);
    }

    /// The keys to request now; keys answered and out for decoding (in a worker, while
    /// the frame loop may want them again) are held, not requested twice.
    fn plan(&mut self, now: Duration, out: &mut Vec<(u8, Key, bool)>, layer: u8) {
        let planned = {
            let cache = self.cache.borrow();
            let decoding = &self.decoding;
            self.planner.plan(now, usize::MAX, |k| {
                cache.is_leaf(k) || cache.contains(k) || decoding.contains_key(&k)
            })
        };
        for p in planned {
            self.planner.sent(p, now);
            out.push((layer, p.key, p.packaged));
        }
    }

    fn stats(&mut self) -> FetchStats {
        let mut s = self.planner.stats().clone();
        s.cache_hits = self.cache_hits;
        s
    }
}

/// A streaming session in domain `R`.
pub struct Client<R: RenderDomain> {
    core: StreamCore<R>,
    elevation: Layer<Details<R::Id>>,
    colour: Option<Layer<ColourDetails<R::Id>>>,
    last: Option<SessionFrame>,
}

/// A failure the page shows.
pub type WebError = String;

/// Milliseconds from the page (`performance.now()`) as a duration.
pub fn ms(t: f64) -> Result<Duration, WebError> {
    // `max` would turn a NaN into 0.
    if t.is_nan() {
        return Err("time NaN ms".into());
    }
    Duration::try_from_secs_f64(t.max(0.0) / 1000.0)
        .map_err(|_| format!("time {t} ms is not a duration"))
}

impl<R: RenderDomain> Client<R>
where
    Details<R::Id>: Wire<R>,
    ColourDetails<R::Id>: Wire<R>,
{
    /// The session `open` describes, at time `now`.
    pub fn new(open: &Open, now: Duration) -> Result<Self, WebError> {
        if open.elevation.meta.channels.len() != 1 {
            return Err(format!(
                "repository {:?} has {} channels: open it as the colour layer of an elevation session",
                open.elevation.name,
                open.elevation.meta.channels.len()
            ));
        }
        let core = core::<R>(open)?;
        let colour = core.colour_layer().map(|_| Layer::new(open, now));
        Ok(Client {
            core,
            elevation: Layer::new(open, now),
            colour,
            last: None,
        })
    }

    /// The core (DAG, refinement).
    pub fn core(&self) -> &StreamCore<R> {
        &self.core
    }

    /// An answer to a request of `layer`: `Ok(Some(packaged))` when its body is to be
    /// decoded (then [`Client::decoded`] or [`Client::decode_failed`]).
    pub fn answer(
        &mut self,
        layer: u8,
        key: Key,
        result: Result<(u16, Bytes), FetchError>,
        now: Duration,
    ) -> Result<Option<bool>, WebError> {
        match (layer, &mut self.colour) {
            (0, _) => Ok(self.elevation.answer(key, result, now)),
            (1, Some(c)) => Ok(c.answer(key, result, now)),
            _ => Err(format!("no layer {layer}")),
        }
    }

    /// A worker's decoding of `key`'s body ([`crate::decode::AnswerDecoder::decode`]).
    pub fn decoded(
        &mut self,
        layer: u8,
        key: Key,
        bytes: &[u8],
        now: Duration,
    ) -> Result<(), WebError> {
        let result = match (layer, &mut self.colour) {
            (0, _) => self.elevation.decoded::<R>(key, bytes),
            (1, Some(c)) => c.decoded::<R>(key, bytes),
            _ => return Err(format!("no layer {layer}")),
        };
        // A malformed buffer is the worker's failure to decode.
        if let Err(e) = result {
            self.decode_failed(layer, key, e.to_string(), now)?;
        }
        Ok(())
    }

    /// A worker refused `key`'s body.
    pub fn decode_failed(
        &mut self,
        layer: u8,
        key: Key,
        reason: String,
        now: Duration,
    ) -> Result<(), WebError> {
        match (layer, &mut self.colour) {
            (0, _) => self.elevation.decode_failed(key, reason, now),
            (1, Some(c)) => c.decode_failed(key, reason, now),
            _ => return Err(format!("no layer {layer}")),
        }
        Ok(())
    }

    /// One frame: takes what arrived, refines and coarsens within `budget` (read from
    /// `clock`), and tells the planners what is wanted.
    pub fn frame(
        &mut self,
        view: &View,
        now: Duration,
        budget: Duration,
        clock: &dyn Clock,
    ) -> Result<SessionFrame, WebError> {
        let started = clock.now();
        for (k, d) in self.elevation.delivered.drain(..) {
            self.core.arrived(k, d);
        }
        let mut failed = std::mem::take(&mut self.elevation.failed);
        if let Some(c) = &mut self.colour {
            for (k, d) in c.delivered.drain(..) {
                self.core.colour_arrived(k, d);
            }
            failed += std::mem::take(&mut c.failed);
        }
        let link = self.elevation.stats();
        let stores = Stores {
            elevation: &self.elevation,
            colour: self
                .colour
                .as_ref()
                .map(|c| c as &dyn Store<ColourDetails<R::Id>>),
        };
        let (mut frame, requests) = self
            .core
            .frame(view, now, budget, clock, stores, || link)
            .map_err(|e| e.to_string())?;
        frame.failed = failed;
        self.elevation.submit(requests.elevation, now);
        if let (Some(c), Some(submit)) = (&mut self.colour, requests.colour) {
            c.submit(submit, now);
        }
        frame.elapsed = clock.now().saturating_sub(started);
        self.last = Some(frame.clone());
        Ok(frame)
    }

    /// The requests to send now, `(layer, key, packaged)`, most urgent first; each is
    /// counted as sent.
    pub fn plan(&mut self, now: Duration) -> Vec<(u8, Key, bool)> {
        let mut out = Vec::new();
        self.elevation.plan(now, &mut out, 0);
        if let Some(c) = &mut self.colour {
            c.plan(now, &mut out, 1);
        }
        out
    }

    /// When the planners next want to act without an answer or a frame (a retry's
    /// backoff, the cap's bucket), if ever.
    pub fn wake_at(&self, now: Duration) -> Option<Duration> {
        let c = self.colour.as_ref().and_then(|c| c.planner.wake_at(now));
        match (self.elevation.planner.wake_at(now), c) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// What entered and left the cut since the last call: `u32 left, (key, u8 half)*,
    /// u32 entered, patch*`; a patch is `key, u8 half, i64 generation, u32 level, u8
    /// affine?, i64 base[3] e1[3] e2[3], i64 corners[12], i32s grid, u32 colour channels,
    /// i32s per channel` (see `web-demo/js/wasm.mjs`).
    pub fn cut_changes(&mut self) -> Vec<u8> {
        let changes = self.core.cut_changes();
        let refiner = Arc::clone(self.core.refiner());
        let mut w = Writer::default();
        w.count(changes.left.len());
        for (id, half) in changes.left {
            w.key(R::key_of(id));
            w.u8(half_byte(half));
        }
        w.count(changes.entered.len());
        for p in changes.entered {
            w.key(R::key_of(p.id));
            w.u8(half_byte(p.half));
            w.i64(i64::try_from(p.generation).unwrap_or(i64::MAX));
            w.u32(refiner.level_of(p.id));
            match refiner.affine(p.id, &p.corners, p.half) {
                Some(a) => {
                    w.u8(1);
                    for v in [a.base, a.e1, a.e2] {
                        w.key(v);
                    }
                }
                None => w.u8(0),
            }
            for c in p.corners {
                w.key(c);
            }
            w.i32s(&p.grid);
            match &p.colour {
                Some(c) => {
                    w.count(c.len());
                    for ch in c.iter() {
                        w.i32s(ch);
                    }
                }
                None => w.count(0),
            }
        }
        w.out
    }

    /// Makes the next [`Client::cut_changes`] report the whole cut.
    pub fn restart_cut_changes(&mut self) {
        self.core.restart_cut_changes();
    }

    /// Sets the most halves the cut may hold.
    pub fn set_max_cut_halves(&mut self, max: Option<usize>) {
        self.core.set_max_cut_halves(max);
    }

    /// What the page's world needs: the renderer's frame, the colour scales, sizes.
    pub fn info(&self) -> Value {
        let refiner = self.core.refiner();
        let layer = self.core.colour_layer();
        let colour_n = layer.map_or(0, |l| l.n());
        let frame = refiner.world_frame(&self.core.world(), colour_n);
        let geometry = match frame.geometry {
            quincunx_client_core::fine::Geometry::Planar {
                metres_per_fine,
                extent_fine,
            } => {
                json!({"kind": "planar", "metresPerFine": metres_per_fine, "extentFine": extent_fine})
            }
            quincunx_client_core::fine::Geometry::Planet {
                radius_m,
                half_side_fine,
            } => json!({"kind": "planet", "radiusM": radius_m, "halfSideFine": half_side_fine}),
        };
        json!({
            "frame": {
                "geometry": geometry,
                "valueScaleM": frame.value_scale_m,
                "valueOffsetM": frame.value_offset_m,
                "n": frame.n,
                "colourN": frame.colour_n,
            },
            "metric": self.core.metric().name(),
        })
    }

    /// Figures for the page's panel and the tests.
    pub fn stats(&mut self) -> Value {
        let mut fetch = self.elevation.stats();
        let mut failures = self.elevation.failures;
        let mut last_error = self.elevation.last_error.clone();
        let mut decoding = self.elevation.decoding.len();
        let mut cache_bytes = self.elevation.cache.borrow().used_bytes();
        if let Some(c) = &mut self.colour {
            fetch.add(&c.stats());
            failures += c.failures;
            last_error = c.last_error.clone().or(last_error);
            decoding += c.decoding.len();
            cache_bytes += c.cache.borrow().used_bytes();
        }
        // And the diamonds refinement took from the caches itself, as `Session` counts.
        fetch.cache_hits += self.core.cache_hits();
        let e = &fetch.errors;
        let dag = self.core.dag();
        let n = self.core.refiner().n();
        let frame = self.last.as_ref();
        json!({
            "patches": dag.cut_len(),
            "triangles": dag.cut_len() * n * n,
            "requests": fetch.requests,
            "responses": fetch.responses,
            "bytesReceived": fetch.bytes_fetched,
            "leaves": fetch.leaves,
            "carried": fetch.carried,
            "cacheHits": fetch.cache_hits,
            "requestsInFlight": fetch.in_flight,
            "queued": fetch.queued,
            "window": fetch.window,
            "bandwidthBitS": fetch.bandwidth_bit_s,
            "rttMs": fetch.rtt.map(|d| d.as_secs_f64() * 1000.0),
            "decoding": decoding,
            "errors": {
                "clientStatus": e.client_status,
                "serverStatus": e.server_status,
                "connection": e.connection,
                "protocol": e.protocol,
                "timeout": e.timeout,
                "decode": e.decode,
                "total": e.client_status + e.server_status + e.connection + e.protocol
                    + e.timeout + e.decode + e.tls,
            },
            "failures": failures,
            "lastError": last_error,
            "dagNodes": dag.len(),
            "dagBytes": dag.memory_bytes(),
            "cacheBytes": cache_bytes,
            "frame": frame.map(|f| json!({
                "refined": f.refine.refined,
                "coarsened": f.refine.coarsened,
                "pending": f.refine.pending,
                "overBudget": f.refine.over_budget,
                "maxErrorPx": f.refine.max_error_px,
                "outOfTime": f.refine.out_of_time,
                "reused": f.refine.reused,
                "converged": f.refine.converged,
                "fullQuality": f.refine.full_quality && f.wanted == 0,
                "settled": f.refine.settled() && f.wanted == 0,
                "wanted": f.wanted,
                "prefetched": f.prefetched,
                "failed": f.failed,
                "elapsedMs": f.elapsed.as_secs_f64() * 1000.0,
            })),
        })
    }

    /// A conservative range of the cut's heights, metres.
    pub fn height_range(&self) -> (f64, f64) {
        self.core.height_range()
    }

    /// The crack and coverage check of the cut.
    pub fn check_cut(&self) -> Value {
        let c = self.core.dag().check_cut();
        json!({
            "ok": c.ok(),
            "halves": c.halves,
            "countedHalves": c.counted_halves,
            "sharedVertices": c.shared_vertices,
            "cracks": c.cracks,
            "colourShared": c.colour_shared,
            "colourCracks": c.colour_cracks,
            "probes": c.probes,
            "uncovered": c.uncovered,
            "overlaps": c.overlaps,
        })
    }
}

fn half_byte(h: Half) -> u8 {
    match h {
        Half::Lower => 0,
        Half::Upper => 1,
    }
}

/// A camera from the page: float64 world metres, as `View` takes it.
#[derive(Clone, Copy, Debug)]
pub struct Camera {
    /// Eye.
    pub position: DVec3,
    /// Looking along.
    pub forward: DVec3,
    /// Up.
    pub up: DVec3,
    /// Vertical field of view, radians.
    pub fov_y_rad: f64,
}

/// The view of `camera` for a viewport and tolerance, if every number is usable.
pub fn view_of(camera: Camera, viewport_px: [u32; 2], tolerance_px: f64) -> Result<View, WebError> {
    let finite = camera.position.is_finite() && camera.forward.is_finite() && camera.up.is_finite();
    if !finite || camera.forward.length_squared() == 0.0 {
        return Err(
            "the camera's position, forward and up must be finite, forward non-zero".into(),
        );
    }
    if !(camera.fov_y_rad.is_finite()
        && camera.fov_y_rad > 0.0
        && camera.fov_y_rad < std::f64::consts::PI)
    {
        return Err(format!("field of view {} rad", camera.fov_y_rad));
    }
    if !(tolerance_px.is_finite() && tolerance_px > 0.0) {
        return Err(format!("tolerance {tolerance_px} px"));
    }
    if viewport_px.contains(&0) {
        return Err("an empty viewport".into());
    }
    Ok(View {
        eye: camera.position,
        target: camera.position + camera.forward,
        up: camera.up,
        fov_y_rad: camera.fov_y_rad,
        viewport_px,
        tolerance_px,
    })
}
