//! Time-budgeted dual-queue refinement (the paper's section 4.2, after ROAM).
//!
//! Each frame:
//! 1. **Split queue.** The cut's diamonds whose projected error exceeds the tolerance, most
//!    urgent first.
//!    - A diamond is refined once its parents are refined; missing parents are refined
//!      first.
//!    - Details come from a [`DetailSource`]; when they have not arrived yet, the diamond
//!      waits and others go ahead.
//! 2. **Merge queue.** Refined diamonds whose error is below the tolerance (with
//!    hysteresis), or that are off-screen, and whose children are unrefined, are coarsened,
//!    least urgent first.
//!
//! The frame stops when the budget is spent. The DAG stays consistent after every single
//! operation, so the cut is crack-free whenever the frame ends.
//!
//! **Error**, in pixels, measured at the nearest point of the diamond's bounding box (its
//! footprint times its height range, widened by the side-information bound its parent's
//! blob carries, which makes it conservative for culling), by [`Metric`]:
//! - [`Metric::Geometric`] (the default): the diamond's error bound (the side information:
//!   how far the finest decoded surface, and every one between, departs from the surface
//!   it draws; `docs/blob-format.md`) projected there, times the box's off-axis factor
//!   ([`View::off_axis_factor_of`]: a vertical step off the view's axis looks larger), so
//!   a tolerance of 1 px means no point of the surface drawn is more than 1 px from where
//!   the full-resolution surface would put it. With a colour layer, the larger of that and the projected size
//!   of its texels (the texel rule: a colour texel is at most the tolerance).
//! - [`Metric::Sampling`] (the paper's): `max(edge, texel)`, the mean projected edge length
//!   of its grid and, with a colour layer, the projected size of its texels. The side
//!   information bound then only skips refinement of flat regions: when refining could
//!   move the surface by less than [`RefineConfig::flat_fraction`] of the tolerance.

use std::cell::RefCell;
use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashSet};
use std::sync::Arc;
use std::time::Duration;

use glam::DVec3;
use quincunx_decoder::diamond::PlanarId;
use quincunx_decoder::entropy::class_bound;
use quincunx_decoder::incremental::Details;

use crate::colour::ColourDetails;
use crate::dag::{Dag, DagError, IdMap};
use crate::domain::{Domain, World};
use crate::view::{Frustum, View};

/// Whether a diamond's data (decoded details of one layer) is here.
#[derive(Clone, Debug)]
pub enum Arrival<T> {
    /// Arrived: decoded details, or `None` for a diamond without a blob (zero details).
    Ready(Option<Arc<T>>),
    /// Requested (or queued) and not here yet.
    Pending,
}

/// Whether a diamond's elevation details are here.
pub type Availability<I = PlanarId> = Arrival<Details<I>>;

/// Where details come from: the data access layer (network thread, caches) or, in tests
/// and local apps, a repository in memory.
pub trait DetailSource<I = PlanarId> {
    /// The details of `id` if they are here; otherwise records that they are wanted with
    /// this priority (higher first) and returns [`Availability::Pending`].
    fn details(&mut self, id: I, priority: f64) -> Availability<I>;

    /// Records that `id` is wanted with this priority without using its details: called
    /// for the split queue's diamonds a frame had no time left for, so the data access
    /// layer keeps requesting them. The default asks [`DetailSource::details`] and drops
    /// the answer.
    fn want(&mut self, id: I, priority: f64) {
        let _ = self.details(id, priority);
    }

    /// The colour details of colour diamond `colour` (refining elevation diamond `id`),
    /// like [`DetailSource::details`]. Asked only with a colour layer, for diamonds the
    /// colour repository codes. The default has none (zero details).
    fn colour(&mut self, id: I, colour: I, priority: f64) -> Arrival<ColourDetails<I>> {
        let _ = (id, colour, priority);
        Arrival::Ready(None)
    }

    /// Records that colour diamond `colour` is wanted (see [`DetailSource::want`]).
    fn want_colour(&mut self, id: I, colour: I, priority: f64) {
        let _ = self.colour(id, colour, priority);
    }
}

/// A monotonic clock, passed in so refinement is testable deterministically.
pub trait Clock {
    /// Time since an arbitrary origin.
    fn now(&self) -> Duration;
}

/// What a diamond's error is: what the tolerance in pixels bounds (see the module docs).
/// Serialised by its [`Metric::name`].
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(into = "String", try_from = "String")]
pub enum Metric {
    /// The projected geometric error bound of the blobs' side information (with colour,
    /// at least the projected texel size).
    #[default]
    Geometric,
    /// The projected grid spacing (and texel size): sampling density, whatever the data.
    Sampling,
}

impl Metric {
    /// Every metric.
    pub const ALL: [Metric; 2] = [Metric::Geometric, Metric::Sampling];

    /// The metric's name on the command line, in reports and in figures.
    pub fn name(self) -> &'static str {
        match self {
            Metric::Geometric => "geometric",
            Metric::Sampling => "sampling",
        }
    }
}

impl From<Metric> for String {
    fn from(m: Metric) -> String {
        m.name().to_string()
    }
}

impl TryFrom<String> for Metric {
    type Error = String;

    fn try_from(s: String) -> Result<Self, Self::Error> {
        s.parse()
    }
}

impl std::fmt::Display for Metric {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Metric {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Metric::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| format!("unknown metric {s:?} (geometric or sampling)"))
    }
}

/// Tuning of refinement.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RefineConfig {
    /// What the tolerance bounds: the projected geometric error (the default) or the
    /// projected sampling density.
    pub metric: Metric,
    /// Coarsen when the error is below `tolerance * hysteresis`. Below 1 it keeps
    /// diamonds that hover around the tolerance from being refined and coarsened in turn
    /// while the camera jitters, at the price of a cut that depends on the path taken;
    /// 1 (the default) makes the cut a function of the view alone.
    pub hysteresis: f64,
    /// Skip refining where the side information bounds the change of the surface below
    /// this fraction of the tolerance (flat regions).
    pub flat_fraction: f64,
    /// Memory budget of the DAG ([`Dag::memory_bytes`]): no refinement that would exceed
    /// it, and while it is exceeded (a smaller budget, or a view that needs more),
    /// coarsening of what matters least: off-screen diamonds first, then the smallest
    /// projected errors. `None`: only the view bounds memory.
    pub max_dag_bytes: Option<usize>,
    /// Most halves in the cut (patches a renderer draws): no refinement that would exceed
    /// it, and while it is exceeded, coarsening of what matters least, as for
    /// `max_dag_bytes`. A renderer whose GPU pool holds `n` patches sets `n`, so the cut
    /// it is given always fits: a tolerance finer than the pool allows then draws the
    /// finest cut that fits, never one with patches left out. `None`: only the view
    /// bounds the cut.
    pub max_cut_halves: Option<usize>,
}

impl Default for RefineConfig {
    fn default() -> Self {
        RefineConfig {
            metric: Metric::default(),
            hysteresis: 1.0,
            flat_fraction: 0.1,
            max_dag_bytes: None,
            max_cut_halves: None,
        }
    }
}

/// What one frame did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameStats {
    /// Diamonds refined.
    pub refined: usize,
    /// Diamonds coarsened.
    pub coarsened: usize,
    /// Diamonds waiting for their details.
    pub pending: usize,
    /// Diamonds in the DAG and halves in the cut after the frame.
    pub dag_nodes: usize,
    /// Halves in the cut after the frame.
    pub cut_halves: usize,
    /// DAG memory after the frame ([`Dag::memory_bytes`]).
    pub dag_bytes: usize,
    /// A budget (DAG memory or cut halves) held refinement back or forced coarsening this
    /// frame: the frame is then not at full quality (`converged` may still say nothing
    /// more can be done).
    pub over_budget: bool,
    /// Largest projected error of a visible cut diamond that still wants refining (0 when
    /// the cut meets the tolerance).
    pub max_error_px: f64,
    /// The budget ran out before both queues were empty.
    pub out_of_time: bool,
    /// Nothing left to do for this view: every visible diamond meets the tolerance (or is
    /// as fine as the repository), nothing waits for data and nothing is left to coarsen.
    pub converged: bool,
    /// Full quality: every visible diamond meets the tolerance (or is as fine as the
    /// repository) and nothing waits for data; coarsening may still be going on.
    pub full_quality: bool,
    /// Time used.
    pub elapsed: Duration,
    /// The frame was the previous one again (same view, world, tuning and DAG after a
    /// frame that changed nothing and waited for nothing): its figures, not run.
    pub reused: bool,
}

impl FrameStats {
    /// As good as it gets: full quality, or, where a budget holds refinement back, the
    /// best cut the budgets allow (converged, and the frame changed nothing: a frame that
    /// coarsened to make room may refine more in the next).
    pub fn settled(&self) -> bool {
        self.full_quality
            || (self.over_budget && self.converged && self.refined == 0 && self.coarsened == 0)
    }
}

/// An `f64` ordered for the heaps (NaN never occurs: errors are finite by construction).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Key<I>(f64, I);

impl<I: PartialEq> Eq for Key<I> {}

impl<I: Ord> PartialOrd for Key<I> {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl<I: Ord> Ord for Key<I> {
    fn cmp(&self, other: &Self) -> Ordering {
        self.0
            .total_cmp(&other.0)
            .then_with(|| self.1.cmp(&other.1))
    }
}

/// How a diamond looks from the camera.
#[derive(Clone, Copy, Debug)]
pub struct Appearance {
    /// Projected error by the [`Metric`], pixels.
    pub error_px: f64,
    /// Inside the frustum (conservatively).
    pub visible: bool,
    /// The side information says refining cannot change the picture.
    pub flat: bool,
    /// How much closer the camera can come before the diamond could want refining
    /// (metres; 0 when it already would if visible).
    pub margin_m: f64,
}

/// Projects diamonds for one view.
struct Projector<'a, W, I> {
    view: &'a View,
    frustum: Frustum,
    world: W,
    config: RefineConfig,
    /// Pixels per metre at 1 m.
    px_at_1m: f64,
    /// The viewport's largest off-axis factor ([`View::off_axis_factor`]).
    off_axis: f64,
    /// Pixels below which a surface change is invisible (flat regions).
    flat_px: f64,
    /// Appearances computed under this view, world and tuning, with the generation of
    /// the node they were computed for (a node's appearance changes only with it).
    seen: RefCell<Appearances<I>>,
}

impl<W: World, I: Copy + Eq + std::hash::Hash> Projector<'_, W, I> {
    fn appearance<R: Domain<World = W, Id = I>>(&self, dag: &Dag<R>, id: I) -> Appearance {
        let Some(node) = dag.node(id) else {
            return self.measure(dag, id);
        };
        if let Some(&(generation, a)) = self.seen.borrow().get(&id)
            && generation == node.generation
        {
            return a;
        }
        let a = self.measure(dag, id);
        self.seen.borrow_mut().insert(id, (node.generation, a));
        a
    }

    fn measure<R: Domain<World = W, Id = I>>(&self, dag: &Dag<R>, id: I) -> Appearance {
        let Some(node) = dag.node(id) else {
            return Appearance {
                error_px: 0.0,
                visible: false,
                flat: true,
                margin_m: f64::INFINITY,
            };
        };
        let w = &self.world;
        let bound_m = node.bound_m(w);
        let z = node.height_bounds_m(w);
        let (bbox, edge_m) = dag.refiner().footprint(w, id, &node.corners, z);
        let texels = dag.texels_per_edge();
        let texel_m = if texels > 0.0 { edge_m / texels } else { 0.0 };
        let distance_m = bbox.distance(self.view.eye).max(View::NEAR_M);
        let px_per_m = self.px_at_1m / distance_m;
        let (error_m, flat, mut trigger_m);
        match self.config.metric {
            Metric::Geometric => {
                // The bound, 0 below the data's finest level (nothing finer is coded
                // there; procedural detail is not counted). A vertical step of that size
                // at the box's nearest point, off the view's axis, looks up to the box's
                // off-axis factor larger than on it; the box's factor changes as the
                // camera turns, so deferrals assume the viewport's largest. Unknown (the
                // roots, or blobs without side information): the sampling error.
                let (geometric_m, most_m) = if !dag.refiner().is_coded(id) {
                    (0.0, 0.0)
                } else {
                    match node.bound_class {
                        Some(k) => {
                            let b = class_bound(k) as f64 * w.value_scale_m().abs();
                            (b * self.view.off_axis_factor_of(&bbox), b * self.off_axis)
                        }
                        None => (edge_m, edge_m),
                    }
                };
                // The texel rule where refining brings colour data (not below the colour
                // layer's finest level, nor outside it).
                let texel_m = if dag.colour_blob_id(id).is_some() {
                    texel_m
                } else {
                    0.0
                };
                error_m = geometric_m.max(texel_m);
                flat = false;
                trigger_m = most_m.max(texel_m) * self.px_at_1m / self.view.tolerance_px;
            }
            Metric::Sampling => {
                // max(edge, texel): texels are edges divided by the texels per edge.
                error_m = if node.colour.is_some() {
                    edge_m.max(texel_m)
                } else {
                    edge_m
                };
                // Flatness speaks for the heights only: with colour, the texels decide.
                flat = node.class.is_some()
                    && node.colour.is_none()
                    && bound_m * px_per_m < self.flat_px;
                // Refining needs error > tolerance and (with a known class) no flatness:
                // both only grow as the camera comes closer.
                trigger_m = error_m * self.px_at_1m / self.view.tolerance_px;
                if node.class.is_some() && node.colour.is_none() {
                    trigger_m = trigger_m.min(bound_m * self.px_at_1m / self.flat_px);
                }
            }
        }
        Appearance {
            error_px: error_m * px_per_m,
            visible: self.frustum.intersects(&bbox)
                && !dag
                    .refiner()
                    .hidden(w, id, &node.corners, z.1, self.view.eye),
            flat,
            margin_m: (distance_m - trigger_m).max(0.0),
        }
    }

    fn wants_split(&self, a: &Appearance) -> bool {
        a.visible && !a.flat && a.error_px > self.view.tolerance_px
    }

    fn allows_merge(&self, a: &Appearance) -> bool {
        !a.visible || a.flat || a.error_px < self.view.tolerance_px * self.config.hysteresis
    }

    /// None of `id`'s children wants refining: coarsening `id` takes nothing a split
    /// would bring back at once.
    fn children_calm<R: Domain<World = W, Id = I>>(&self, dag: &Dag<R>, id: I) -> bool {
        dag.children(id).iter().all(|&c| {
            dag.node(c)
                .is_none_or(|_| !self.wants_split(&self.appearance(dag, c)))
        })
    }
}

/// Refinement state kept across frames.
///
/// Deferred evaluation (after ROAM's deferred priority recomputation): an unrefined
/// diamond that does not want refining stays that way until the camera has travelled
/// far enough to bring it within the distance where its projected error (and its side
/// information bound) could exceed the tolerance. Such diamonds are not re-evaluated
/// before then, unless the diamond itself changed or the projection did (field of view,
/// viewport, tolerance, world mapping, metric). Visibility does not matter for them: a diamond
/// that does not want refining when visible does not when hidden either.
#[derive(Clone, Debug)]
pub struct Refinement<I = PlanarId> {
    /// Tuning.
    pub config: RefineConfig,
    /// Camera travel so far (metres) and the last eye position.
    travel_m: f64,
    last_eye: Option<DVec3>,
    /// What the deferrals were computed under.
    projection: Option<Projection>,
    /// Per diamond: the travel at which to look again, and its generation then.
    deferred: IdMap<(f64, u64), I>,
    /// The last frame, when it changed nothing and waited for nothing: what it was run
    /// under (view, world, tuning, [`Dag::changes`]) and its figures. A frame under the
    /// same is the same, so it is not run again: a held camera costs nothing per frame.
    quiet: Option<Quiet>,
    /// The appearances of the last frame and what they were computed under: a held
    /// camera (a jump waiting for its data) projects only the diamonds that changed.
    seen: Option<(Seen, Appearances<I>)>,
}

/// What deferrals depend on: field of view, viewport, tolerance, world mapping, metric.
type Projection = (f64, [u32; 2], f64, [f64; 4], Metric);

/// What appearances depend on besides the node.
type Seen = (View, [f64; 4], RefineConfig);

/// Appearances by diamond, with the node generation each was computed for.
type Appearances<I> = IdMap<(u64, Appearance), I>;

/// What a quiet frame ran under, and its figures.
#[derive(Clone, Copy, Debug)]
struct Quiet {
    under: Seen,
    changes: u64,
    stats: FrameStats,
}

impl<I> Default for Refinement<I> {
    fn default() -> Self {
        Refinement {
            config: RefineConfig::default(),
            travel_m: 0.0,
            last_eye: None,
            projection: None,
            deferred: IdMap::default(),
            quiet: None,
            seen: None,
        }
    }
}

impl<I: Copy + Eq + Ord + std::hash::Hash + std::fmt::Debug> Refinement<I> {
    /// Refinement with `config` and nothing deferred yet.
    pub fn with_config(config: RefineConfig) -> Refinement<I> {
        Refinement {
            config,
            ..Refinement::default()
        }
    }

    /// Accumulates camera travel; forgets every deferral when the projection changed.
    fn track_camera(&mut self, view: &View, world: &impl World) {
        let projection = (
            view.fov_y_rad,
            view.viewport_px,
            view.tolerance_px,
            world.fingerprint(),
            self.config.metric,
        );
        if self.projection != Some(projection) {
            self.projection = Some(projection);
            self.deferred.clear();
        }
        if let Some(last) = self.last_eye {
            self.travel_m += (view.eye - last).length();
        }
        self.last_eye = Some(view.eye);
    }
}

impl<I: Copy + Eq + Ord + std::hash::Hash + std::fmt::Debug> Refinement<I> {
    fn projector<'a, W: World>(&self, view: &'a View, world: W) -> Projector<'a, W, I> {
        Projector {
            view,
            frustum: view.frustum(),
            world,
            config: self.config,
            px_at_1m: view.px_per_m(1.0),
            off_axis: view.off_axis_factor(),
            flat_px: self.config.flat_fraction * view.tolerance_px,
            seen: RefCell::default(),
        }
    }

    /// How diamond `id` of the DAG looks from `view` (what refinement decides by).
    pub fn appearance<R: Domain<Id = I>>(
        &self,
        dag: &Dag<R>,
        view: &View,
        world: R::World,
        id: I,
    ) -> Appearance {
        self.projector(view, world).appearance(dag, id)
    }

    /// The unrefined diamonds of the DAG that `view` would want refined, with their
    /// projected errors: for prefetching along a predicted camera. Changes nothing.
    pub fn wanted_splits<R: Domain<Id = I>>(
        &self,
        dag: &Dag<R>,
        view: &View,
        world: R::World,
    ) -> Vec<(I, f64)> {
        let projector = self.projector(view, world);
        dag.nodes()
            .filter(|n| n.refined.is_none() && dag.refiner().is_refinable(n.id))
            .filter_map(|n| {
                let a = projector.appearance(dag, n.id);
                projector.wants_split(&a).then_some((n.id, a.error_px))
            })
            .collect()
    }
}

/// Whether `extra` more halves would take the cut over `max`.
fn cut_over<R: Domain>(dag: &Dag<R>, max: Option<usize>, extra: usize) -> bool {
    max.is_some_and(|m| dag.cut_len() + extra > m)
}

/// Coarsens `id` unless the deadline has passed (then `None`, and the frame is out of
/// time); returns its parents that became coarsenable.
fn coarsen_in_time<R: Domain>(
    dag: &mut Dag<R>,
    id: R::Id,
    clock: &dyn Clock,
    deadline: Duration,
    stats: &mut FrameStats,
) -> Result<Option<Vec<R::Id>>, DagError> {
    // The frame's first coarsening runs even past the deadline (building the queue may
    // have taken the budget), so coarsening makes progress too.
    if stats.coarsened > 0 && clock.now() >= deadline {
        stats.out_of_time = true;
        return Ok(None);
    }
    dag.coarsen(id)?;
    stats.coarsened += 1;
    let mut parents = dag.parents(id);
    parents.retain(|&p| dag.is_coarsenable(p));
    Ok(Some(parents))
}

enum Outcome {
    Done,
    Pending,
    Impossible,
    /// Its parents refined, the diamond no longer wants splitting (its bound, in its
    /// owner's blob, turned out smaller than the parent's it was judged by).
    Unwanted,
}

impl<I: Copy + Eq + Ord + std::hash::Hash + std::fmt::Debug> Refinement<I> {
    /// Runs one frame: splits and merges until both queues are empty or `budget` is
    /// spent (checked between operations against `clock`).
    pub fn update<R: Domain<Id = I>>(
        &mut self,
        dag: &mut Dag<R>,
        view: &View,
        world: R::World,
        source: &mut dyn DetailSource<I>,
        clock: &dyn Clock,
        budget: Duration,
    ) -> Result<FrameStats, DagError> {
        let start = clock.now();
        let deadline = start + budget;
        let under: Seen = (*view, world.fingerprint(), self.config);
        if let Some(q) = self
            .quiet
            .as_ref()
            .filter(|q| q.under == under && q.changes == dag.changes())
        {
            return Ok(FrameStats {
                elapsed: clock.now().saturating_sub(start),
                reused: true,
                ..q.stats
            });
        }
        let mut projector = self.projector(view, world);
        if let Some((seen_under, seen)) = self.seen.take()
            && seen_under == under
        {
            projector.seen = RefCell::new(seen);
        }
        let mut stats = FrameStats::default();
        // The error of the split the cut budget refused this frame.
        let mut blocked = None;

        self.track_camera(view, &world);
        // Split queue: the cut's diamonds that want refining, most urgent first.
        let travel = self.travel_m;
        let mut splits = BinaryHeap::new();
        for n in dag.nodes() {
            if n.refined.is_some() || !dag.refiner().is_refinable(n.id) {
                continue;
            }
            if self
                .deferred
                .get(&n.id)
                .is_some_and(|&(at, generation)| generation == n.generation && travel < at)
            {
                continue;
            }
            let a = projector.appearance(dag, n.id);
            if projector.wants_split(&a) {
                splits.push(Key(a.error_px, n.id));
            } else if a.margin_m > 0.0 {
                self.deferred
                    .insert(n.id, (travel + a.margin_m, n.generation));
            }
        }
        if self.deferred.len() > 4 * dag.len() + 1024 {
            self.deferred.retain(|id, _| dag.node(*id).is_some());
        }
        let mut waiting = 0;
        // The first split runs even when building the queue took the whole budget, so
        // every frame makes progress (and a budget-limited cut can settle).
        let mut worked = false;
        // The ancestors the frame's splits needed (refined or waiting for data): neither
        // merged nor evicted to make room, or they would be refined again next frame.
        let mut needed = HashSet::new();
        while let Some(Key(error, id)) = splits.pop() {
            // The clock is read after each operation that did work.
            if worked && clock.now() >= deadline {
                stats.out_of_time = true;
                stats.max_error_px = stats.max_error_px.max(error);
                // What there was no time for is still wanted: keep its data coming.
                want(dag, source, id, error);
                for Key(error, id) in splits.drain() {
                    if dag.node(id).is_some_and(|n| n.refined.is_none()) {
                        want(dag, source, id, error);
                    }
                }
                break;
            }
            let refined_before = stats.refined;
            if dag.node(id).is_none_or(|n| n.refined.is_some()) {
                continue;
            }
            // With a cut budget, a split whose 4-8 closure does not fit is refused before
            // any of it is refined: a part of the chain (a parent that does not want
            // refining itself) would be coarsened again by the merge queue. The rest of
            // the queue (smaller errors) waits too: room is made below, and they come
            // up next frame.
            if let Some(max) = self.config.max_cut_halves
                && cut_over(dag, Some(max), 2 * unrefined_closure(dag, id, max))
            {
                stats.over_budget = true;
                stats.max_error_px = stats.max_error_px.max(error);
                blocked = Some(error);
                break;
            }
            let mut newly = Vec::new();
            let mut chain = HashSet::new();
            let outcome = self.refine_with_parents(
                dag, id, error, source, &mut stats, 0, &projector, &mut newly, &mut chain,
            )?;
            // Parents refined for a split that, once they were, no longer wanted it are not
            // needed by it: the merge queue may coarsen them in this frame.
            if !matches!(outcome, Outcome::Unwanted) {
                needed.extend(chain);
            }
            // Children of everything refined (the diamond and any parents it needed),
            // complete or not: an incomplete one gets its other parent refined first when
            // it comes up.
            for refined in newly {
                for &child in dag.children(refined).iter() {
                    if dag.node(child).is_some_and(|n| n.refined.is_none())
                        && dag.refiner().is_refinable(child)
                    {
                        let a = projector.appearance(dag, child);
                        if projector.wants_split(&a) {
                            splits.push(Key(a.error_px, child));
                        }
                    }
                }
            }
            match outcome {
                Outcome::Done => {}
                Outcome::Pending => {
                    waiting += 1;
                    stats.max_error_px = stats.max_error_px.max(error);
                }
                Outcome::Impossible | Outcome::Unwanted => {}
            }
            worked = stats.refined > refined_before;
        }

        let splits_done = !stats.out_of_time;
        // Merge queue: refined diamonds with unrefined children that are now too fine or
        // off-screen, least urgent first.
        if !stats.out_of_time {
            // Only refined diamonds whose children are unrefined can merge; coarsening
            // one may free its parents, which join the queue.
            let mut merges: BinaryHeap<std::cmp::Reverse<Key<I>>> = dag
                .nodes()
                // Coarsenable first: it is cheap, and most refined diamonds of a deep
                // DAG have refined children.
                .filter(|n| n.refined.is_some() && dag.is_coarsenable(n.id))
                .filter_map(|n| {
                    let a = projector.appearance(dag, n.id);
                    projector
                        .allows_merge(&a)
                        .then_some(std::cmp::Reverse(Key(a.error_px, n.id)))
                })
                .collect();
            while let Some(std::cmp::Reverse(Key(_, id))) = merges.pop() {
                if !dag.is_coarsenable(id) {
                    continue;
                }
                if needed.contains(&id) || !projector.children_calm(dag, id) {
                    continue;
                }
                let Some(freed) = coarsen_in_time(dag, id, clock, deadline, &mut stats)? else {
                    break;
                };
                for parent in freed {
                    let a = projector.appearance(dag, parent);
                    if projector.allows_merge(&a) {
                        merges.push(std::cmp::Reverse(Key(a.error_px, parent)));
                    }
                }
            }
        }

        let over = |dag: &Dag<R>| {
            self.config
                .max_dag_bytes
                .is_some_and(|max| dag.memory_bytes() > max)
                || cut_over(dag, self.config.max_cut_halves, 0)
        };
        if let (Some(blocked), Some(max)) = (blocked, self.config.max_cut_halves)
            && !stats.out_of_time
        {
            // Room for the refused split: coarsen what matters less than it (off-screen
            // diamonds, then visible ones under half its error, so a swap is always a
            // clear gain and the cut settles), to a sixteenth below the budget (at least
            // 64 halves): room for the split with the parents the 4-8 rule asks for, or
            // the parents refined for it would be coarsened again, frame after frame.
            // Only diamonds whose children are calm: a parent refined for a wanted
            // child (off-screen while the child is not) would be refined again next
            // frame, and the cut would churn instead of settling.
            let target = max.saturating_sub((max / 16).max(64).min(max / 2));
            let room = |dag: &Dag<R>| dag.cut_len() > target;
            self.evict(
                dag,
                &projector,
                &room,
                Some((blocked / 2.0, &needed)),
                clock,
                deadline,
                &mut stats,
            )?;
        }
        if over(dag) && !stats.out_of_time {
            stats.over_budget = true;
            self.evict(dag, &projector, &over, None, clock, deadline, &mut stats)?;
        }

        stats.pending = waiting;
        stats.dag_bytes = dag.memory_bytes();
        stats.dag_nodes = dag.len();
        stats.cut_halves = dag.cut_len();
        stats.converged = !stats.out_of_time && waiting == 0;
        stats.full_quality = splits_done && waiting == 0 && !stats.over_budget;
        let mut seen = projector.seen.into_inner();
        if seen.len() > 2 * dag.len() + 1024 {
            seen.retain(|id, _| dag.node(*id).is_some());
        }
        self.seen = Some((under, seen));
        stats.elapsed = clock.now().saturating_sub(start);
        self.quiet =
            (stats.converged && stats.refined == 0 && stats.coarsened == 0).then_some(Quiet {
                under,
                changes: dag.changes(),
                stats,
            });
        Ok(stats)
    }

    /// Coarsens until `over` is false: off-screen diamonds first, then the smallest
    /// projected errors. To make room (`below` is `Some((error, needed))`): only diamonds
    /// of smaller error, not needed by a split and whose children are calm. To meet a
    /// budget (`None`): any.
    #[allow(clippy::too_many_arguments)]
    fn evict<R: Domain<Id = I>>(
        &self,
        dag: &mut Dag<R>,
        projector: &Projector<'_, R::World, I>,
        over: &dyn Fn(&Dag<R>) -> bool,
        below: Option<(f64, &HashSet<I>)>,
        clock: &dyn Clock,
        deadline: Duration,
        stats: &mut FrameStats,
    ) -> Result<(), DagError> {
        let rank = |dag: &Dag<R>, id: I| {
            let a = projector.appearance(dag, id);
            // Off-screen diamonds rank below every visible one.
            let e = if a.visible {
                a.error_px
            } else {
                -1.0 / (1.0 + a.error_px)
            };
            std::cmp::Reverse(Key(e, id))
        };
        let mut queue: BinaryHeap<std::cmp::Reverse<Key<I>>> = dag
            .nodes()
            .filter(|n| n.refined.is_some() && dag.is_coarsenable(n.id))
            .map(|n| rank(dag, n.id))
            .collect();
        while over(dag) {
            let Some(std::cmp::Reverse(Key(e, id))) = queue.pop() else {
                break;
            };
            if below.is_some_and(|(b, _)| e >= b) {
                break;
            }
            let spare =
                |needed: &HashSet<I>| !needed.contains(&id) && projector.children_calm(dag, id);
            if !dag.is_coarsenable(id) || below.is_some_and(|(_, needed)| !spare(needed)) {
                continue;
            }
            let Some(freed) = coarsen_in_time(dag, id, clock, deadline, stats)? else {
                break;
            };
            for parent in freed {
                queue.push(rank(dag, parent));
            }
        }
        Ok(())
    }

    /// Refines `id`, refining its missing parents first.
    #[allow(clippy::too_many_arguments)]
    fn refine_with_parents<R: Domain<Id = I>>(
        &mut self,
        dag: &mut Dag<R>,
        id: I,
        priority: f64,
        source: &mut dyn DetailSource<I>,
        stats: &mut FrameStats,
        depth: usize,
        projector: &Projector<'_, R::World, I>,
        newly: &mut Vec<I>,
        needed: &mut HashSet<I>,
    ) -> Result<Outcome, DagError> {
        if depth > 128 || !dag.refiner().is_refinable(id) {
            return Ok(Outcome::Impossible);
        }
        if depth > 0 {
            needed.insert(id);
        }
        if dag.node(id).is_some_and(|n| n.refined.is_some()) {
            return Ok(Outcome::Done);
        }
        let mut pending = false;
        for parent in dag.parents(id) {
            if !dag.refiner().is_refinable(parent) {
                continue; // outside the raster: that half never exists
            }
            if dag.node(parent).is_none_or(|n| n.refined.is_none()) {
                // A parent comes first: it is coarser, so its error is larger (about
                // sqrt(2) per level).
                match self.refine_with_parents(
                    dag,
                    parent,
                    priority * std::f64::consts::SQRT_2,
                    source,
                    stats,
                    depth + 1,
                    projector,
                    newly,
                    needed,
                )? {
                    Outcome::Done => {}
                    Outcome::Pending => pending = true,
                    Outcome::Impossible | Outcome::Unwanted => return Ok(Outcome::Impossible),
                }
            }
        }
        if pending {
            return Ok(Outcome::Pending);
        }
        if !dag.is_refinable(id) {
            return Ok(Outcome::Impossible);
        }
        // With its parents refined, its side information is known: a diamond refined for
        // its own sake (not as a parent) is refined only if it still wants to be, so the
        // cut does not depend on the order in which its parents arrived.
        if depth == 0 && !projector.wants_split(&projector.appearance(dag, id)) {
            return Ok(Outcome::Unwanted);
        }
        if self
            .config
            .max_dag_bytes
            .is_some_and(|max| dag.memory_bytes() + dag.refinement_bytes() > max)
        {
            stats.over_budget = true;
            stats.max_error_px = stats.max_error_px.max(priority);
            return Ok(Outcome::Impossible);
        }
        // Both layers are asked at once, so both requests go out in the same frame.
        let details = if dag.refiner().is_coded(id) {
            source.details(id, priority)
        } else {
            Arrival::Ready(None)
        };
        let colour = match dag.colour_blob_id(id) {
            Some(c) => source.colour(id, c, priority),
            None => Arrival::Ready(None),
        };
        match (details, colour) {
            (Arrival::Ready(details), Arrival::Ready(colour)) => {
                dag.refine_layers(id, details.as_deref(), colour.as_deref())?;
                stats.refined += 1;
                newly.push(id);
                Ok(Outcome::Done)
            }
            _ => Ok(Outcome::Pending),
        }
    }
}

/// How many diamonds refining `id` takes: itself and the unrefined ancestors the 4-8 rule
/// asks for (each adds at most 2 halves to the cut: it replaces each present half by two
/// children's halves). Counting stops past `limit`.
fn unrefined_closure<R: Domain>(dag: &Dag<R>, id: R::Id, limit: usize) -> usize {
    let mut seen = HashSet::new();
    let mut stack = vec![id];
    while let Some(d) = stack.pop() {
        if seen.len() > limit {
            break;
        }
        if !dag.refiner().is_refinable(d)
            || dag.node(d).is_some_and(|n| n.refined.is_some())
            || !seen.insert(d)
        {
            continue;
        }
        stack.extend(dag.parents(d));
    }
    seen.len()
}

/// Records that `id`'s data is wanted in every layer that fetches it.
fn want<R: Domain>(dag: &Dag<R>, source: &mut dyn DetailSource<R::Id>, id: R::Id, priority: f64) {
    if dag.refiner().is_coded(id) {
        source.want(id, priority);
    }
    if let Some(c) = dag.colour_blob_id(id) {
        source.want_colour(id, c, priority);
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::Metric;

    #[test]
    fn metrics_are_named_alike_in_json_on_the_command_line_and_in_figures() {
        for m in Metric::ALL {
            let json = serde_json::to_string(&m).unwrap();
            assert_eq!(json, format!("\"{}\"", m.name()));
            assert_eq!(serde_json::from_str::<Metric>(&json).unwrap(), m);
            assert_eq!(m.name().parse::<Metric>().unwrap(), m);
            assert_eq!(m.to_string(), m.name());
        }
        let err = serde_json::from_str::<Metric>("\"texel\"").unwrap_err();
        assert!(err.to_string().contains("unknown metric"), "{err}");
    }
}
